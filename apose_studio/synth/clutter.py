"""Cluttered benches for `apose render --clutter`: the base object off-centre in the image, with
objects of about its height standing against it (touching: no gap for depth to split at) and around
it, as on a real workbench. Pure scene sampling: meshes and poses, metres, world z up (table z = 0)."""

from __future__ import annotations

import math
from dataclasses import dataclass

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

    def gap(s: float, bound: float = np.inf) -> float:  # inf when no pair is closer than `bound`
        xy = centre_xy + s * d
        return float(base_tree.query(pts + [xy[0], xy[1], lift], distance_upper_bound=bound)[0].min())

    s_far = reach
    s = reach
    while s > 0:
        g = gap(s)
        if g < step:
            break
        # the gap closes by at most as much as the object moves (it is 1-Lipschitz in s): the next grid points
        # closer than (g - step) stay >= step away and would not stop the walk; they are stepped over unasked
        for _ in range(1 + max(int((g - 1.001 * step) / step), 0)):
            s_far, s = s, s - step
            if s <= 0:
                break
    else:
        return None
    lo, hi = s, s_far  # gap(lo) < step <= gap(hi)
    for _ in range(12):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if gap(mid, TOUCH_GAP_M) < TOUCH_GAP_M else (lo, mid)
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


# --------------------------------------------------------------------------------- harder benches


@dataclass(frozen=True)
class Pattern:
    """A printed surface: the colour varied by waves of the surface point's position in the object's own
    frame (so it moves with the object), as wood grain, print and labels on real desks. `hard`: two-tone
    print (a label: the second colour where the waves' sum is positive), else a soft grain (the colour
    scaled by 1 +- contrast)."""

    directions: np.ndarray  # (3, 3) unit wave directions
    frequencies: np.ndarray  # (3,) waves per metre
    phases: np.ndarray  # (3,)
    contrast: float
    hard: bool
    second: tuple[float, float, float]

    @classmethod
    def draw(cls, rng: np.random.Generator, size: float, table: bool = False) -> "Pattern":
        """A random pattern for a surface near an object of `size` metres (a table's: a long grain)."""
        d = rng.normal(size=(3, 3))
        if table:
            d[:, 2] = 0.0  # the table's grain lies in its plane
        d /= np.linalg.norm(d, axis=1, keepdims=True) + 1e-12
        wavelengths = size * (rng.uniform(0.6, 2.0, 3) if table else rng.uniform(0.08, 0.5, 3))
        return cls(d, 1.0 / wavelengths, rng.uniform(0, 2 * np.pi, 3), float(rng.uniform(0.15, 0.35)),
                   bool(not table and rng.random() < 0.5), tuple(float(c) for c in rng.uniform(0.05, 0.95, 3)))

    def colours(self, points_obj: np.ndarray, colour) -> np.ndarray:
        """(N, 3) colours of surface points (object frame) printed with this pattern on `colour`."""
        waves = np.sin(2 * np.pi * (points_obj @ self.directions.T) * self.frequencies + self.phases).sum(axis=1)
        base = np.asarray(colour, np.float32)[None, :]
        if self.hard:
            return np.where((waves > 0.6)[:, None], np.asarray(self.second, np.float32)[None, :], base)
        return base * (1.0 + self.contrast * np.clip(waves / 2.0, -1, 1))[:, None].astype(np.float32)


_FLAT: dict[tuple[float, float], list[trimesh.Trimesh]] = {}


def flat_pool(base_diameter: float, base_height: float) -> list[trimesh.Trimesh]:
    """12 flat objects for the top of a base (tins, books, a phone): 12-30 % of its height, 25-55 % of its
    diameter across, made once per base size."""
    key = (round(base_diameter, 6), round(base_height, 6))
    if key not in _FLAT:
        rng = np.random.default_rng(13)
        pool = []
        for k in range(12):
            h = max(base_height * rng.uniform(0.12, 0.3), 0.004)
            w = base_diameter * rng.uniform(0.25, 0.55)
            pool.append(trimesh.creation.box((w, w * rng.uniform(0.5, 1.0), h)) if k % 2 == 0 else
                        trimesh.creation.cylinder(radius=w / 2, height=h, sections=40))
        if len(_FLAT) > 16:
            _FLAT.clear()
        _FLAT[key] = pool
    return _FLAT[key]


def _heights(mesh_world: trimesh.Trimesh, xy: np.ndarray) -> np.ndarray:
    """The highest surface of a mesh (world, z up) above each (x, y): NaN where a ray from above misses it."""
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh_world.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh_world.faces, np.uint32)))
    top = float(mesh_world.bounds[1][2]) + 1.0
    rays = np.zeros((len(xy), 6), np.float32)
    rays[:, :2], rays[:, 2], rays[:, 5] = xy, top, -1.0
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(t), top - t, np.nan)


