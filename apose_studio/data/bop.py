"""BOP interoperability: BOP scene folders as input, the BOP19 results CSV out and in.

A BOP scene folder holds scene_camera.json, rgb/ (or gray/), depth/ and, with ground truth,
scene_gt.json (+ mask_visib/). A split folder (e.g. lmo/test) holds scene folders named by number.
Units are BOP's at the edge (mm, row-major R) and metres inside. Facts checked against bop_toolkit:
../shared/docs/BOP_NOTES.md.
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from apose_studio import safeio
from apose_studio.assembly.fileio import atomic_write_text
from apose_studio.data.dataset import (
    DatasetError,
    Frame,
    check_camera_entry,
    check_scene_images,
    gt_entries,
    read_depth,
    read_image,
    read_json,
    read_rgb,
    world_frame,
)
from apose_studio.errors import AposeError
from apose_studio.geometry import se3

CSV_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]


def is_bop_scene(path: Path) -> bool:
    path = Path(path)
    return (path / "scene_camera.json").is_file() and (path / "depth").is_dir()


def scene_folders(split: Path) -> list[Path]:
    """The BOP scene folders of a split folder (or the folder itself when it is one scene)."""
    split = Path(split)
    if is_bop_scene(split):
        return [split]
    return sorted(p for p in split.iterdir() if p.is_dir() and p.name.isdigit() and is_bop_scene(p)) if split.is_dir() else []


def parse_obj_map(items: list[str] | None, parts) -> dict[str, int]:
    """['can=5', ...] -> {part id: BOP obj_id}; DatasetError naming the flag for a bad entry."""
    out: dict[str, int] = {}
    for item in items or []:
        name, _, num = item.partition("=")
        num = num.strip()
        if not (num.isascii() and num.isdigit()) or len(num) > 9:  # a superscript digit passes isdigit alone
            raise DatasetError(f"--obj-map {item}: expected PART=OBJ_ID, e.g. can=5")
        if name not in parts:
            raise DatasetError(f"--obj-map {item}: the assembly has no part {name!r}; parts: {', '.join(parts)}")
        out[name] = int(num)
    return out


class BopScene:
    """One BOP scene folder, read lazily: frames with the camera of each image and, where scene_gt.json
    maps an object to a part (obj_of_part), its pose and visible mask."""

    def __init__(self, folder: str | Path, obj_of_part: dict[str, int] | None = None):
        self.dir = Path(folder)
        if not is_bop_scene(self.dir):
            raise DatasetError(f"{self.dir}: not a BOP scene folder (scene_camera.json and depth/ expected)")
        self.camera = check_scene_images(read_json(self.dir / "scene_camera.json"), str(self.dir / "scene_camera.json"),
                                         "{cam_K, depth_scale}")
        gt = self.dir / "scene_gt.json"
        self.gt = check_scene_images(read_json(gt), str(gt), "[{obj_id, cam_R_m2c, cam_t_m2c}]") if gt.exists() else {}
        self.obj_of_part = dict(obj_of_part or {})
        self.scene_id = int(self.dir.name) if self.dir.name.isdigit() else 0

    def image_ids(self) -> list[int]:
        return sorted(int(k) for k in self.camera)

    def images_with(self, obj_id: int) -> int:
        """In how many images scene_gt.json shows obj_id (its entries are checked when a frame is read)."""
        return sum(isinstance(v, list) and any(isinstance(e, dict) and e.get("obj_id") == obj_id for e in v)
                   for v in self.gt.values())

    def obj_ids(self) -> list[int]:
        """The obj_ids scene_gt.json shows, sorted."""
        return sorted({e["obj_id"] for v in self.gt.values() if isinstance(v, list) for e in v
                       if isinstance(e, dict) and isinstance(e.get("obj_id"), int)})

    def check_obj_map(self, obj_of_part: dict[str, int], base: str | None = None, need_base: bool = True,
                      flag: str = "--obj-map") -> None:
        """DatasetError where the truth would silently be missing: `base` (the step's base part) mapped to an
        obj_id that none of the scene's images shows, or (`need_base`) not mapped at all although ids were
        given; without a base, no mapped obj_id in any image. A part not in this scene is fine (a dataset-wide
        map names every object)."""
        if not obj_of_part:
            return
        present = ", ".join(map(str, self.obj_ids())) or "none"
        n = len(self.image_ids())
        if base is None:
            if not any(self.images_with(oid) for oid in obj_of_part.values()):
                items = ", ".join(f"{p}={o}" for p, o in obj_of_part.items())
                raise DatasetError(f"{flag} {items}: none of these obj_ids is in this scene's {n} images (its "
                                   f"scene_gt.json shows obj_ids {present})")
        elif base in obj_of_part:
            oid = obj_of_part[base]
            if not self.images_with(oid):
                raise DatasetError(f"{flag} {base}={oid}: obj_id {oid} is in none of this scene's {n} images (its "
                                   f"scene_gt.json shows obj_ids {present})")
        elif need_base:
            raise DatasetError(f"{flag} names no obj_id for the step's base {base!r}: its ground truth needs "
                               f"{base}=ID (this scene shows obj_ids {present})")

    def _image(self, sub: str, im_id: int) -> Path:
        for ext in (".png", ".jpg", ".tif"):
            p = self.dir / sub / f"{im_id:06d}{ext}"
            if p.exists():
                return p
        return self.dir / sub / f"{im_id:06d}.png"

    def frame(self, im_id: int, view=None) -> Frame:
        """Frame im_id (metres). With a step's view, its ground truth T_world_base / T_world_part when
        scene_gt.json shows base[0] (mapped to an obj_id)."""
        key = str(im_id)
        if key not in self.camera:
            ids = self.image_ids()
            listed = ", ".join(map(str, ids)) if len(ids) <= 8 else f"{len(ids)} from {ids[0]} to {ids[-1]}, not every number"
            raise DatasetError(f"{self.dir}: no image {im_id} in scene_camera.json; its images are {listed}" if ids
                               else f"{self.dir}: scene_camera.json lists no images")
        rgb_path = self._image("rgb", im_id)
        if not rgb_path.exists() and self._image("gray", im_id).exists():
            rgb_path = self._image("gray", im_id)
        rgb = read_rgb(rgb_path)
        h, w = rgb.shape[:2]
        cam, scale, T_world_camera = check_camera_entry(self.camera[key], f"{self.dir / 'scene_camera.json'}: {key}", w, h)
        depth = read_depth(self._image("depth", im_id), scale, f"{self.dir / 'scene_camera.json'}: {key}")
        if depth.shape != (h, w):
            raise DatasetError(f"{self.dir}: image {im_id}: depth is {depth.shape[1]}x{depth.shape[0]} but RGB is {w}x{h}")
        T_world_camera, world = world_frame(T_world_camera, depth, cam, f"in {self.dir / 'scene_camera.json'}: {key}")
        frame = Frame(rgb=rgb, depth=depth, camera=cam, T_world_camera=T_world_camera, im_id=im_id,
                      source=str(rgb_path), step=self.scene_id, world=world)
        part_of = {v: k for k, v in self.obj_of_part.items()}
        for i, (obj_id, T_camera_obj) in enumerate(gt_entries(self.gt, key, str(self.dir / "scene_gt.json"))):
            pid = part_of.get(obj_id)
            if pid is None or pid in frame.poses:
                continue
            frame.poses[pid] = T_world_camera @ T_camera_obj
            mpath = self.dir / "mask_visib" / f"{im_id:06d}_{i:06d}.png"
            if mpath.exists():
                frame.masks[pid] = read_image(mpath, cv2.IMREAD_GRAYSCALE) > 127
        if view is not None:
            frame.part, frame.base, frame.T_base_part = view.part, tuple(view.base), view.T_base_part
            if view.base[0] in frame.poses:
                frame.T_world_base = frame.poses[view.base[0]]
                frame.T_world_part = frame.T_world_base @ view.T_base_part
        return frame


# --------------------------------------------------------------------------------------- results CSV


@dataclass
class BopResult:
    scene_id: int
    im_id: int
    obj_id: int
    score: float
    T_camera_obj: np.ndarray  # metres
    time: float  # seconds for the image (-1: unknown)


def write_results_csv(path: Path, rows: list[BopResult]) -> None:
    """BOP19 results: one line per estimate, R row-major and t in mm, space-separated (atomic write)."""
    lines = [",".join(CSV_HEADER)]
    for r in rows:
        R, t = r.T_camera_obj[:3, :3].reshape(-1), r.T_camera_obj[:3, 3] * 1000.0
        lines.append(f"{r.scene_id},{r.im_id},{r.obj_id},{r.score!r},{' '.join(repr(float(v)) for v in R)},"
                     f"{' '.join(repr(float(v)) for v in t)},{r.time!r}")
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


_WHOLE = re.compile(r"\s*[0-9]{1,9}\s*")  # ASCII digits only: int() also takes "１" and "1_0"
_REAL = re.compile(r"\s*[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?\s*|\s*[+-]?(?:nan|inf)\s*", re.I)


def _whole(text: str) -> int:
    if not _WHOLE.fullmatch(text):
        raise ValueError(text)
    return int(text)


def _real(text: str) -> float:
    if len(text) > 64 or not _REAL.fullmatch(text):  # nan and inf are read, then refused by name
        raise ValueError(text)
    return float(text)


def read_results_csv(path: Path) -> list[BopResult]:
    """A BOP19 results CSV from any method; DatasetError naming the line for a malformed one."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise DatasetError(f"{path}: no such results file")
    try:
        text = safeio.read_text(path, "a BOP19 results file", safeio.LIMITS.csv_bytes)  # a BOM is dropped
    except AposeError as e:
        raise DatasetError(str(e)) from None
    rows = []
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader, None)
        if header is None or [h.strip() for h in header] != CSV_HEADER:
            raise DatasetError(f"{path}: line 1: expected the BOP19 header {','.join(CSV_HEADER)}")
        for rec in reader:
            n = reader.line_num
            if not rec:
                continue
            try:
                scene, im, obj, score, R, t, tm = rec
                R9 = np.array([_real(v) for v in R.split()], float)
                t3 = np.array([_real(v) for v in t.split()], float)
                if R9.shape != (9,) or t3.shape != (3,) or not (np.isfinite(R9).all() and np.isfinite(t3).all()):
                    raise ValueError
                ids = _whole(scene), _whole(im), _whole(obj)
                score_v, time_v = _real(score), _real(tm)
            except ValueError:
                raise DatasetError(f"{path}: line {n}: expected scene_id,im_id,obj_id,score,R (9 numbers),t (3 numbers, "
                                   "mm),time") from None
            if min(ids) < 0:
                raise DatasetError(f"{path}: line {n}: scene_id, im_id and obj_id are whole numbers >= 0, got "
                                   f"{','.join(map(str, ids))}")
            if not math.isfinite(score_v):
                raise DatasetError(f"{path}: line {n}: score is {score}; write a finite number (the highest score "
                                   "per image is the estimate that counts)")
            rows.append(BopResult(*ids, score_v, se3.make_T(R9.reshape(3, 3), t3 / 1000.0), time_v))
    except csv.Error as e:
        raise DatasetError(f"{path}: line {reader.line_num}: not a readable CSV row ({e}); is it a BOP19 results "
                           "file?") from None
    return rows


