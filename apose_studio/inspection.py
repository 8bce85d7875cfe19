"""What the studio's Inspect tab shows, as pure functions: boxes, their 2D projection, clouds per stage.

Colours follow the brief: target cloud red, source cloud blue, estimated box green, ground truth red.
Everything is metres and world frame unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from . import se3
from .config import CameraIntrinsics
from .register import RegistrationResult

RED = (220, 40, 40)
BLUE = (40, 90, 230)
GREEN = (30, 190, 60)
MAGENTA = (220, 60, 220)  # other placements that fit as well as the estimate (an ambiguous result)

# the 12 edges of a box whose corners are ordered as mesh.PartModel.box_corners() (x major, z minor)
BOX_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]])


def box_segments(corners_part: np.ndarray, T_world_part: np.ndarray) -> np.ndarray:
    """(12, 2, 3) world line segments of a part's box (corners in the part frame) at a pose."""
    c = se3.transform_points(T_world_part, corners_part)
    return c[BOX_EDGES]


def project_points(points_world: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) and a mask of the points in front of the camera."""
    pc = se3.transform_points(se3.inv(T_world_camera), points_world)
    front = pc[:, 2] > 1e-6
    u, v = cam.project(np.where(front[:, None], pc, [0.0, 0.0, 1.0]))
    return np.stack([u, v], axis=1), front


def draw_boxes(rgb: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray, corners_part: np.ndarray,
               boxes: list[tuple[np.ndarray, tuple[int, int, int]]], thickness: int = 2) -> np.ndarray:
    """A copy of the RGB image with each (T_world_part, colour) box projected and drawn (OpenCV lines).
    Earlier boxes are drawn thicker, so a later box on top of one (a good estimate on the truth) leaves
    both visible."""
    out = np.ascontiguousarray(rgb.copy())
    for i, (T, colour) in enumerate(boxes):
        width = thickness + 2 * (len(boxes) - 1 - i)
        seg = box_segments(corners_part, T).reshape(-1, 3)
        uv, front = project_points(seg, T_world_camera, cam)
        for k in range(0, len(uv), 2):
            if front[k] and front[k + 1]:
                a = tuple(int(round(v)) for v in uv[k])
                b = tuple(int(round(v)) for v in uv[k + 1])
                cv2.line(out, a, b, colour, width, cv2.LINE_AA)
    return out


def scene_cloud(depth: np.ndarray, rgb: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray,
                max_points: int = 60000) -> tuple[np.ndarray, np.ndarray]:
    """The whole depth image back-projected to world points with their RGB colours, thinned on a pixel
    grid to at most ~max_points (so a browser draws it smoothly)."""
    h, w = depth.shape
    stride = max(1, int(np.ceil(np.sqrt(h * w / max_points))))
    d = depth[::stride, ::stride]
    vs, us = np.nonzero(np.isfinite(d) & (d > 0))
    u, v = us * stride, vs * stride
    pc = cam.backproject(u, v, d[vs, us])
    return se3.transform_points(T_world_camera, pc).astype(np.float32), rgb[v, u]


def pixels_in_box(depth: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray, T_world_box: np.ndarray,
                  size: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose depth point lies inside a box (pose of its centre, full side lengths)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    z = np.where(np.isfinite(depth), depth, 0.0)
    pc = cam.backproject(u, v, z).reshape(-1, 3)
    local = se3.transform_points(se3.inv(T_world_box) @ T_world_camera, pc)
    inside = (np.abs(local) <= np.asarray(size) / 2.0).all(axis=1).reshape(h, w)
    return inside & (z > 0)


def thin(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    if len(points) <= max_points:
        return points
    idx = np.random.default_rng(seed).choice(len(points), max_points, replace=False)
    return points[np.sort(idx)]


@dataclass(frozen=True)
class StageView:
    """One frame of the registration replay."""

    name: str
    source_world: np.ndarray  # (N, 3) the source cloud at this stage's pose
    T_world_base: np.ndarray
    fitness: float
    inlier_rmse: float


def replay(result: RegistrationResult, max_points: int = 20000) -> list[StageView]:
    """The source cloud moved by each stage's T_world_base: initial -> global -> ICP iterations -> final."""
    src = thin(result.source_cloud, max_points)
    return [StageView(s.name, se3.transform_points(s.T_world_base, src).astype(np.float32), s.T_world_base,
                      float(s.fitness), float(s.inlier_rmse)) for s in result.stages]


def metrics_markdown(score, result: RegistrationResult | None) -> str:
    """The metrics panel: errors against ground truth (when known) and the estimator's own numbers."""
    if result is None:
        return "_No estimate for this frame yet: press **Estimate frame**._"
    if not result.ok:
        return f"**Estimation failed:** {result.reason}"
    rows = [("fitness", f"{result.fitness:.3f}"), ("inlier RMSE", f"{result.inlier_rmse * 1000:.2f} mm"),
            ("time", f"{result.seconds * 1000:.0f} ms"), ("coverage", f"{result.coverage:.0%}")]
    if score is not None and score.adi is not None:
        rows = [("ADI", f"{score.adi * 1000:.2f} mm"), ("MSSD", f"{score.mssd * 1000:.2f} mm"),
                ("te", f"{score.te * 1000:.2f} mm"), ("re", f"{score.re_deg:.2f}°")] + rows
    if score is not None and score.mask_iou is not None:
        rows.append(("mask IoU", f"{score.mask_iou:.3f}"))
    flags = []
    if result.ambiguous:
        flags.append(f"ambiguous: {len(result.alternatives) + 1} placements fit the data equally (a (nearly) symmetric "
                     "base, and what tells them apart is not in view); the others are the magenta boxes")
    if not result.confident:
        flags.append("low confidence: the model explains too little of the target")
    table = "| metric | value |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)
    return table + ("\n\n" + "\n\n".join(f"⚠ {f}" for f in flags) if flags else "")


@dataclass
class ResultCache:
    """Estimates per (dataset, step, frame, preset, mask, prior), so revisiting a frame is instant."""

    entries: dict = field(default_factory=dict)

    @staticmethod
    def key(dataset: str, step: int | None, im_id: int, preset: str, mask, prior: bool) -> tuple:
        return (str(dataset), step, int(im_id), preset, mask, bool(prior))

    def get(self, key):
        return self.entries.get(key)

    def put(self, key, value) -> None:
        self.entries[key] = value

    def __len__(self) -> int:
        return len(self.entries)
