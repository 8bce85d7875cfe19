"""Datasets in the BOP layout, extended for assembly steps; and the reader the rest of the code uses.

Layout (one BOP scene per assembly step; BOP's own files keep BOP's units, millimetres):

    DIR/
      dataset_info.json       apose extension: assembly name, part -> obj_id, steps, render settings
      assembly.yaml           the assembly, with meshes pointing at models/ (units: mm)
      camera.json             BOP: default intrinsics and depth_scale
      models/obj_000001.ply   BOP: one mesh per part, in mm; models_info.json (diameter, symmetries)
      test/000001/            BOP scene = assembly step 1
        rgb/000000.jpg (JPEG q95, as BOP's PBR sets)  depth/000000.png (uint16, depth_mm = value * depth_scale)
        mask_visib/000000_000000.png   (image id, index into scene_gt's list): the visible part
        mask/000000_000000.png         the whole silhouette (as if nothing occluded it), as BOP writes
        scene_camera.json  scene_gt.json  scene_gt_info.json
        scene_assembly.json   apose extension, metres: the step's base, part, T_base_part, and per
                              image T_world_base, T_world_part (ground-truth assembly pose),
                              T_world_camera
A frame is listed in the scene's JSON files only after its images are on disk, so an interrupted
render leaves every listed frame readable.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from apose_studio import safeio
from apose_studio.assembly.fileio import atomic_write_bytes, atomic_write_text
from apose_studio.assembly.mesh import PartModel
from apose_studio.assembly.model import Assembly, load_assembly, save_assembly
from apose_studio.data.outdir import claim
from apose_studio.errors import AposeError, DatasetError
from apose_studio.geometry import se3
from apose_studio.geometry.camera import FOCAL_PX, CameraIntrinsics, is_number, principal_point_problem
from apose_studio.geometry.plane import table_frame
from apose_studio.geometry.units import MAX_COORDINATE_M

FORMAT = "apose-bop/1"
SPLIT = "test"
DEPTH_SCALE = 0.1  # BOP: depth in mm = PNG value * depth_scale; 0.1 mm steps up to 6.5 m


def write_json(path: Path, data) -> None:
    atomic_write_text(claim(path), json.dumps(data, indent=1))


def read_json(path: Path, what: str = "a JSON file"):
    """A dataset's JSON file: regular, size-capped, strict (safeio); DatasetError naming the file."""
    if not Path(path).exists() and not Path(path).is_symlink():
        raise DatasetError(f"{path}: missing")
    try:
        return safeio.read_json(path, what)
    except DatasetError:
        raise
    except AposeError as e:
        raise DatasetError(str(e)) from None


def scene_dir(root: Path, step: int) -> Path:
    return Path(root) / SPLIT / f"{step:06d}"


# ----------------------------------------------------------------------------------- frames


@dataclass
class Frame:
    """One RGB-D view, in metres. For a real capture `poses`, `masks` and `step` may be empty."""

    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres; 0 where the sensor gave nothing
    camera: CameraIntrinsics
    T_world_camera: np.ndarray
    masks: dict[str, np.ndarray] = field(default_factory=dict)  # part id -> (H, W) bool visible mask
    poses: dict[str, np.ndarray] = field(default_factory=dict)  # part id -> T_world_part in this view
    step: int | None = None
    part: str | None = None  # the part to place
    base: tuple[str, ...] = ()
    T_base_part: np.ndarray | None = None
    T_world_base: np.ndarray | None = None  # ground truth, pose of base[0]
    T_world_part: np.ndarray | None = None  # ground-truth assembly pose
    im_id: int = 0
    source: str = ""
    placement: int | None = None  # frames of one step with the same placement show the base at the same pose
    world: str = "the dataset's world frame"  # what T_world_camera's world is, in words (a capture's: world_frame)
    depth_scale_known: bool = False  # the depth's scale is the renderer's own (a dataset apose rendered): the
    # depth-scale check (registration.calibration) has nothing to check; False for captures, BOP scenes, cameras

    @property
    def K(self) -> np.ndarray:
        return self.camera.K

    def base_mask(self) -> np.ndarray:
        """Union of the visible masks of the base parts."""
        out = np.zeros(self.depth.shape, bool)
        for p in self.base:
            if p in self.masks:
                out |= self.masks[p]
        return out


def read_image(path: Path, flags: int, what: str = "an image", header: bool = False, depth: bool = False):
    """An image through safeio (regular file; size, pixels, channels, bits and decoded bytes checked
    from the header before decoding; `depth`: one 16-bit channel)."""
    if not path.exists() and not path.is_symlink():
        raise DatasetError(f"{path}: missing")
    try:
        img, head = safeio.read_image(path, flags, what, depth=depth)
    except AposeError as e:
        raise DatasetError(str(e)) from None
    return (img, head) if header else img


