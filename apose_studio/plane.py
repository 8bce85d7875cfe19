"""The plane a scene stands on, fitted by a seeded RANSAC in numpy: the same points give the same plane
in every process (Open3D's segment_plane is multi-threaded and unseeded). Shared by the estimator's
upright search and the depth masks.

PLANE_ITERATIONS draws are enough for a stable fit: on the 50 RealSense-like frames of
tests/test_plane.py the table normal from 20 seeds agrees within 0.25 degrees on every frame
(300 draws of the old fit: up to several degrees, and the wrong plane on some).
"""

from __future__ import annotations

import numpy as np

PLANE_ITERATIONS = 200
SCORE_POINTS = 1000  # hypotheses are scored on this many points; the winner is refitted on all its inliers


def fit_plane(points: np.ndarray, tol: float, seed: int = 0, iterations: int = PLANE_ITERATIONS,
              towards: np.ndarray | None = None, above: np.ndarray | None = None) -> tuple[np.ndarray, float, np.ndarray] | None:
    """(unit normal n, offset d, inlier mask) of the plane n . x + d = 0 with the most points within `tol`.

    `towards`: orient n so that this point (the camera) is on its positive side. `above`: points that
    must mostly lie on that side (an object standing on the plane): planes with most of them behind
    (a wall behind the object, a shelf above it) are not the plane it stands on. None when no plane is
    found (fewer than 3 points, or every draw degenerate)."""
    points = np.asarray(points, float)
    n_pts = len(points)
    if n_pts < 3:
        return None
    rng = np.random.default_rng(seed)
    score = points[rng.choice(n_pts, min(n_pts, SCORE_POINTS), replace=False)]
    tri = score[rng.integers(0, len(score), (iterations, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-12
    if not ok.any():
        return None
    normals, tri = normals[ok] / norm[ok, None], tri[ok]
    offsets = -np.einsum("ij,ij->i", normals, tri[:, 0])
    if towards is not None:
        flip = normals @ towards + offsets < 0
        normals[flip], offsets[flip] = -normals[flip], -offsets[flip]
    counts = (np.abs(score @ normals.T + offsets) < tol).sum(axis=0)
    if above is not None and towards is not None and len(above):
        above = above[:: max(1, len(above) // 500)]
        behind = np.mean((above @ normals.T + offsets) < -tol, axis=0)
        counts = np.where(behind > 0.5, -1, counts)
    best = int(np.argmax(counts))
    if counts[best] < 3:
        return None
    n, d = normals[best], offsets[best]
    for _ in range(2):  # refit on every inlier (least squares), then count again
        inl = np.abs(points @ n + d) < tol
        if inl.sum() < 3:
            break
        c = points[inl].mean(axis=0)
        n_new = np.linalg.svd(points[inl] - c, full_matrices=False)[2][2]
        n, d = (n_new, -float(n_new @ c)) if n_new @ n >= 0 else (-n_new, float(n_new @ c))
    return n, float(d), np.abs(points @ n + d) < tol
