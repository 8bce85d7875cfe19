"""The base object of a step, prepared once per step: its mesh in the frame of base[0], surface
samples, symmetries, and the per-step caches the searches use (model features, near-surface grid)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from apose_studio.assembly.mesh import diameter, sample_surface
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.nn import NearestTree
from apose_studio.geometry.raycast import body as cast_body
from apose_studio.geometry.raycast import raycast_points
from apose_studio.geometry.symmetry import (
    EXACT_SYMMETRY_MAX_M,
    NEAR_SYMMETRY_TOLERANCE,
    SYMMETRY_TOLERANCE,
    detect_symmetries,
    surface_offsets,
)
from apose_studio.params import Params
from apose_studio.registration.side_by_side import check as check_wanted
from apose_studio.registration.stages import cloud, normals_fpfh

RAYS_KEPT = 8  # the last casts of a base kept (raycast_source): a frame casts ~8, the last one again
_RAYS_LOCK = threading.Lock()


@dataclass(frozen=True, eq=False)
class BaseObject:
    """The base object of a step, prepared once: merged mesh in the frame of base[0] and what derives from it."""

    mesh: object  # trimesh.Trimesh, base frame, metres
    diameter: float
    centre: np.ndarray  # (3,) centre of its bounding box, base frame
    samples: np.ndarray  # (N, 3) surface points, base frame
    sample_normals: np.ndarray  # (N, 3) outward unit normals at the samples
    symmetries: np.ndarray  # (n, 4, 4) T_base_base that map the base onto itself, identity first: exact symmetries,
    # which move no point of its surface more than symmetry.EXACT_SYMMETRY_MAX_M off it (the same assembly)
    symmetry_residuals: np.ndarray  # (n,) the largest distance a surface point moves off the surface, metres
    close_twins: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # the near-symmetries that leave a
    # tiny mean distance (< SYMMETRY_TOLERANCE, a small feature moved): twins that can fool a view that hides the
    # feature, so every result's twins under them are scored (near_symmetries includes them)
    near_symmetries: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # turns that almost fit but
    # are not symmetries (a motor block whose connector alone breaks its 4-fold symmetry): extra starting poses
    region: "Region | None" = None  # where the base has a member that is a region of a larger part (`roi`): what
    # of the target belongs to it; None: the whole base is the object
    _features: dict = field(default_factory=dict, repr=False)  # voxel -> (model cloud, FPFH): per step, not per frame

    def belongs(self, points_world: np.ndarray, T_world_base: np.ndarray, margin: float) -> np.ndarray:
        """(N,) which target points (world) belong to the base at T_world_base: all of them, unless the base is
        a region of a larger part, whose surface runs on past the region by nature (Region)."""
        if self.region is None:
            return np.ones(len(points_world), bool)
        return self.region.contains(se3.transform_points(se3.inv(T_world_base), points_world), margin)

    def model_features(self, voxel: float, p: "Params"):
        key = (round(voxel, 9), p.normal_radius_factor, p.feature_radius_factor)
        if key not in self._features:
            pts, normals = self.outer_surface()
            model = cloud(pts, normals).voxel_down_sample(voxel)
            self._features[key] = (model, normals_fpfh(model, voxel, p, None))
        return self._features[key]

    def near_grid(self, voxel: float, p: "Params") -> "NearGrid":
        """Where the model's outer surface is within 2 voxels, as a grid (the screening's lookup)."""
        key = ("near", round(voxel, 9))
        if key not in self._features:
            self._features[key] = NearGrid.around(np.asarray(self.model_features(voxel, p)[0].points), 2 * voxel)
        return self._features[key]

    def extremes(self) -> np.ndarray:
        """The vertices of the surface samples' convex hull (built once): a rigid motion moves no sample farther
        than it moves the farthest of these (a point's displacement is convex in the point), at a
        hundredth of the cost of moving every sample."""
        if "extremes" not in self._features:
            from scipy.spatial import ConvexHull, QhullError

            try:
                self._features["extremes"] = self.samples[ConvexHull(self.samples).vertices]
            except (QhullError, ValueError):  # flat or too few samples: all of them
                self._features["extremes"] = self.samples
        return self._features["extremes"]

    def samples_tree(self):
        """k-d tree of the surface samples (base frame): a model point's normal is its nearest sample's."""
        if "samples_tree" not in self._features:
            self._features["samples_tree"] = NearestTree(self.samples)
        return self._features["samples_tree"]

    def warm_up(self, p: "Params") -> None:
        """Compute the per-step pieces (model features, flips) now, so per-frame timings are per frame."""
        if p.global_source == "model":
            self.near_grid(p.voxel(self.diameter) * p.global_voxel_factor, p)
            self.flips()
        self.extremes()  # the tracker's

    def flips(self) -> np.ndarray:
        """(4, 4, 4) T_base_base: identity and the half turns about the principal axes through the centre.

        A partial view of a flat or box-like object often matches the model upside down or turned
        round; these are the starting points that undo such a global result.
        """
        if "flips" not in self._features:
            pts = self.samples
            c = pts.mean(axis=0)
            _, vecs = np.linalg.eigh(np.cov((pts - c).T))
            out = [np.eye(4)]
            out += [se3.turn_about(vecs[:, i], np.pi, c) for i in range(3)]
            self._features["flips"] = np.stack(out)
        return self._features["flips"]

    def outer_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """What cameras all around can see: ray-cast from 26 directions (cube corners, edges, faces).

        Drops hidden and internal surfaces, and gives normals that face outwards whatever the mesh's
        triangle winding: the model that a partial view is matched against.
        """
        if "outer" not in self._features:
            cam = CameraIntrinsics(200, 200, 250.0, 250.0, 100.0, 100.0)  # 44 deg field of view
            dirs = [np.array([x, y, z], float) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if x or y or z]
            pts, nrm = [], []
            for d in dirs:
                eye = self.centre + 1.5 * self.diameter * d / np.linalg.norm(d)
                p_, n_ = raycast_points(self.mesh, np.eye(4), se3.look_at(eye, self.centre), cam)
                pts.append(p_)
                nrm.append(n_)
            self._features["outer"] = (np.concatenate(pts), np.concatenate(nrm))
        return self._features["outer"]


@dataclass(frozen=True)
class Region:
    """The extent of a base with a region member (a part with `roi`: a rocker-arm seat of an engine head): each
    member's roi, or for a whole member its box, with T_member_base. A target point belongs to the base where it
    lies in one of them (within a margin); the rest of the larger part is not evidence for or against the pose."""

    boxes: tuple  # ((Roi, T_member_base), ...)
    body: object = None  # the base's members whole (trimesh, base frame): the larger part the region belongs to, whose
    # rest the depth must not see past at a region's pose (pipeline.judge: `body_past`)
    twins: tuple = ()  # ((name, S), ...): the other regions of the same part alike to this one (rocker-arm seats of
    # one head), S: T_base_base moving this region onto that one; only the rest of the part tells them apart
    plain: bool = False  # the region's own surface cannot pin a pose (a flat patch, a cylinder's side: plainness);
    # no view of it can, so its results are never confident

    def contains(self, points_base: np.ndarray, margin: float) -> np.ndarray:
        out = np.zeros(len(points_base), bool)
        for roi, T_member_base in self.boxes:
            grown = replace(roi, size=tuple(v + 2 * margin for v in roi.size)) if roi.kind == "box" \
                else replace(roi, radius=roi.radius + margin)
            out |= grown.contains(se3.transform_points(T_member_base, points_base))
        return out


PLAIN_SHARE = 0.005  # plainness: below this share per surface point in the least constrained motion, a region is plain.
# The engine head: a seat 0.017, a seat's top above its deck 0.044, a sphere on a seat 0.022, a flat patch of the
# deck 0.000, the deck with its rail 0.002, a post alone 0.0002


def plainness(mesh, n: int = 5000) -> float:
    """How well a surface's own points pin a rigid pose: the least eigenvalue of the point-to-plane information
    matrix of n surface samples with their normals (turns taken at the surface's rim), per point. 0 for a plane
    (it slides along itself) or a cylinder's side (it turns about its axis)."""
    pts, face = sample_surface(mesh, n, 0, return_faces=True)
    nrm = np.asarray(mesh.face_normals)[face]
    r = max(float(np.linalg.norm(mesh.extents)) / 2, 1e-9)
    J = np.hstack([np.cross(pts - pts.mean(axis=0), nrm) / r, nrm])
    return max(float(np.linalg.eigvalsh(J.T @ J)[0]), 0.0) / len(pts)


@dataclass(frozen=True)
class NearGrid:
    """Points within `radius` of a cloud, as a boolean voxel grid: a lookup per query point instead of a
    k-d tree search (screening 36 poses x 500 points takes a fraction of a millisecond). Cells are
    radius/4 wide (wider where that would take more than MAX_CELLS: a fine voxel set by hand on a big
    part, where a cell counts as near when any point of it may be) and hold whether their centre is
    within radius of the cloud, so a query is right to within a cell's half diagonal (0.22 x radius)."""

    MAX_CELLS = 2_000_000

    origin: np.ndarray  # (3,) corner of cell (0, 0, 0)
    cell: float
    occupied: np.ndarray  # (nx, ny, nz) bool

    @classmethod
    def around(cls, points: np.ndarray, radius: float) -> "NearGrid":
        extent = points.max(axis=0) - points.min(axis=0) + 2 * radius
        cell = max(radius / 4, float(np.prod(extent) / cls.MAX_CELLS) ** (1 / 3))
        origin = points.min(axis=0) - radius - cell
        shape = np.ceil((points.max(axis=0) + radius + cell - origin) / cell).astype(int)
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
        reach = radius + (cell - radius / 4) * np.sqrt(3) / 2  # wider cells err on the near side
        d = NearestTree(points).query(origin + (idx + 0.5) * cell, distance_upper_bound=reach)[0]
        return cls(origin, cell, (d < reach).reshape(shape))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) whether each point lies within the radius of the cloud."""
        q = (points - self.origin) / self.cell
        n0, n1, n2 = self.occupied.shape
        q0, q1, q2 = q[:, 0], q[:, 1], q[:, 2]  # per axis, not an (N, 3) test reduced along its rows: half the time
        inside = (q0 >= 0) & (q0 < n0) & (q1 >= 0) & (q1 < n1) & (q2 >= 0) & (q2 < n2)
        i = q.astype(np.intp)  # truncation: the floor wherever q >= 0, which is wherever the answer is looked up
        flat = (i[:, 0] * n1 + i[:, 1]) * n2 + i[:, 2]
        return np.take(self.occupied.reshape(-1), flat, mode="clip") & inside


def prepare_base(mesh, n_samples: int = 20000, seed: int = 0, detect: bool = True, region: Region | None = None) -> BaseObject:
    pts, face = sample_surface(mesh, n_samples, seed, return_faces=True)
    normals = np.asarray(mesh.face_normals)[face]
    d = diameter(mesh.vertices)
    lo, hi = mesh.bounds
    if not detect:
        return BaseObject(mesh, d, (lo + hi) / 2, pts, normals, np.eye(4)[None], np.zeros(1), region=region)
    turns, mean = detect_symmetries(pts, d, tolerance=NEAR_SYMMETRY_TOLERANCE)
    offsets = np.zeros(len(turns))
    close = mean < SYMMETRY_TOLERANCE * d  # only these can be exact: the largest offset decides
    close[0] = False
    offsets[close] = surface_offsets(mesh, pts, turns[close])
    exact = close & (offsets < EXACT_SYMMETRY_MAX_M)
    exact[0] = True
    return BaseObject(mesh, d, (lo + hi) / 2, pts, normals, turns[exact], offsets[exact], turns[close & ~exact],
                      turns[~exact], region=region)


def place_source(base: BaseObject, target_centre: np.ndarray, R_world_base: np.ndarray | None = None) -> np.ndarray:
    """TFORM: T_world_source that puts the base's box centre on the target's centre, orientation kept;
    (n, 4, 4) for (n, 3, 3) orientations."""
    R = np.eye(3) if R_world_base is None else np.asarray(R_world_base)
    T = np.tile(np.eye(4), R.shape[:-2] + (1, 1))
    T[..., :3, :3], T[..., :3, 3] = R, target_centre - R @ base.centre
    return T


NEAREST_M = 0.04  # raycast_source: a pose that puts the camera within this of the base's box sees nothing (RGB-D
# cameras measure from 7 cm (RealSense D405) to 50 cm (Kinect v1) on): a RANSAC start with the base's bottom face through
# the camera cast every ray of a 1280 x 960 capture onto it, 1.2 million points, 30 s of an estimate


def raycast_source(base: BaseObject, T_world_source: np.ndarray, T_world_camera: np.ndarray,
                   cam: CameraIntrinsics, look_at: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """RCAST: the base mesh at T_world_source seen by a pinhole camera at the real camera's position.

    With `look_at`, the virtual camera turns to look at that point (the paper's virtual camera looks
    at the target's centre); otherwise it is the real camera. Returns world points and normals.
    """
    check_wanted()  # a reading computed ahead and no longer wanted stops here (side_by_side)
    T_cam = T_world_camera if look_at is None else se3.look_at(T_world_camera[:3, 3], look_at)
    key = (np.asarray(T_world_source, float).tobytes(), np.asarray(T_cam, float).tobytes(), cam)
    with _RAYS_LOCK:
        rays = base._features.setdefault("rays", OrderedDict())
        hit = rays.get(key)
    if hit is None:  # else the same cast again (the judge's at the chosen pose, then the mask cut there): ~4 ms
        corners = cast_body(base.mesh).corners  # (its box's lowest corner first, its highest last)
        eye = se3.transform_points(se3.inv(T_world_source), T_cam[:3, 3][None])[0]
        if np.all(eye > corners[0] - NEAREST_M) and np.all(eye < corners[-1] + NEAREST_M):  # no depth camera sees
            return np.zeros((0, 3)), np.zeros((0, 3))  # the base from there
        hit = raycast_points(base.mesh, T_world_source, T_cam, cam)
        with _RAYS_LOCK:
            rays[key] = hit
            while len(rays) > RAYS_KEPT:
                rays.popitem(last=False)
    return hit[0].copy(), hit[1].copy()  # copies: a caller may change its arrays