def stack_on(base_world: trimesh.Trimesh, rng: np.random.Generator) -> tuple[trimesh.Trimesh, np.ndarray] | None:
    """A flat object lying on top of the base (a tin on a box): on the base's highest region, resting on the
    highest points under its footprint. None when the base has no top to put it on."""
    lo, hi = base_world.bounds
    height = float(hi[2] - lo[2])
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 24), np.linspace(lo[1], hi[1], 24))
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    z = _heights(base_world, grid)
    if not np.isfinite(z).any():
        return None
    top = grid[np.nan_to_num(z, nan=-np.inf) >= hi[2] - 0.2 * height]
    centre = top.mean(axis=0)
    near = top[np.argsort(np.linalg.norm(top - centre, axis=1))[:max(1, len(top) // 3)]]  # the top's inner third
    xy = near[rng.integers(len(near))]
    pool = flat_pool(float(np.linalg.norm(hi - lo)), height)
    mesh = pool[rng.integers(len(pool))]
    R = se3.axis_angle_matrix((0, 0, 1), rng.uniform(0, 2 * np.pi))
    foot = sample_surface(mesh, 400, rng) @ R.T
    foot = foot[foot[:, 2] < float((mesh.vertices @ R.T)[:, 2].min()) + 1e-4]  # its underside
    under = _heights(base_world, foot[:, :2] + xy) if len(foot) else np.array([hi[2]])
    rest = float(np.nanmax(under)) if np.isfinite(under).any() else float(hi[2])
    lift = rest - float((mesh.vertices @ R.T)[:, 2].min()) + TOUCH_GAP_M
    return mesh, se3.make_T(R, (xy[0], xy[1], lift))


_SCREENS: dict[tuple[float, float], list[trimesh.Trimesh]] = {}


def screen_pool(base_diameter: float, base_height: float) -> list[trimesh.Trimesh]:
    """8 boxes to stand in front of a base (a binder, a monitor foot, a toolbox): 0.9-1.6 of its diameter
    wide, 1-3 of its height tall, lowest first."""
    key = (round(base_diameter, 6), round(base_height, 6))
    if key not in _SCREENS:
        rng = np.random.default_rng(17)
        if len(_SCREENS) > 16:
            _SCREENS.clear()
        _SCREENS[key] = [trimesh.creation.box((base_diameter * rng.uniform(0.9, 1.6), base_diameter * rng.uniform(0.15, 0.3),
                                               base_height * f)) for f in np.linspace(1.0, 3.0, 8)]
    return _SCREENS[key]


HIDDEN_VISIBLE = (0.2, 0.35)  # `hidden`: the share of the base's silhouette left visible


def hide_base(base: list[tuple[trimesh.Trimesh, np.ndarray]], T_world_camera: np.ndarray, rng: np.random.Generator,
              visible_share) -> tuple[trimesh.Trimesh, np.ndarray, float]:
    """An object standing on the table between the camera and the base ([(mesh, T_world_obj)] of its
    members): the lowest of screen_pool that, squarely in front, hides enough (else the tallest), slid
    sideways until only 20-35 % of the base's silhouette stays visible (a bisection on the sideways
    offset; `visible_share(mesh, T_world_obj)` measures a try). Returns (mesh, T_world_obj, the share
    reached): the rest of the clutter may hide more. A camera looking steeply down sees over any screen
    of sensible height: the share then stays above the goal (the dataset's visib_fract says how much)."""
    verts = np.concatenate([se3.transform_points(T, np.asarray(m.vertices)) for m, T in base])
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    centre = (lo + hi) / 2
    to_cam = T_world_camera[:3, 3] - centre
    c = to_cam[:2] / np.linalg.norm(to_cam[:2]) if np.linalg.norm(to_cam[:2]) > 1e-6 else np.array([1.0, 0.0])
    side = np.array([-c[1], c[0]]) * (1 if rng.random() < 0.5 else -1)
    reach = float(np.max((verts[:, :2] - centre[:2]) @ c))  # how far the base reaches towards the camera
    gap = rng.uniform(0.002, 0.1) * float(np.linalg.norm(hi[:2] - lo[:2]))
    R = np.eye(3)
    R[:2, :2] = np.column_stack([[-c[1], c[0]], c])  # the screen's width across the line of sight
    target = rng.uniform(*HIDDEN_VISIBLE)

    def pose(mesh: trimesh.Trimesh, offset: float) -> np.ndarray:
        xy = centre[:2] + (reach + mesh.extents[1] / 2 + gap) * c + offset * side
        return se3.make_T(R, (xy[0], xy[1], -float(mesh.bounds[0][2])))

    for mesh in screen_pool(float(np.linalg.norm(hi - lo)), float(hi[2] - lo[2])):
        share0 = visible_share(mesh, pose(mesh, 0.0))
        if share0 <= target:
            break
    lo_off, hi_off = 0.0, float(reach + mesh.extents[0])  # fully in front ... fully beside
    best = (abs(share0 - target), lo_off, share0)
    for _ in range(10):
        mid = (lo_off + hi_off) / 2
        share = visible_share(mesh, pose(mesh, mid))
        best = min(best, (abs(share - target), mid, share))
        lo_off, hi_off = (mid, hi_off) if share < target else (lo_off, mid)
    return mesh, pose(mesh, best[1]), best[2]