def read_rgb(path: Path) -> np.ndarray:
    img = read_image(path, cv2.IMREAD_COLOR, "the colour image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


NO_READING_CODES = (2047, 4095, 8191, 16383, 32767, 65535)  # all ones in 11-16 bits: what some tools write where a
# sensor has no reading (a Kinect v1's raw 2047), instead of 0
NO_READING_SHARE = 0.005  # ... read as "no reading" when the image's largest value is one of them on this share of its
# pixels: a real surface farthest in view at exactly 2047 mm on 1,500 pixels of a 640 x 480 image is not a scene; taken
# as depth, those pixels inside a prompt made the target span 7 times the base and read as "depth_scale 10x too large".
# 65535 on any pixel: a saturated 16-bit value (65 m in mm, 6.5 m in 0.1 mm) is never a reading (1,200 pixels of it in
# a prompt's corners, 0.4 % of the image, turned a confident pose into an ambiguous one 10 mm off)


def read_depth(path: Path, depth_scale_mm: float, scale_from: str = "") -> np.ndarray:
    """uint16 depth PNG -> metres (float32); NaN, negative and missing become 0. `scale_from`: the file that gave
    depth_scale, named when the depth it gives looks wrong."""
    raw, head = read_image(path, cv2.IMREAD_UNCHANGED, "the depth image", header=True, depth=True)
    return depth_metres(raw, head, depth_scale_mm, path, scale_from)


def depth_metres(raw: np.ndarray, head, depth_scale_mm: float, path, scale_from: str = "") -> np.ndarray:
    """A decoded depth image (checked: one uint16 channel, mm-scaled) in metres; `path` names it in errors, and
    `scale_from` the file that gave depth_scale."""
    if raw.ndim != 2:  # the header said one channel (checked before decoding); the decoder disagrees
        raise DatasetError(f"{path}: its {head.format} header says one channel but it decodes to {raw.shape[2]}; "
                           "the file is damaged or crafted: save the depth image again as a 16-bit PNG")
    if raw.dtype != np.uint16:
        raise DatasetError(f"{path}: a {raw.dtype} depth image; expected 16-bit integers (depth in mm = value x "
                           "depth_scale), as RealSense, Kinect and BOP write them")
    top = int(raw.max()) if raw.size else 0
    if top == 65535 or (top in NO_READING_CODES and np.count_nonzero(raw == top) >= NO_READING_SHARE * raw.size):
        raw = np.where(raw == top, np.uint16(0), raw)  # a sensor's "no reading", not a surface 2 or 65 m away
    if not raw.any():
        raise DatasetError(f"{path}: no pixel has a depth reading (all 0{f', or the no-reading code {top}' if top else ''});"
                           " is it the depth image of this frame, aligned to the colour image?")
    valid = raw[::4, ::4][raw[::4, ::4] > 0]  # every 16th pixel: the median of a sanity check, at a 16th of the cost
    if len(valid) and np.median(valid) * depth_scale_mm < 20.0:
        median = f"{path}: the median depth is {np.median(valid) * depth_scale_mm:g} mm"
        if scale_from:
            raise DatasetError(f"{median} with depth_scale {depth_scale_mm:g} from {scale_from}: is depth_scale too small "
                               "(millimetres per depth unit: 1.0 for RealSense and Kinect, 0.1 for BOP's 0.1 mm steps)? "
                               "If it is right, the PNG is metre-scaled: write depth in mm (or 0.1 mm) steps")
        raise DatasetError(f"{median}: the PNG looks metre-scaled (or depth_scale far too small); write depth in mm "
                           "(or 0.1 mm) steps")
    d = raw.astype(np.float32) * np.float32(depth_scale_mm / 1000.0)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


METRES_LIKE_MM = 10.0  # a camera.json's camera closer than this to the world's origin (but not at it) had its cam_t_w2c
# in metres: an outsider's ROS pose (0.29, 0.71 m) was read as 0.7 mm, and the part came out 657 mm under the table
METRES_AT_LEAST_MM = 0.05  # ... nearer than this it is at the origin, written with a float's noise (a camera 5 cm from
# the robot's origin in metres reads 0.05 mm)


def json_text(v) -> str:
    """A JSON value as the file spells it (null, true, "text"), for a message about the file."""
    try:
        return json.dumps(v)
    except (TypeError, ValueError):
        return repr(v)


def _T_from_Rt(R_flat, t_mm) -> np.ndarray:
    return se3.make_T(np.asarray(R_flat, float).reshape(3, 3), np.asarray(t_mm, float).reshape(3) / 1000.0)


def _Rt_from_T(T: np.ndarray) -> tuple[list, list]:
    return T[:3, :3].reshape(-1).tolist(), (T[:3, 3] * 1000.0).tolist()


class Dataset:
    """Read access to a rendered dataset (cheap to open; frames are read on demand)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        info_path = self.root / "dataset_info.json"
        if not info_path.exists() and not info_path.is_symlink():  # a FIFO or device there: named by read_json
            hint = " (a real capture folder? open it with load_capture)" if (self.root / "rgb.png").exists() else ""
            raise DatasetError(f"{self.root}: not an apose dataset, dataset_info.json is missing{hint}; "
                               "make one with `apose render`")
        self.info = read_json(info_path)
        if not isinstance(self.info, dict) or self.info.get("format") != FORMAT:
            got = self.info.get("format") if isinstance(self.info, dict) else type(self.info).__name__
            raise DatasetError(f"{info_path}: format {got!r}, expected {FORMAT!r}")
        ids, steps = self.info.get("obj_ids"), self.info.get("steps_rendered")
        if not (isinstance(ids, dict) and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in ids.values())
                and isinstance(steps, list) and all(isinstance(v, int) and not isinstance(v, bool) and 0 < v < 10 ** 6
                                                    for v in steps)):
            raise DatasetError(f"{info_path}: obj_ids (part -> number) or steps_rendered (step numbers) missing or "
                               "malformed; the manifest was edited or damaged: re-render the dataset")
        self.obj_ids: dict[str, int] = self.info["obj_ids"]
        self.part_of_obj = {v: k for k, v in self.obj_ids.items()}
        self._scenes: dict[int, dict] = {}
        self._assembly: Assembly | None = None

    @property
    def assembly(self) -> Assembly:
        if self._assembly is None:
            self._assembly = load_assembly(self.root / "assembly.yaml")
        return self._assembly

    @property
    def steps(self) -> list[int]:
        return [s for s in self.info["steps_rendered"] if scene_dir(self.root, s).is_dir()]

    @property
    def missing_steps(self) -> list[int]:
        """Steps dataset_info.json lists whose folder is gone."""
        return [s for s in self.info["steps_rendered"] if not scene_dir(self.root, s).is_dir()]

    def _scene(self, step: int) -> dict:
        if step not in self._scenes:
            d = scene_dir(self.root, step)
            if not d.is_dir():
                raise DatasetError(f"{self.root}: step {step} was not rendered; rendered steps: "
                                   f"{', '.join(map(str, self.steps)) or 'none'}")
            sc = {name: read_json(d / f"{name}.json") for name in
                  ("scene_camera", "scene_gt", "scene_gt_info", "scene_assembly")}
            for name in ("scene_camera", "scene_gt", "scene_gt_info"):
                check_scene_images(sc[name], str(d / f"{name}.json"), "...")
            if not isinstance(sc["scene_assembly"], dict) or not isinstance(sc["scene_assembly"].get("frames"), dict):
                raise DatasetError(f"{d / 'scene_assembly.json'}: expected an object with frames; re-render the step")
            self._scenes[step] = sc
        return self._scenes[step]

    def image_ids(self, step: int) -> list[int]:
        """Frames complete on disk (listed in every JSON file of the scene)."""
        sc = self._scene(step)
        ids = set(sc["scene_gt"]) & set(sc["scene_camera"]) & set(sc["scene_assembly"]["frames"])
        return sorted(int(i) for i in ids)

    def placements(self, step: int) -> dict[int, list[int]]:
        """placement id -> its frames (im_ids, ascending): the frames that show the base at one pose
        (`apose render --views-per-scene`; a dataset without placements has one frame per placement)."""
        frames = self._scene(step)["scene_assembly"]["frames"]
        out: dict[int, list[int]] = {}
        for im_id in self.image_ids(step):
            out.setdefault(int(frames[str(im_id)].get("placement", im_id)), []).append(im_id)
        return out

    def frame(self, step: int, im_id: int) -> Frame:
        sc = self._scene(step)
        key = str(im_id)
        if key not in sc["scene_gt"]:
            ids = self.image_ids(step)
            raise DatasetError(f"{self.root}: step {step} has no frame {im_id}; frames are "
                               f"{ids[0]}..{ids[-1]}" if ids else f"{self.root}: step {step} has no frames")
        d = scene_dir(self.root, step)
        rgb_path = d / "rgb" / f"{im_id:06d}.jpg"
        rgb = read_rgb(rgb_path if rgb_path.exists() else rgb_path.with_suffix(".png"))
        camera, depth_scale, T_world_camera = check_camera_entry(
            sc["scene_camera"][key], f"{d / 'scene_camera.json'}: {key}", rgb.shape[1], rgb.shape[0])
        if T_world_camera is None:
            raise DatasetError(f"{d / 'scene_camera.json'}: {key}: missing cam_R_w2c / cam_t_w2c; re-render the step")
        depth = read_depth(d / "depth" / f"{im_id:06d}.png", depth_scale, f"{d / 'scene_camera.json'}: {key}")
        if depth.shape != rgb.shape[:2]:
            raise DatasetError(f"{d}: frame {im_id}: depth is {depth.shape[1]}x{depth.shape[0]} but RGB is "
                               f"{rgb.shape[1]}x{rgb.shape[0]}")
        masks, poses = {}, {}
        for i, (obj_id, T_camera_obj) in enumerate(gt_entries(sc["scene_gt"], key, str(d / "scene_gt.json"))):
            if obj_id not in self.part_of_obj:
                raise DatasetError(f"{d / 'scene_gt.json'}: {key}[{i}]: obj_id {obj_id} is no part of this dataset "
                                   f"(dataset_info.json maps {sorted(self.part_of_obj)})")
            pid = self.part_of_obj[obj_id]
            poses[pid] = T_world_camera @ T_camera_obj
            mpath = d / "mask_visib" / f"{im_id:06d}_{i:06d}.png"
            masks[pid] = read_image(mpath, cv2.IMREAD_GRAYSCALE) > 127
            if masks[pid].shape != depth.shape:
                raise DatasetError(f"{mpath}: mask is {masks[pid].shape[1]}x{masks[pid].shape[0]} but the depth is "
                                   f"{depth.shape[1]}x{depth.shape[0]}")
        asm = sc["scene_assembly"]
        fr = asm["frames"][key]
        return Frame(rgb=rgb, depth=depth, camera=camera,
                     T_world_camera=T_world_camera, masks=masks, poses=poses, step=step, part=asm["part"],
                     base=tuple(asm["base"]), T_base_part=np.asarray(asm["T_base_part"]),
                     T_world_base=np.asarray(fr["T_world_base"]), T_world_part=np.asarray(fr["T_world_part"]),
                     im_id=im_id, source=str(rgb_path), placement=int(fr.get("placement", im_id)),
                     depth_scale_known=True)


def check_scene_images(doc, where: str, entry: str) -> dict:
    """A BOP scene file keyed by image id (scene_camera.json, scene_gt.json, ...): a JSON object whose keys
    are image numbers; DatasetError naming the file and the key otherwise. `entry` says what each value is."""
    if not isinstance(doc, dict):
        raise DatasetError(f"{where}: expected a JSON object keyed by image id ({{\"0\": {entry}, ...}}), "
                           f"got a {type(doc).__name__}")
    for k in doc:
        if not (k.isascii() and k.isdigit()) or len(k) > 9:
            raise DatasetError(f"{where}: key {k!r}: image ids are whole numbers (\"0\", \"1\", ...)"[:240])
    return doc


MAX_OBJECTS_PER_IMAGE = 1000  # scene_gt.json entries of one image (BOP's busiest scenes show a few dozen)


def gt_entries(doc: dict, key: str, where: str) -> list[tuple[int, np.ndarray]]:
    """(obj_id, T_camera_object in metres) per entry of scene_gt.json's image `key`, checked."""
    items = doc.get(key, [])
    if not isinstance(items, list):
        raise DatasetError(f"{where}: {key}: expected a list of objects ({{obj_id, cam_R_m2c, cam_t_m2c}})")
    if len(items) > MAX_OBJECTS_PER_IMAGE:  # each is checked in Python: 400,000 held the studio for over 10 s
        raise DatasetError(f"{where}: {key}: lists {len(items)} objects; a BOP image shows at most a few dozen "
                           f"(over {MAX_OBJECTS_PER_IMAGE} is refused): is this file a scene_gt.json?")
    out = []
    for i, g in enumerate(items):
        at = f"{key}[{i}]"
        if not isinstance(g, dict):
            raise DatasetError(f"{where}: {at}: expected an object with obj_id, cam_R_m2c, cam_t_m2c")
        missing = [k for k in ("obj_id", "cam_R_m2c", "cam_t_m2c") if k not in g]
        if missing:
            raise DatasetError(f"{where}: {at}: missing {', '.join(missing)}")
        obj = g["obj_id"]
        if isinstance(obj, bool) or not isinstance(obj, int) or obj < 0:
            raise DatasetError(f"{where}: {at}.obj_id must be a whole number >= 0, got {obj!r}"[:240])
        out.append((obj, pose_entry(g["cam_R_m2c"], g["cam_t_m2c"], where, f"{at}.cam_R_m2c", f"{at}.cam_t_m2c")))
    return out


def read_capture_camera(path: Path, width: int, height: int) -> tuple[CameraIntrinsics, float, np.ndarray | None]:
    """(intrinsics, depth_scale in mm per unit, T_world_camera or None) from a capture's camera.json, checked.

    Two forms: ours ({fx, fy, cx, cy, depth_scale}) and BOP's ({cam_K: row-major 3x3, depth_scale});
    either may add BOP's cam_R_w2c / cam_t_w2c (mm) for the camera pose (else None: load_capture puts
    the world on the table)."""
    return checked_pose_unit(check_camera_entry(read_json(path), str(path), width, height), str(path))


def checked_pose_unit(entry: tuple, where: str) -> tuple:
    """A capture's (or a request's) camera entry (check_camera_entry's), refused when its camera pose looks given in
    metres: the camera METRES_AT_LEAST_MM to METRES_LIKE_MM from the world's origin (nearer: at it, the camera as the
    world). Not
    for a BOP scene's images, which may lie millimetres apart in a world of its first camera."""
    T_world_camera = entry[2]
    t_mm = float(np.linalg.norm(T_world_camera[:3, 3])) * 1000.0 if T_world_camera is not None else 0.0
    if METRES_AT_LEAST_MM <= t_mm < METRES_LIKE_MM:
        raise DatasetError(f"{where}: cam_t_w2c puts the camera {t_mm:.2g} mm from the world's origin; cam_t_w2c is in "
                           "millimetres (BOP's unit): if these numbers are metres (as ROS gives them), multiply them by "
                           "1000")
    return entry


def check_camera_entry(cam, where: str, width: int, height: int) -> tuple[CameraIntrinsics, float, np.ndarray | None]:
    """One camera entry (a capture's camera.json, or one image of BOP's scene_camera.json), checked;
    errors start with `where`."""
    if not isinstance(cam, dict):
        raise DatasetError(f"{where}: expected a JSON object with fx, fy, cx, cy, depth_scale (or BOP's cam_K)")

    def number(key, value=None):
        v = cam.get(key) if value is None else value
        if not is_number(v):
            raise DatasetError(f"{where}: {key} must be a finite number, got {json_text(v)}"[:200])
        return float(v)

    if "cam_K" in cam:
        K = cam["cam_K"]
        if not (isinstance(K, list) and len(K) == 9):
            nested = isinstance(K, list) and len(K) == 3 and all(isinstance(r, list) and len(r) == 3 for r in K)
            raise DatasetError(f"{where}: cam_K must be 9 numbers (a row-major 3x3 matrix, BOP's form)"
                               + ("; it is 3 rows of 3: write them one after the other in one list" if nested else ""))
        k = [number(f"cam_K[{i}]", K[i]) for i in range(9)]
        fx, skew, cx, _, fy, cy = k[:6]
        if k[3] != 0 or k[6] != 0 or k[7] != 0 or abs(k[8] - 1.0) > 1e-9:
            raise DatasetError(f"{where}: cam_K's last row must be 0 0 1 and K[3] 0 (a pinhole camera matrix), got "
                               f"{k[3]:g}, {k[6]:g} {k[7]:g} {k[8]:g}; is it transposed? (it is the row-major 3x3 matrix)")
        if abs(skew) > 1e-6 * max(abs(fx), 1.0):
            raise DatasetError(f"{where}: cam_K[1] (skew) is {skew:g}; apose's pinhole model has no skew. Rectify the "
                               "images, or set it to 0 if the calibration's skew is negligible")
        for key, value in zip(("fx", "fy", "cx", "cy"), (fx, fy, cx, cy)):  # both forms: two readers, two cameras
            if key in cam and number(key, cam[key]) != value:
                raise DatasetError(f"{where}: {key} is {number(key, cam[key]):g} but cam_K says {value:g}; keep one "
                                   "form of the intrinsics (cam_K, or fx, fy, cx, cy)")
    else:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in cam]
        if missing:
            raise DatasetError(f"{where}: missing {', '.join(missing)}: give the intrinsics in pixels as fx, fy, cx, cy, "
                               "or as BOP's cam_K")
        fx, fy, cx, cy = (number(k) for k in ("fx", "fy", "cx", "cy"))
    if "depth_scale" not in cam:
        raise DatasetError(f"{where}: missing depth_scale (millimetres per depth unit: 1.0 for RealSense and Kinect "
                           "PNGs in mm, 0.1 for apose renders)")
    depth_scale = number("depth_scale")
    if fx <= 0 or fy <= 0:
        raise DatasetError(f"{where}: fx and fy must be positive focal lengths in pixels, got fx={fx:g}, fy={fy:g}")
    if not (FOCAL_PX[0] <= fx <= FOCAL_PX[1] and FOCAL_PX[0] <= fy <= FOCAL_PX[1]):
        raise DatasetError(f"{where}: fx={fx:g}, fy={fy:g} pixels; a camera's focal length in pixels lies between "
                           f"{FOCAL_PX[0]:g} and {FOCAL_PX[1]:g} (Kinect: ~525, RealSense D435: ~615). Are they in "
                           "pixels, for this image size?")
    for key, size in (("width", width), ("height", height)):  # optional; when given, the images' own size
        if key in cam and number(key) != size:
            raise DatasetError(f"{where}: {key} is {number(key):g} but the images are {width}x{height}: the intrinsics "
                               f"are for another resolution; use the calibration for {width}x{height} (or leave out "
                               "width and height)")
    wrong_size = principal_point_problem(width, height, cx, cy)
    if wrong_size is not None:
        raise DatasetError(f"{where}: {wrong_size}")
    if not DEPTH_SCALE_MM[0] <= depth_scale <= DEPTH_SCALE_MM[1]:
        raise DatasetError(f"{where}: depth_scale is {depth_scale:g}; it is millimetres per depth unit, between "
                           f"{DEPTH_SCALE_MM[0]:g} and {DEPTH_SCALE_MM[1]:g} (1.0 for RealSense and Kinect PNGs in mm, "
                           "0.1 for apose renders)")
    T_world_camera = None  # none given: the caller puts the world on the table
    if "cam_R_w2c" in cam or "cam_t_w2c" in cam:
        if "cam_R_w2c" not in cam or "cam_t_w2c" not in cam:
            raise DatasetError(f"{where}: cam_R_w2c (9 numbers) and cam_t_w2c (3 numbers, mm) go together")
        T_world_camera = se3.inv(pose_entry(cam["cam_R_w2c"], cam["cam_t_w2c"], where, "cam_R_w2c", "cam_t_w2c"))
    return CameraIntrinsics(width, height, fx, fy, cx, cy), depth_scale, T_world_camera