def best_per_image(rows: list[BopResult], obj_id: int) -> dict[tuple[int, int], BopResult]:
    """The highest-scoring estimate of obj_id per (scene_id, im_id) (BOP's rule for one instance)."""
    out: dict[tuple[int, int], BopResult] = {}
    for r in rows:
        if r.obj_id != obj_id:
            continue
        k = (r.scene_id, r.im_id)
        if k not in out or r.score > out[k].score:  # scores are finite (read_results_csv refuses others)
            out[k] = r
    return out


# --------------------------------------------------------------------------------------- our datasets


def step_truth(ds, step: int) -> tuple[dict, np.ndarray, int]:
    """(frames of scene_assembly.json, T_base_part, obj_id of base[0]) of a rendered step."""
    sa = ds._scene(step)["scene_assembly"]
    return sa["frames"], np.asarray(sa["T_base_part"], float), ds.obj_ids[sa["base"][0]]


def results_from_eval(ds, doc: dict) -> list[BopResult]:
    """The BOP19 rows of an `apose eval` document: per estimated frame, base[0]'s pose in the camera
    (T_camera_base = T_camera_world T_world_part T_part_base), scene_id = step, score 1 when confident
    else 0.5."""
    rows = []
    for st in doc["steps"]:
        frames, T_base_part, obj_id = step_truth(ds, st["step"])
        for f in st["frames"]:
            if not f["ok"] or f["T_world_part_est"] is None:
                continue
            T_world_camera = np.asarray(frames[str(f["im_id"])]["T_world_camera"], float)
            T = se3.inv(T_world_camera) @ np.asarray(f["T_world_part_est"], float) @ se3.inv(T_base_part)
            rows.append(BopResult(st["step"], f["im_id"], obj_id, 1.0 if f["confident"] else 0.5, T, float(f["time_s"])))
    return rows
