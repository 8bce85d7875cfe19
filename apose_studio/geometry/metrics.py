"""Pose and registration metrics, each a plain function over numpy arrays (metres, 4x4 poses).

Definitions follow the BOP toolkit (bop_toolkit_lib/pose_error.py, https://bop.felk.cvut.cz/challenges/)
and the paper (`docs/METHOD.md` in shared): a pose is T (4x4) mapping model points to the world or
camera frame; `pts` are (N, 3) model points in the part frame; `syms` is the (n, 4, 4) symmetry set.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from apose_studio.geometry.se3 import rotation_angle_deg, transform_points

# BOP's MSSD thresholds for AR: 5 % to 50 % of the object diameter
BOP_MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)


def add(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD: mean distance between corresponding model points under the two poses."""
    return float(np.mean(np.linalg.norm(transform_points(T_est, pts) - transform_points(T_gt, pts), axis=1)))


def adi(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADI (ADD-S): mean over gt-posed points of the distance to the nearest est-posed point."""
    est = transform_points(T_est, pts)
    gt = transform_points(T_gt, pts)
    d, _ = cKDTree(est).query(gt, k=1)
    return float(np.mean(d))


def mssd(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, syms: np.ndarray | None = None) -> float:
    """MSSD: min over symmetries S of max over points x of ||T_gt x - T_est S x||."""
    syms = np.eye(4)[None] if syms is None else syms
    gt = transform_points(T_gt, pts)
    return float(min(np.max(np.linalg.norm(gt - transform_points(T_est @ S, pts), axis=1)) for S in syms))


def project(T_cam_obj: np.ndarray, pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    p = transform_points(T_cam_obj, pts)
    uv = p @ K.T
    return uv[:, :2] / uv[:, 2:3]


def mspd(T_est_cam: np.ndarray, T_gt_cam: np.ndarray, pts: np.ndarray, K: np.ndarray,
         syms: np.ndarray | None = None) -> float:
    """MSPD (pixels): min over symmetries of the max 2D distance of projected points. Poses in the camera frame."""
    syms = np.eye(4)[None] if syms is None else syms
    gt = project(T_gt_cam, pts, K)
    return float(min(np.max(np.linalg.norm(gt - project(T_est_cam @ S, pts, K), axis=1)) for S in syms))


def te(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Translation error (metres)."""
    return float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


def re_deg(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Rotation error (degrees): angle of R_est^T R_gt."""
    return rotation_angle_deg(T_est[:3, :3].T @ T_gt[:3, :3])


def recall(errors, diameter: float, fraction: float = 0.1) -> float:
    """Share of errors below fraction * diameter; NaN (a failed estimate) counts as a miss."""
    e = np.asarray(errors, dtype=float)
    if len(e) == 0:
        return float("nan")
    return float(np.mean(np.nan_to_num(e, nan=np.inf) < fraction * diameter))


def average_recall(errors, diameter: float, thresholds=BOP_MSSD_THRESHOLDS) -> float:
    """BOP-style AR: recall averaged over thresholds (fractions of the diameter)."""
    return float(np.mean([recall(errors, diameter, f) for f in thresholds]))


def quick_tree(points: np.ndarray) -> cKDTree:
    """A k-d tree built for a few queries: unbalanced and uncompacted builds twice as fast."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def fitness_rmse(target: np.ndarray, source: np.ndarray, threshold: float) -> tuple[float, float]:
    """Open3D's definitions: fitness = share of target points with a source point within `threshold`;
    inlier_rmse = RMS distance over those inliers (0 when there are none)."""
    if len(target) == 0 or len(source) == 0:
        return 0.0, 0.0
    d, _ = quick_tree(source).query(target, k=1, distance_upper_bound=threshold)
    inl = np.isfinite(d)
    if not inl.any():
        return 0.0, 0.0
    return float(inl.mean()), float(np.sqrt(np.mean(d[inl] ** 2)))