DEPTH_SCALE_MM = (1e-3, 100.0)  # mm per depth unit: 0.001 (um) .. 100
MAX_TRANSLATION_MM = MAX_COORDINATE_M * 1000.0  # 10 km: anything further is a unit or format mistake


def pose_entry(R_flat, t_mm, where: str, r_key: str, t_key: str) -> np.ndarray:
    """A BOP pose (row-major R of 9 numbers, t of 3 numbers in mm) as T in metres; DatasetError naming the
    keys for anything else: wrong counts, text, non-finite, not a rotation (det -1 is a mirror)."""
    def numbers(v, n: int, key: str) -> np.ndarray:
        if not isinstance(v, list) or len(v) != n or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise DatasetError(f"{where}: {key} must be a list of {n} numbers, got {v!r}"[:240])
        a = np.asarray(v, float)
        if not np.isfinite(a).all():
            raise DatasetError(f"{where}: {key} holds non-finite numbers")
        return a

    R = numbers(R_flat, 9, r_key).reshape(3, 3)
    t = numbers(t_mm, 3, t_key)
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > 1e-3:
        raise DatasetError(f"{where}: {r_key} is not a rotation (R R^T differs from I by {err:.3g}); write the "
                           "row-major 3x3 rotation matrix")
    if np.linalg.det(R) < 0:
        raise DatasetError(f"{where}: {r_key} is a reflection (determinant -1), not a rotation; a camera or object "
                           "pose has determinant +1 (was one axis flipped?)")
    if np.abs(t).max() > MAX_TRANSLATION_MM:
        raise DatasetError(f"{where}: {t_key} is {np.abs(t).max():g} mm away; translations are in millimetres")
    return se3.make_T(R, t / 1000.0)


