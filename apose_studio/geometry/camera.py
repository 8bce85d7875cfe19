"""Pinhole cameras: the intrinsics (OpenCV convention), and an assembly file's `camera` section read
with every problem reported at its key path."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from apose_studio.errors import Problem


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels (OpenCV convention: x right, y down, z forward)."""

    width: int = 640
    height: int = 480
    fx: float = 615.0
    fy: float = 615.0
    cx: float = 320.0
    cy: float = 240.0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def backproject(self, u, v, z) -> np.ndarray:
        """Camera-frame points (..., 3) of pixels (u, v) at depth z (metres), any matching shapes."""
        z = np.asarray(z, dtype=np.float64)
        return np.stack([(u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z], axis=-1)

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (u, v) of camera-frame points (N, 3); NaN for points not in front (z <= 0)."""
        p = np.asarray(points, dtype=np.float64)
        z = np.where(p[:, 2] > 1e-9, p[:, 2], np.nan)
        return self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy

    @staticmethod
    def from_K(K: np.ndarray, width: int, height: int) -> "CameraIntrinsics":
        return CameraIntrinsics(int(width), int(height), float(K[0, 0]), float(K[1, 1]),
                                float(K[0, 2]), float(K[1, 2]))


def is_number(v) -> bool:
    """A number as a file gives it (an int or a float, not a bool, not text) that is finite as a float: so
    `float(v)` is safe after it (an int of 400 digits is not one)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


OTHER_RESOLUTION = 1.4  # a principal point whose image (2 cx by 2 cy) is this many times larger or smaller than
# the image on both axes is that of intrinsics for another resolution (a camera's principal point lies within a few
# per cent of its image's centre: Kinect 640 x 480 at (320, 240), BOP's LM at (325, 242)). A 1280 x 720 calibration on
# 640 x 480 frames: 2 and 1.5. Scaled by less than 1.4 (1.25, 1.33) it cannot be told from a crop off the centre
SAME_RATIO = 0.15  # the two axes' ratios within this share of each other: one factor mends all four numbers
TURNED = 0.1  # a principal point within this share of the centre of the image turned a quarter (and not of the image)


def principal_point_problem(width: int, height: int, cx: float, cy: float) -> str | None:
    """Why intrinsics with principal point (cx, cy) cannot be those of a `width` x `height` image, in words, or None:
    the point outside the image or on its edge; the centre of an image 1.4 times as large (or small) on both axes,
    what intrinsics for another resolution of the camera look like (a 1280 x 960 calibration on 640 x 480 frames);
    the centre of the image turned a quarter (a portrait frame with the landscape calibration). Each puts every
    pixel's ray off: the scene comes out flattened, stretched or skewed, and the pose fits it worse than its noise
    allows or not at all, with no word about the camera."""
    outside = (f"the principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image or on its edge; are the "
               "intrinsics for another resolution, or cx and cy missing?")
    if cx <= 0 or cy <= 0:
        return outside
    rx, ry = 2 * cx / width, 2 * cy / height  # the size of the image the point is the centre of, per image side
    if min(rx, ry) >= OTHER_RESOLUTION or max(rx, ry) <= 1 / OTHER_RESOLUTION:
        said = (f"the principal point ({cx:g}, {cy:g}) is the centre of a {2 * cx:.0f}x{2 * cy:.0f} image, not of this "
                f"{width}x{height} one: the intrinsics look like those for another resolution. Use the calibration for "
                f"{width}x{height}")
        return said + (f", or scale fx, fy, cx and cy by about {width / (2 * cx):.3g}" if abs(rx / ry - 1) < SAME_RATIO
                       else "")
    if cx >= width or cy >= height:
        return outside
    if width != height and abs(2 * cx / height - 1) < TURNED and abs(2 * cy / width - 1) < TURNED \
            and not (abs(rx - 1) < TURNED and abs(ry - 1) < TURNED):
        return (f"the principal point ({cx:g}, {cy:g}) is the centre of a {height}x{width} image, this {width}x{height} "
                "one turned a quarter: was the image rotated after calibration? Turn it back, or use intrinsics for the "
                "turned image (fx and fy swapped, cx and cy the new centre)")
    return None


_CAMERA_KEYS = {"width": "int", "height": "int", "fx": "float", "fy": "float", "cx": "float", "cy": "float"}
FOCAL_PX = (10.0, 1e5)  # focal lengths in pixels a camera can have (Kinect ~525, RealSense D435 ~615)
MAX_SIDE_PX = 16384  # an image's side


def camera_from_dict(data, file: str, key: str = "camera") -> tuple[CameraIntrinsics | None, list[Problem]]:
    if data is None:
        return None, []
    if not isinstance(data, dict):
        return None, [Problem(file, key, f"expected a mapping with {', '.join(_CAMERA_KEYS)}, got {type(data).__name__}")]
    problems = [Problem(file, f"{key}.{k}", f"unknown key; expected one of {', '.join(_CAMERA_KEYS)}")
                for k in data if k not in _CAMERA_KEYS]
    values = {}
    for k, kind in _CAMERA_KEYS.items():
        v = data.get(k)
        if v is None:
            problems.append(Problem(file, f"{key}.{k}", "missing; expected a positive number"))
        elif kind == "int" and not (isinstance(v, int) and not isinstance(v, bool) and 0 < v <= MAX_SIDE_PX):
            problems.append(Problem(file, f"{key}.{k}", f"expected a positive whole number of pixels, got {v!r}"))
        elif kind == "float" and not (is_number(v) and v > 0):
            problems.append(Problem(file, f"{key}.{k}", f"expected a positive number of pixels, got {v!r}"))
        elif k in ("fx", "fy") and not FOCAL_PX[0] <= v <= FOCAL_PX[1]:
            problems.append(Problem(file, f"{key}.{k}", f"{v:g} px; a focal length is {FOCAL_PX[0]:g} to {FOCAL_PX[1]:g} "
                                    "pixels (Kinect ~525, RealSense D435 ~615)"))
        elif k in ("cx", "cy") and v > 2 * MAX_SIDE_PX:
            problems.append(Problem(file, f"{key}.{k}", f"{v:g} px; the principal point lies near the image's centre"))
        else:
            values[k] = v if kind == "int" else float(v)
    if problems:
        return None, problems
    return CameraIntrinsics(**values), []


def camera_to_dict(cam: CameraIntrinsics) -> dict:
    return dataclasses.asdict(cam)


def fov_camera(width: int, height: int, hfov_deg: float) -> CameraIntrinsics:
    """A centred pinhole camera of `width` x `height` pixels with a horizontal field of view in degrees."""
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return CameraIntrinsics(width, height, f, f, width / 2, height / 2)


__all__ = ["FOCAL_PX", "CameraIntrinsics", "camera_from_dict", "camera_to_dict", "fov_camera", "is_number", "mask_bounds",
           "mask_pixels", "valid_mask_pixels"]


def box_region(shape: tuple[int, int], box, margin: int = 0) -> np.ndarray:
    """(H, W) bool: the pixels of the box (x0, y0, x1, y1; right and bottom exclusive), `margin` pixels wider
    per side, clipped to the image (a box off the image gives no pixels)."""
    h, w = shape[:2]
    x0, y0, x1, y1 = (int(v) for v in box)
    out = np.zeros((h, w), bool)
    out[max(y0 - margin, 0):max(min(y1 + margin, h), 0), max(x0 - margin, 0):max(min(x1 + margin, w), 0)] = True
    return out


def mask_bounds(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(v0, v1, u0, u1): the rows and columns the True pixels of an (H, W) bool image span (v1, u1 exclusive), or
    None when none is True."""
    rows = np.flatnonzero(mask.any(axis=1))
    if not len(rows):
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def mask_pixels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vs, us): np.nonzero of an (H, W) bool image, the same pixels in the same (row-major) order, found in the box
    its True pixels span (mask_bounds). A base covers a few per cent of a frame: on a 640 x 480 mask 0.15 ms against
    0.6 ms for the whole image, and the estimate reads its masks a dozen times a frame."""
    return valid_mask_pixels(mask, None)


def valid_mask_pixels(mask: np.ndarray, depth: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(vs, us): mask_pixels of `mask` where `depth` (the same shape; None: everywhere) has a reading (finite, > 0),
    the same as np.nonzero(mask & np.isfinite(depth) & (depth > 0)) with the tests made in the mask's box only."""
    bounds = mask_bounds(mask)
    if bounds is None:
        empty = np.zeros(0, np.intp)
        return empty, empty.copy()
    v0, v1, u0, u1 = bounds
    m = mask[v0:v1, u0:u1]
    if depth is not None:
        d = depth[v0:v1, u0:u1]
        m = m & np.isfinite(d) & (d > 0)
    vs, us = np.nonzero(m)
    return vs + v0, us + u0
