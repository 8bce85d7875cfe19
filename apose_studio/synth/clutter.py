"""Cluttered benches for `apose render --clutter`: the base object off-centre in the image, with
objects of about its height standing against it (touching: no gap for depth to split at) and around
it, as on a real workbench. Pure scene sampling: meshes and poses, metres, world z up (table z = 0)."""

from __future__ import annotations

import math

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from apose_studio.assembly.mesh import sample_surface
from apose_studio.geometry import se3

TOUCH_GAP_M = 0.0005  # a toucher stands this close to the base (surface to surface)

_POOL: dict[tuple[float, float], list[trimesh.Trimesh]] = {}


def clutter_pool(base_diameter: float, base_height: float) -> list[trimesh.Trimesh]:
    """24 boxes, cylinders and capsules of about the base's height (0.5-1.1x), made once per base size."""
    key = (round(base_diameter, 6), round(base_height, 6))
    if key not in _POOL:
        rng = np.random.default_rng(11)
        pool = []
        for k in range(24):
            h = base_height * rng.uniform(0.5, 1.1)
            w = base_diameter * rng.uniform(0.2, 0.4)
            if k % 3 == 0:
                pool.append(trimesh.creation.box((w, w * rng.uniform(0.5, 1.5), h)))
            elif k % 3 == 1:
                pool.append(trimesh.creation.cylinder(radius=w / 2, height=h, sections=32))
            else:
                r = min(w / 2, h / 2 * 0.9)
                pool.append(trimesh.creation.capsule(height=max(h - 2 * r, 1e-3), radius=r, count=[16, 16]))
        if len(_POOL) > 16:
            _POOL.clear()
        _POOL[key] = pool
    return _POOL[key]


def touching_pose(base_tree: cKDTree, centre_xy: np.ndarray, reach: float, mesh: trimesh.Trimesh, yaw: float,
                  angle: float, rng: np.random.Generator, step: float = 0.002) -> np.ndarray | None:
    """The resting pose that puts `mesh` (turned by `yaw`) against the base along direction `angle`
    from its centre, its surface TOUCH_GAP_M from the base's (base_tree holds the base's surface
    points in the world). Walks in from `reach` until the two come within `step`, then bisects.
    None when it never comes near (a direction through a hole in the base)."""
    R = se3.axis_angle_matrix((0, 0, 1), yaw)
    pts = sample_surface(mesh, 1500, rng) @ R.T
    lift = -float((mesh.vertices @ R.T)[:, 2].min())
    d = np.array([math.cos(angle), math.sin(angle)])

    def gap(s: float) -> float:
        xy = centre_xy + s * d
        return float(base_tree.query(pts + [xy[0], xy[1], lift])[0].min())

    s_far = reach
    s = reach
    while s > 0:
        if gap(s) < step:
            break
        s_far, s = s, s - step
    else:
        return None
    lo, hi = s, s_far  # gap(lo) < step <= gap(hi)
    for _ in range(12):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if gap(mid) < TOUCH_GAP_M else (lo, mid)
    xy = centre_xy + hi * d
    return se3.make_T(R, (xy[0], xy[1], lift))


def clutter_around(base_world: trimesh.Trimesh, rng: np.random.Generator, touching: int = 2,
                   around: int = 4) -> tuple[list[tuple[trimesh.Trimesh, np.ndarray]], np.ndarray]:
    """Objects for a cluttered bench around the base (its mesh in the world): `touching` of them against
    it, `around` more close by; and the point the camera should look at, off the base's centre by
    0.2-0.4 of its diameter (the base is off-centre in the image). Returns ([(mesh, T_world_obj)], target)."""
    lo, hi = base_world.bounds
    centre = (lo + hi) / 2
    base_d = float(np.linalg.norm(hi - lo))
    pool = clutter_pool(base_d, float(hi[2] - lo[2]))
    tree = cKDTree(sample_surface(base_world, 6000, rng))
    out: list[tuple[trimesh.Trimesh, np.ndarray]] = []
    discs: list[tuple[np.ndarray, float]] = []
    start = rng.uniform(0, 2 * np.pi)
    for k in range(touching):
        mesh = pool[rng.integers(len(pool))]
        r = float(np.linalg.norm(mesh.extents[:2])) / 2
        angle = start + 2 * np.pi * k / max(touching, 1) + rng.uniform(-0.4, 0.4)
        T = touching_pose(tree, centre[:2], base_d / 2 + 2 * r + 0.01, mesh, rng.uniform(0, 2 * np.pi), angle, rng)
        if T is None or any(np.linalg.norm(T[:2, 3] - c) < r + rc for c, rc in discs):
            continue
        discs.append((T[:2, 3], r))
        out.append((mesh, T))
    for _ in range(around):
        mesh = pool[rng.integers(len(pool))]
        r = float(np.linalg.norm(mesh.extents[:2])) / 2
        for _try in range(50):
            ang, dist = rng.uniform(0, 2 * np.pi), rng.uniform(1.0, 1.5) * (base_d / 2 + r)
            xy = centre[:2] + dist * np.array([math.cos(ang), math.sin(ang)])
            if all(np.linalg.norm(xy - c) > r + rc for c, rc in discs):
                R = se3.axis_angle_matrix((0, 0, 1), rng.uniform(0, 2 * np.pi))
                lift = -float((mesh.vertices @ R.T)[:, 2].min())
                discs.append((xy, r))
                out.append((mesh, se3.make_T(R, (xy[0], xy[1], lift))))
                break
    off = rng.uniform(0.2, 0.4) * base_d
    ang = rng.uniform(0, 2 * np.pi)
    target = centre + off * np.array([math.cos(ang), math.sin(ang), 0.0])
    return out, target