CAPTURE_RGB = ("rgb.png", "rgb.jpg")  # a capture's colour image: PNG, or JPEG as BOP and our renders store it


def capture_rgb(folder: Path) -> Path:
    """The capture's colour image: rgb.png, else rgb.jpg when only that is there."""
    for name in CAPTURE_RGB:
        if os.path.lexists(folder / name):
            return folder / name
    return folder / CAPTURE_RGB[0]


def load_capture(folder: str | Path) -> Frame:
    """A real capture: rgb.png (or rgb.jpg), depth.png (uint16) and camera.json (see read_capture_camera).
    Without the camera's pose, the world frame sits on the table plane when one is seen (z = 0 on it, z
    up, origin where the optical axis meets it), else on the camera."""
    folder = Path(folder)
    absent = [n for n, p in (("rgb.png (or rgb.jpg)", capture_rgb(folder)), ("depth.png", folder / "depth.png"),
                             ("camera.json", folder / "camera.json")) if not os.path.lexists(p)]
    if absent and folder.is_dir():
        raise DatasetError(f"{folder}: no {' or '.join(absent)}; a capture folder holds rgb.png (or rgb.jpg), "
                           "depth.png (16-bit depth) and camera.json (the intrinsics and depth_scale): "
                           "docs/CAPTURES_AND_BOP.md")
    rgb = read_rgb(capture_rgb(folder))
    h, w = rgb.shape[:2]
    intr, depth_scale, T_world_camera = read_capture_camera(folder / "camera.json", w, h)
    depth = read_depth(folder / "depth.png", depth_scale, str(folder / "camera.json"))
    if depth.shape != rgb.shape[:2]:
        raise DatasetError(f"{folder}: depth.png is {depth.shape[1]}x{depth.shape[0]} but rgb.png is "
                           f"{rgb.shape[1]}x{rgb.shape[0]}; align depth to colour first")
    T_world_camera, world = world_frame(T_world_camera, depth, intr, f"in {folder / 'camera.json'}")
    return Frame(rgb=rgb, depth=depth, camera=intr, T_world_camera=T_world_camera, source=str(folder), world=world)


