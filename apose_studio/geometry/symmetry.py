"""Rotational symmetries of a surface, found from its samples: the turns that map a part (or a base
object) onto itself, and the near-symmetries that almost do. A property of the geometry, used by the
estimator (twin poses, starting poses) and available to the renderer and the metrics.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from apose_studio.geometry import se3
from apose_studio.geometry.raycast import body

SYMMETRY_TOLERANCE = 0.005  # a symmetry: mean surface distance after the turn < 0.5 % of the diameter
EXACT_SYMMETRY_MAX_M = 0.001  # an exact symmetry moves no point of the surface more than 1 mm off the surface:
# its twins are physically the same assembly. A turn that moves some feature further (a motor's connector,
# a boss: the mean distance stays tiny, the largest does not) is a near-symmetry, whose twin is a wrong placement
NEAR_SYMMETRY_TOLERANCE = 0.03  # a near-symmetry (a starting pose worth trying): < 3 %


def detect_symmetries(points: np.ndarray, diameter: float, tolerance: float = 0.005,
                      orders=(2, 3, 4, 6, 8, 12), max_count: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Rotations that map a surface (nearly) onto itself: (n, 4, 4) with identity first, and residuals.

    Candidate axes are the principal axes and the frame axes through the centroid; a rotation by
    360/n degrees is kept when the mean distance of the moved surface to the original stays below
    `tolerance` x diameter (0.5 % by default: the fidget casing's 2-fold turn leaves 0.16 mm of 38 mm).
    For each axis the largest passing order is kept (all its multiples join the set).
    """
    rng = np.random.default_rng(0)
    # two independent halves of the samples: moved half B against half A, so that the sampling's own
    # spacing (the distance B has to A with no motion at all) can be subtracted
    tree = cKDTree(points[0::2])
    half = points[1::2]
    pts = half[rng.choice(len(half), size=min(3000, len(half)), replace=False)]
    baseline = float(np.mean(tree.query(pts)[0]))
    c = pts.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((pts - c).T))
    axes = [vecs[:, i] for i in range(3)] + [np.eye(3)[i] for i in range(3)]
    unique = []
    for a in axes:
        if all(abs(np.dot(a, b)) < 0.999 for b in unique):
            unique.append(a / np.linalg.norm(a))
    found: list[tuple[np.ndarray, float]] = []
    for a in unique:
        best = None
        for n in orders:
            R = se3.axis_angle_matrix(a, 2 * np.pi / n)
            T = se3.make_T(R, c - R @ c)
            res = float(np.mean(tree.query(se3.transform_points(T, pts))[0])) - baseline
            if res < tolerance * diameter:
                best = (n, a)
        if best:
            n, a = best
            for k in range(1, n):
                R = se3.axis_angle_matrix(a, 2 * np.pi * k / n)
                T = se3.make_T(R, c - R @ c)
                res = max(0.0, float(np.mean(tree.query(se3.transform_points(T, pts))[0])) - baseline)
                if res < 3 * SYMMETRY_TOLERANCE * diameter:  # a symmetry, or a close twin: exact enough to derive twin poses by
                    T = refine_self_map(T, pts, tree, 0.02 * diameter)
                    res = max(0.0, float(np.mean(tree.query(se3.transform_points(T, pts))[0])) - baseline)
                if all(se3.rotation_angle_deg(T[:3, :3].T @ F[:3, :3]) > 1.0 for F, _ in found):
                    found.append((T, res))
    found.sort(key=lambda x: x[1])
    found = found[: max_count - 1]
    syms = np.stack([np.eye(4)] + [T for T, _ in found])
    return syms, np.array([0.0] + [r for _, r in found])


def surface_offsets(mesh, points: np.ndarray, turns: np.ndarray) -> np.ndarray:
    """(n,) for each turn T (n, 4, 4): the largest distance (metres) of the turned surface samples from
    the mesh's surface itself (exact, by Open3D's distance query: no sampling spacing in it)."""
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    scene = body(mesh).scene
    out = np.zeros(len(turns))
    for i, T in enumerate(turns):
        moved = se3.transform_points(T, points).astype(np.float32)
        out[i] = float(scene.compute_distance(o3d.core.Tensor(moved)).numpy().max()) if len(moved) else 0.0
    return out


def refine_self_map(T: np.ndarray, pts: np.ndarray, tree: cKDTree, max_dist: float, iterations: int = 10) -> np.ndarray:
    """A turn that nearly maps a surface onto itself, refined by point-to-point ICP of the surface
    onto itself. The turn is taken about an axis through the samples' centroid, which an off-centre
    feature (a connector) pulls off the true axis: the twin pose would then sit a millimetre off."""
    for _ in range(iterations):
        moved = se3.transform_points(T, pts)
        d, i = tree.query(moved, distance_upper_bound=max_dist)
        ok = np.isfinite(d)
        if ok.sum() < 10:
            break
        T = se3.fit_rigid(moved[ok], tree.data[i[ok]]) @ T
    return T
