"""Typed settings read from an assembly file: camera intrinsics and registration parameters.

Each is a frozen dataclass with its defaults in one place; `*_from_dict` validates a mapping and
reports every problem with the key path it sits at.
"""

from __future__ import annotations

import dataclasses
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


@dataclass(frozen=True)
class RegistrationConfig:
    """Parameters of the estimator; None means "the preset decides". Lengths in metres."""

    preset: str | None = None
    voxel_size_m: float | None = None
    normal_radius_factor: float | None = None
    feature_radius_factor: float | None = None
    ransac_max_iterations: int | None = None
    ransac_confidence: float | None = None
    ransac_edge_length: float | None = None
    ransac_distance_factor: float | None = None
    icp_threshold_factor: float | None = None
    icp_max_iterations: int | None = None
    seed: int | None = None
    use_orientation_prior: bool | None = None
    upright: bool | None = None
    deterministic: bool | None = None
    max_seconds: float | None = None

    def overrides(self) -> dict:
        """The parameters that were set, by name."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}


PRESETS = ("paper", "default")

# name -> (kind, check, what the check expects)
_REG_RULES: dict[str, tuple[str, object, str]] = {
    "preset": ("str", lambda v: v in PRESETS, f"one of {', '.join(PRESETS)}"),
    "voxel_size_m": ("float", lambda v: 1e-4 <= v <= 0.5, "a length in metres from 0.0001 to 0.5"),
    "normal_radius_factor": ("float", lambda v: 0.5 <= v <= 20, "a number from 0.5 to 20 (x voxel)"),
    "feature_radius_factor": ("float", lambda v: 0.5 <= v <= 50, "a number from 0.5 to 50 (x voxel)"),
    "ransac_max_iterations": ("int", lambda v: 1 <= v <= 1_000_000, "a whole number from 1 to 1000000"),
    "ransac_confidence": ("float", lambda v: 0 < v <= 1, "a number in (0, 1]"),
    "ransac_edge_length": ("float", lambda v: 0 < v < 1, "a number in (0, 1)"),
    "ransac_distance_factor": ("float", lambda v: 0.1 <= v <= 20, "a number from 0.1 to 20 (x voxel)"),
    "icp_threshold_factor": ("float", lambda v: 0.05 <= v <= 20, "a number from 0.05 to 20 (x voxel)"),
    "icp_max_iterations": ("int", lambda v: 1 <= v <= 1000, "a whole number from 1 to 1000"),
    "seed": ("int", lambda v: 0 <= v < 2 ** 32, "a whole number from 0 to 4294967295"),
    "use_orientation_prior": ("bool", lambda v: True, "true or false"),
    "upright": ("bool", lambda v: True, "true or false"),
    "deterministic": ("bool", lambda v: True, "true or false"),
    "max_seconds": ("float", lambda v: 0 <= v <= 3600, "seconds from 0 (no limit) to 3600"),
}


def is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def registration_from_dict(data, file: str, key: str = "registration") -> tuple[RegistrationConfig, list[Problem]]:
    problems: list[Problem] = []
    if data is None:
        return RegistrationConfig(), problems
    if not isinstance(data, dict):
        return RegistrationConfig(), [Problem(file, key, f"expected a mapping of parameter names, got {type(data).__name__}")]
    values = {}
    for name, v in data.items():
        where = f"{key}.{name}"
        if name not in _REG_RULES:
            problems.append(Problem(file, where, f"unknown parameter; known: {', '.join(_REG_RULES)}"))
            continue
        kind, check, expected = _REG_RULES[name]
        ok_type = {"str": isinstance(v, str), "bool": isinstance(v, bool),
                   "int": isinstance(v, int) and not isinstance(v, bool),
                   "float": is_number(v)}[kind]
        if not ok_type or not check(v):
            problems.append(Problem(file, where, f"expected {expected}, got {v!r}"))
            continue
        values[name] = float(v) if kind == "float" else v
    return RegistrationConfig(**values), problems


_CAMERA_KEYS = {"width": "int", "height": "int", "fx": "float", "fy": "float", "cx": "float", "cy": "float"}


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
        elif kind == "int" and not (isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 16384):
            problems.append(Problem(file, f"{key}.{k}", f"expected a positive whole number of pixels, got {v!r}"))
        elif kind == "float" and not (is_number(v) and v > 0):
            problems.append(Problem(file, f"{key}.{k}", f"expected a positive number of pixels, got {v!r}"))
        else:
            values[k] = v if kind == "int" else float(v)
    if problems:
        return None, problems
    return CameraIntrinsics(**values), []


def camera_to_dict(cam: CameraIntrinsics) -> dict:
    return dataclasses.asdict(cam)


def registration_to_dict(reg: RegistrationConfig) -> dict:
    return reg.overrides()


__all__ = ["CameraIntrinsics", "RegistrationConfig", "PRESETS", "registration_from_dict",
           "camera_from_dict", "camera_to_dict", "registration_to_dict", "is_number"]