def world_frame(T_world_camera: np.ndarray | None, depth: np.ndarray, cam: CameraIntrinsics,
                given: str) -> tuple[np.ndarray, str]:
    """(T_world_camera, what its world is in words) of a capture, a BOP scene's image or an API call: the camera pose
    given (`given` says where: "in .../camera.json", a scene_camera.json's cam_R_w2c and cam_t_w2c), else the table's
    frame when one is seen (z = 0 on it, z up, the origin where the optical axis meets it), else the camera's own."""
    if T_world_camera is not None:
        return np.asarray(T_world_camera, float), f"the world of the camera pose {given}"
    T_table = table_frame(depth, cam)
    if T_table is not None:
        return T_table, "the table's frame (z up from the table, the origin where the optical axis meets it)"
    return np.eye(4), "the camera's frame (no table seen; x right, y down, z forward)"


def write_capture(frame: Frame, folder: str | Path, depth_unit_mm: float = 1.0, info: dict | None = None) -> Path:
    """`frame` as a capture folder that `load_capture` (and `apose estimate`) reads: rgb.png, depth.png (uint16,
    `depth_unit_mm` millimetres per unit: 1.0 is a RealSense's and Kinect's step) and a BOP-style camera.json
    (`cam_K`, `depth_scale`, plus `info`, e.g. the device). The camera's pose is written (BOP's
    cam_R_w2c/cam_t_w2c) unless it is the identity (a camera with no known pose: the reader then finds the
    table). The folder is written beside its place and renamed into it, so it is whole or absent; an existing
    folder is refused, never overwritten."""
    folder = Path(folder)
    if os.path.lexists(folder):
        raise AposeError(f"{folder}: already exists; captures are never overwritten: choose another name")
    if not folder.parent.is_dir():
        raise AposeError(f"{folder.parent}: no such folder")
    if not 0.01 <= depth_unit_mm <= 10.0:
        raise AposeError(f"depth unit {depth_unit_mm:g} mm: expected 0.01..10 mm per 16-bit step")
    raw = np.round(np.nan_to_num(frame.depth, nan=0.0, posinf=0.0, neginf=0.0) * (1000.0 / depth_unit_mm))
    if raw.max(initial=0) > 65535:
        raise AposeError(f"the depth reaches {raw.max() * depth_unit_mm / 1000:.1f} m, past 16 bits of "
                         f"{depth_unit_mm:g} mm steps; write with a larger depth unit")
    cam = {"cam_K": frame.camera.K.reshape(-1).tolist(), "depth_scale": float(depth_unit_mm)}
    if not np.allclose(frame.T_world_camera, np.eye(4)):
        R, t = _Rt_from_T(se3.inv(frame.T_world_camera))
        cam.update(cam_R_w2c=R, cam_t_w2c=t)
    cam.update(info or {})
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".partial", dir=folder.parent))  # a new name: never
    # one the user made
    try:
        for name, img in (("rgb.png", np.ascontiguousarray(frame.rgb[..., ::-1])), ("depth.png", raw.astype(np.uint16))):
            if not cv2.imwrite(str(tmp / name), img):
                raise AposeError(f"{tmp / name}: could not write the image (disk full or no permission?)")
        atomic_write_text(tmp / "camera.json", json.dumps(cam, indent=1))
        if os.path.lexists(folder):  # made meanwhile (another capture, another program): never replaced
            raise AposeError(f"{folder}: already exists; captures are never overwritten: choose another name")
        try:
            os.rename(tmp, folder)
        except OSError as e:  # it appeared between the look and the rename (a folder with files is never replaced)
            raise AposeError(f"{folder}: could not be placed ({e.strerror}); choose another name") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


# ----------------------------------------------------------------------------------- writing


@dataclass
class AnnotatedObject:
    """An object with ground truth in a frame; masks are kept only inside its image window."""

    obj_id: int
    T_world_obj: np.ndarray
    visible: np.ndarray  # (v1-v0, u1-u0) bool
    full: np.ndarray  # same shape: the object as if alone
    window: tuple[int, int, int, int] | None  # (v0, v1, u0, u1); None when off-image

    def paste(self, m: np.ndarray, shape) -> np.ndarray:
        out = np.zeros(shape, np.uint8)
        if self.window is not None:
            v0, v1, u0, u1 = self.window
            out[v0:v1, u0:u1] = m
        return out

    def bbox(self, m: np.ndarray) -> list[int]:
        """BOP bbox [x, y, w, h] of a window mask in image coordinates; [-1]*4 when empty."""
        if self.window is None or not m.any():
            return [-1, -1, -1, -1]
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        v0, _, u0, _ = self.window
        return [int(u0 + cols[0]), int(v0 + rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)]


class SceneWriter:
    """Accumulates one BOP scene (= one assembly step) and keeps its JSON files in step with the images."""

    def __init__(self, root: Path, step: int, view_info: dict):
        self.dir = scene_dir(root, step)
        for sub in ("rgb", "depth", "mask", "mask_visib"):
            (self.dir / sub).mkdir(parents=True, exist_ok=True)
        self.camera, self.gt, self.gt_info = {}, {}, {}
        self.assembly = dict(view_info, frames={})

    def write_images(self, im_id: int, rgb: np.ndarray, depth_m: np.ndarray, objects: list["AnnotatedObject"]) -> np.ndarray:
        """Write one frame's images (thread-safe: touches only this frame's files); returns the uint16 depth."""
        name = f"{im_id:06d}"
        depth_u16 = np.clip(np.round(depth_m * (1000.0 / DEPTH_SCALE)), 0, 65535).astype(np.uint16)
        # JPEG (quality 95) as in BOP's PBR sets: ~10x faster to encode than PNG for a noisy render
        _imwrite(self.dir / "rgb" / f"{name}.jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
        _imwrite(self.dir / "depth" / f"{name}.png", depth_u16)
        for i, o in enumerate(objects):
            _imwrite(self.dir / "mask_visib" / f"{name}_{i:06d}.png", o.paste(o.visible, depth_u16.shape) * np.uint8(255))
            _imwrite(self.dir / "mask" / f"{name}_{i:06d}.png", o.paste(o.full, depth_u16.shape) * np.uint8(255))
        return depth_u16

    def record(self, im_id: int, cam: CameraIntrinsics, T_world_camera: np.ndarray, depth_u16: np.ndarray,
               objects: list["AnnotatedObject"], extra: dict) -> None:
        """List a frame whose images are on disk (BOP scene_camera, scene_gt, scene_gt_info entries)."""
        T_cam_world = se3.inv(T_world_camera)
        R, t = _Rt_from_T(T_cam_world)
        self.camera[str(im_id)] = {"cam_K": cam.K.reshape(-1).tolist(), "depth_scale": DEPTH_SCALE,
                                   "cam_R_w2c": R, "cam_t_w2c": t}
        gts, infos = [], []
        for o in objects:
            R, t = _Rt_from_T(T_cam_world @ o.T_world_obj)
            gts.append({"cam_R_m2c": R, "cam_t_m2c": t, "obj_id": o.obj_id})
            n_all, n_vis = int(o.full.sum()), int(o.visible.sum())
            valid = 0
            if o.window is not None:
                v0, v1, u0, u1 = o.window
                valid = int((o.visible & (depth_u16[v0:v1, u0:u1] > 0)).sum())
            infos.append({"bbox_obj": o.bbox(o.full), "bbox_visib": o.bbox(o.visible), "px_count_all": n_all,
                          "px_count_valid": valid, "px_count_visib": n_vis,
                          "visib_fract": n_vis / n_all if n_all else 0.0})
        self.gt[str(im_id)], self.gt_info[str(im_id)] = gts, infos
        self.assembly["frames"][str(im_id)] = {k: np.asarray(v).tolist() for k, v in extra.items()}

    def flush(self) -> None:
        write_json(self.dir / "scene_camera.json", self.camera)
        write_json(self.dir / "scene_gt.json", self.gt)
        write_json(self.dir / "scene_gt_info.json", self.gt_info)
        write_json(self.dir / "scene_assembly.json", self.assembly)


def _imwrite(path: Path, img: np.ndarray, params=(cv2.IMWRITE_PNG_COMPRESSION, 1)) -> None:
    # fast PNG compression by default: renders are written far more often than they are read

    if not cv2.imwrite(str(claim(path)), img, list(params)):
        raise AposeError(f"{path}: could not write the image (disk full or no permission?)")


# ----------------------------------------------------------------------------------- models (BOP)


def _models_info(model: PartModel) -> dict:
    """BOP models_info entry (millimetres)."""
    lo, hi = model.aabb * 1000.0
    info = {"diameter": model.diameter * 1000.0, "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
            "size_x": hi[0] - lo[0], "size_y": hi[1] - lo[1], "size_z": hi[2] - lo[2]}
    return {k: float(v) for k, v in info.items()}


def _symmetry_info(part, model: PartModel) -> dict:
    if part.symmetry is None:
        return {}
    if part.symmetry.order == 0:
        return {"symmetries_continuous": [{"axis": list(part.symmetry.axis),
                                           "offset": [v * 1000.0 for v in part.symmetry.origin]}]}
    out = []
    for S in model.symmetries[1:]:
        S = S.copy()
        S[:3, 3] *= 1000.0
        out.append(S.reshape(-1).tolist())
    return {"symmetries_discrete": out}


def write_models(asm: Assembly, models: dict[str, PartModel], out) -> tuple[dict[str, int], Assembly]:
    """models/ in BOP form and the assembly rewritten to point at them (units mm)."""
    mdir = Path(out) / "models"
    mdir.mkdir(parents=True, exist_ok=True)
    obj_ids, infos, parts = {}, {}, {}
    for i, (pid, part) in enumerate(asm.parts.items(), start=1):
        obj_ids[pid] = i
        path = mdir / f"obj_{i:06d}.ply"
        mm = models[pid].mesh.copy()
        mm.apply_scale(1000.0)
        atomic_write_bytes(claim(path), mm.export(file_type="ply"))
        infos[str(i)] = {**_models_info(models[pid]), **_symmetry_info(part, models[pid])}
        parts[pid] = replace(part, mesh=path.resolve(), solid=None)  # one PLY per part, whatever it was read from
    write_json(mdir / "models_info.json", infos)
    ds_asm = replace(asm, units="mm", parts=parts)
    save_assembly(ds_asm, claim(Path(out) / "assembly.yaml"))
    return obj_ids, ds_asm
