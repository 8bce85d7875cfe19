"""Assembly pose estimation by point-cloud registration (the paper's Alg. 1), with every step kept.

Stages, each a function: PROJ3D (masked depth -> world cloud), TFORM + RCAST (base mesh moved to the
target's centre and ray-cast from the real camera -> source cloud and T_world_source), PCDREG (global
FPFH + RANSAC, then point-to-plane ICP), and the composition T_world_part = T_world_base @ T_base_part.

Two presets:
- `paper`: the authors' settings (voxel 8 mm, FPFH on the full clouds, RANSAC 100000 / 0.899, ICP
  at 0.4 voxel, source ray-cast at 1280x720, fov 60 deg). It trusts the CAD's orientation: the mesh is
  only translated to the target.
- `default`: ours. Scale-aware voxel from the base diameter, FPFH on down-sampled clouds, RANSAC
  against the whole model (no orientation prior needed), early-terminating, ICP coarse to fine
  against what the camera can see of the model at each candidate pose, and the base object's
  (near-)symmetries turned into candidate poses that are scored and reported.
Frames: T_<to>_<from>, metres.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from . import se3
from .config import CameraIntrinsics, RegistrationConfig
from .errors import AposeError
from .metrics import fitness_rmse, quick_tree

MIN_POINTS = 30  # fewer target points than this cannot constrain 6 DoF with any confidence
TIE_MARGIN = 0.03  # candidates scoring within this of the best explain the data equally well
CONFIDENT_COVERAGE = 0.85  # below this share of target points within 2 voxels of the model, flag a poor fit
SYMMETRY_TOLERANCE = 0.005  # a symmetry: mean surface distance after the turn < 0.5 % of the diameter
NEAR_SYMMETRY_TOLERANCE = 0.03  # a near-symmetry (a starting pose worth trying): < 3 %


# ----------------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class Params:
    preset: str
    voxel_size_m: float | None  # None: base diameter / voxels_per_diameter
    voxels_per_diameter: float
    normal_radius_factor: float
    feature_radius_factor: float
    downsample: bool  # FPFH on voxel-down-sampled clouds (ours) or on the full clouds (paper)
    ransac_max_iterations: int
    ransac_confidence: float
    ransac_edge_length: float
    ransac_distance_factor: float
    mutual_filter: bool
    icp_threshold_factor: float
    icp_max_iterations: int
    global_source: str  # "raycast": the paper's partial view; "model": the whole model (orientation-free)
    source_camera: CameraIntrinsics | None  # None: the real camera
    use_symmetries: bool
    use_orientation_prior: bool  # with no prior from the caller, take the CAD's orientation as one (the paper does)
    seed: int = 0
    global_voxel_factor: float = 1.0  # the global step works at voxel x this (ours: coarser, faster)
    feature_matches: int = 1  # >1 (ours): RANSAC draws from the k nearest model features of each target point
    ransac_retry_iterations: int = 0  # ours: when the fast RANSAC explains < 60 % of the target, retry this long
    use_flips: bool = False  # ours: also start ICP from the global pose turned half round about each principal axis
    max_starts: int = 6  # ours: ICP from this many of the screened starting poses
    retry_below: float = 0.95  # retry RANSAC when the best start explains less than this share of what it shows
    prior_fast_path: bool = False  # ours: with an orientation prior, try ICP from it first and stop if it fits
    polish_voxel_factor: float = 0.0  # ours: > 0, a last ICP of the target (down-sampled at voxel x this) onto the
    # model seen at the chosen pose, with the model's exact normals (the noisy target's normals bias point-to-plane)
    polish_threshold_factor: float = 1.0  # its correspondence distance, x voxel
    upright: bool = False  # ours: where a table is seen, first search the yaw of the base standing on it as modelled
    # (CAD +z along the table's normal); no table, or no confident upright fit: the free search

    def voxel(self, diameter: float) -> float:
        return self.voxel_size_m if self.voxel_size_m else diameter / self.voxels_per_diameter


def _fov_camera(width: int, height: int, hfov_deg: float) -> CameraIntrinsics:
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return CameraIntrinsics(width, height, f, f, width / 2, height / 2)


PRESET_PARAMS = {
    "paper": Params("paper", 0.008, 40.0, 2.0, 3.0, False, 100000, 0.899, 0.09, 1.2, False, 0.4, 30,
                    "raycast", _fov_camera(1280, 720, 60.0), False, True),
    "default": Params("default", None, 50.0, 2.5, 5.0, True, 3000, 0.999, 0.9, 1.5, False, 0.6, 15,
                      "model", None, True, False, global_voxel_factor=2.0, ransac_retry_iterations=30000, use_flips=True,
                      prior_fast_path=True, upright=True, polish_voxel_factor=0.5),
}


def resolve_params(preset: str = "default", config: RegistrationConfig | None = None, **overrides) -> Params:
    """The preset's parameters, overridden by the assembly file's `registration` section and the caller."""
    cfg = config.overrides() if config else {}
    preset = overrides.pop("preset", None) or cfg.pop("preset", None) or preset
    cfg.pop("preset", None)
    if preset not in PRESET_PARAMS:
        raise AposeError(f"unknown preset {preset!r}; choose one of {', '.join(PRESET_PARAMS)}")
    return replace(PRESET_PARAMS[preset], **{**cfg, **overrides})


# ----------------------------------------------------------------------------------- the base object


@dataclass(frozen=True, eq=False)
class BaseObject:
    """The base object of a step, prepared once: merged mesh in the frame of base[0] and what derives from it."""

    mesh: object  # trimesh.Trimesh, base frame, metres
    diameter: float
    centre: np.ndarray  # (3,) centre of its bounding box, base frame
    samples: np.ndarray  # (N, 3) surface points, base frame
    sample_normals: np.ndarray  # (N, 3) outward unit normals at the samples
    symmetries: np.ndarray  # (n, 4, 4) T_base_base that map the base (nearly) onto itself, identity first
    symmetry_residuals: np.ndarray  # (n,) mean surface distance after each symmetry, metres
    near_symmetries: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # turns that almost fit but
    # are not symmetries (a motor block whose connector alone breaks its 4-fold symmetry): extra starting poses
    _features: dict = field(default_factory=dict, repr=False)  # voxel -> (model cloud, FPFH): per step, not per frame

    def model_features(self, voxel: float, p: "Params"):
        key = (round(voxel, 9), p.normal_radius_factor, p.feature_radius_factor)
        if key not in self._features:
            pts, normals = self.outer_surface()
            model = _cloud(pts, normals).voxel_down_sample(voxel)
            self._features[key] = (model, _normals_fpfh(model, voxel, p, None))
        return self._features[key]

    def near_grid(self, voxel: float, p: "Params") -> "NearGrid":
        """Where the model's outer surface is within 2 voxels, as a grid (the screening's lookup)."""
        key = ("near", round(voxel, 9))
        if key not in self._features:
            self._features[key] = NearGrid.around(np.asarray(self.model_features(voxel, p)[0].points), 2 * voxel)
        return self._features[key]

    def warm_up(self, p: "Params") -> None:
        """Compute the per-step pieces (model features, flips) now, so per-frame timings are per frame."""
        if p.global_source == "model":
            self.near_grid(p.voxel(self.diameter) * p.global_voxel_factor, p)
            self.flips()

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
            for i in range(3):
                R = se3.axis_angle_matrix(vecs[:, i], np.pi)
                out.append(se3.make_T(R, c - R @ c))
            self._features["flips"] = np.stack(out)
        return self._features["flips"]

    def outer_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """What cameras all around can see: ray-cast from 26 directions (cube corners, edges, faces).

        Drops hidden and internal surfaces, and gives normals that face outwards whatever the mesh's
        triangle winding: the model that a partial view is matched against.
        """
        if "outer" not in self._features:
            from .render import raycast_points

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
        d = quick_tree(points).query(origin + (idx + 0.5) * cell, distance_upper_bound=reach)[0]
        return cls(origin, cell, (d < reach).reshape(shape))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) whether each point lies within the radius of the cloud."""
        idx = np.floor((points - self.origin) / self.cell).astype(np.int64)
        shape = np.array(self.occupied.shape)
        inside = np.all((idx >= 0) & (idx < shape), axis=-1)
        out = np.zeros(len(points), bool)
        i = idx[inside]
        out[inside] = self.occupied[i[:, 0], i[:, 1], i[:, 2]]
        return out


def prepare_base(mesh, n_samples: int = 20000, seed: int = 0, detect: bool = True) -> BaseObject:
    from .mesh import diameter, sample_surface

    pts, face = sample_surface(mesh, n_samples, seed, return_faces=True)
    normals = np.asarray(mesh.face_normals)[face]
    d = diameter(mesh.vertices)
    lo, hi = mesh.bounds
    if not detect:
        return BaseObject(mesh, d, (lo + hi) / 2, pts, normals, np.eye(4)[None], np.zeros(1))
    near, res = detect_symmetries(pts, d, tolerance=NEAR_SYMMETRY_TOLERANCE)
    strict = res < SYMMETRY_TOLERANCE * d
    return BaseObject(mesh, d, (lo + hi) / 2, pts, normals, near[strict], res[strict], near[~strict])


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
                if res < SYMMETRY_TOLERANCE * diameter:  # a symmetry proper: exact enough to derive twin poses by
                    T = _refine_self_map(T, pts, tree, 0.02 * diameter)
                    res = max(0.0, float(np.mean(tree.query(se3.transform_points(T, pts))[0])) - baseline)
                if all(se3.rotation_angle_deg(T[:3, :3].T @ F[:3, :3]) > 1.0 for F, _ in found):
                    found.append((T, res))
    found.sort(key=lambda x: x[1])
    found = found[: max_count - 1]
    syms = np.stack([np.eye(4)] + [T for T, _ in found])
    return syms, np.array([0.0] + [r for _, r in found])


def _refine_self_map(T: np.ndarray, pts: np.ndarray, tree: cKDTree, max_dist: float, iterations: int = 10) -> np.ndarray:
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


# ----------------------------------------------------------------------------------- results


@dataclass
class Stage:
    """One step of the registration, for the studio's replay."""

    name: str  # "initial", "global", "icp 1", ..., "final"
    T_world_base: np.ndarray
    fitness: float
    inlier_rmse: float


@dataclass
class Candidate:
    T_world_base: np.ndarray
    T_world_part: np.ndarray
    fitness: float  # share of target points explained by the model
    source_fitness: float  # share of what the model shows the camera that the target confirms
    inlier_rmse: float
    score: float
    symmetry: int  # index into BaseObject.symmetries it came from (0 = as registered)
    coverage: float = float("nan")  # share of target points within 2 voxels of what the model shows (loose fitness)


@dataclass
class RegistrationResult:
    ok: bool
    reason: str = ""
    T_world_base: np.ndarray | None = None
    T_world_part: np.ndarray | None = None
    T_world_source: np.ndarray | None = None  # the source's initial pose (TFORM)
    target_cloud: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # world
    source_cloud: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # base frame
    stages: list[Stage] = field(default_factory=list)
    fitness: float = 0.0
    inlier_rmse: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    candidates: list[Candidate] = field(default_factory=list)
    ambiguous: bool = False
    alternatives: list[Candidate] = field(default_factory=list)  # other placements of the part that fit as well
    preset: str = ""
    voxel: float = 0.0
    coverage: float = float("nan")  # share of target points within 2 voxels of what the model shows (loose fitness)

    @property
    def seconds(self) -> float:
        return float(sum(self.timings.values()))

    @property
    def confident(self) -> bool:
        """The model explains most of the target; a poor fit is likely a wrong pose, whatever else it says."""
        return bool(self.ok and (np.isnan(self.coverage) or self.coverage >= CONFIDENT_COVERAGE))


def failed(reason: str, **kw) -> RegistrationResult:
    return RegistrationResult(ok=False, reason=reason, **kw)


# ----------------------------------------------------------------------------------- stages


def project_to_cloud(depth: np.ndarray, mask: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray) -> np.ndarray:
    """PROJ3D: masked depth pixels (metres; 0, NaN and inf ignored) back-projected to world points (N, 3)."""
    if depth.shape != mask.shape:
        raise AposeError(f"mask is {mask.shape[1]}x{mask.shape[0]} but depth is {depth.shape[1]}x{depth.shape[0]}")
    vs, us = np.nonzero(mask & np.isfinite(depth) & (depth > 0))
    return se3.transform_points(T_world_camera, cam.backproject(us, vs, depth[vs, us]))


def place_source(base: BaseObject, target_centre: np.ndarray, R_world_base: np.ndarray | None = None) -> np.ndarray:
    """TFORM: T_world_source that puts the base's box centre on the target's centre, orientation kept;
    (n, 4, 4) for (n, 3, 3) orientations."""
    R = np.eye(3) if R_world_base is None else np.asarray(R_world_base)
    T = np.tile(np.eye(4), R.shape[:-2] + (1, 1))
    T[..., :3, :3], T[..., :3, 3] = R, target_centre - R @ base.centre
    return T


def raycast_source(base: BaseObject, T_world_source: np.ndarray, T_world_camera: np.ndarray,
                   cam: CameraIntrinsics, look_at: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """RCAST: the base mesh at T_world_source seen by a pinhole camera at the real camera's position.

    With `look_at`, the virtual camera turns to look at that point (the paper's virtual camera looks
    at the target's centre); otherwise it is the real camera. Returns world points and normals.
    """
    from .render import raycast_points

    T_cam = T_world_camera if look_at is None else se3.look_at(T_world_camera[:3, 3], look_at)
    return raycast_points(base.mesh, T_world_source, T_cam, cam)


def _cloud(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return pc


def _normals(pc, voxel: float, p: Params, camera_pos: np.ndarray | None) -> None:
    """Estimate normals once (oriented towards the camera when its position is known)."""
    import open3d as o3d

    if not pc.has_normals():
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=p.normal_radius_factor * voxel, max_nn=30))
        if camera_pos is not None:
            pc.orient_normals_towards_camera_location(camera_pos)


def _normals_fpfh(pc, voxel: float, p: Params, camera_pos: np.ndarray | None):
    import open3d as o3d

    reg = o3d.pipelines.registration
    _normals(pc, voxel, p, camera_pos)
    return reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=p.feature_radius_factor * voxel, max_nn=100))


def global_registration(source, target, f_source, f_target, voxel: float, p: Params) -> np.ndarray:
    """PCDREG, global part: RANSAC on FPFH matches. Returns T_target_source."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(p.seed)
    dist = p.ransac_distance_factor * voxel
    checkers = [reg.CorrespondenceCheckerBasedOnEdgeLength(p.ransac_edge_length), reg.CorrespondenceCheckerBasedOnDistance(dist)]
    if p.feature_matches > 1:
        # repetitive geometry (gear teeth) makes the single nearest feature often wrong: offer k of them
        fs, ft = np.asarray(f_source.data).T, np.asarray(f_target.data).T
        _, idx = cKDTree(fs).query(ft, k=p.feature_matches)
        corr = np.stack([idx.reshape(-1), np.repeat(np.arange(len(ft)), p.feature_matches)], axis=1)
        res = reg.registration_ransac_based_on_correspondence(
            source, target, o3d.utility.Vector2iVector(corr.astype(np.int32)), dist,
            reg.TransformationEstimationPointToPoint(False), 3, checkers,
            reg.RANSACConvergenceCriteria(p.ransac_max_iterations, p.ransac_confidence))
        return np.asarray(res.transformation)
    res = reg.registration_ransac_based_on_feature_matching(
        source, target, f_source, f_target, p.mutual_filter, dist,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(p.ransac_edge_length), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(p.ransac_max_iterations, p.ransac_confidence))
    return np.asarray(res.transformation)


def icp(source, target, T_init: np.ndarray, threshold: float, iterations: int, trace: list | None = None) -> np.ndarray:
    """Point-to-plane ICP, L(T) = sum ((p - T q) . n_p)^2 with target normals n_p. Returns T_target_source.

    With `trace`, runs one iteration at a time and appends each T (same result, for replay).
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    est = reg.TransformationEstimationPointToPlane()
    if trace is None:
        res = reg.registration_icp(source, target, threshold, T_init, est,
                                   reg.ICPConvergenceCriteria(1e-6, 1e-6, iterations))
        return np.asarray(res.transformation)
    T = T_init
    prev = None
    for _ in range(iterations):
        res = reg.registration_icp(source, target, threshold, T, est, reg.ICPConvergenceCriteria(1e-6, 1e-6, 1))
        T = np.asarray(res.transformation)
        trace.append(T.copy())
        if prev is not None and abs(prev - res.inlier_rmse) < 1e-7:
            break
        prev = res.inlier_rmse
    return T


# ----------------------------------------------------------------------------------- the pipeline


def estimate(depth: np.ndarray, mask: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray,
             base: BaseObject, T_base_part: np.ndarray, params: Params,
             prior_T_world_base: np.ndarray | None = None, trace_iterations: bool = True) -> RegistrationResult:
    """T_world_part for one frame. Never raises on bad data: a degenerate input gives ok=False and a reason."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if mask is None or not np.any(mask):
        return failed("empty mask: no pixels of the base object in this frame", preset=params.preset)
    target_pts = project_to_cloud(depth, mask, cam, T_world_camera)
    timings["proj3d"] = time.perf_counter() - t0
    if len(target_pts) < MIN_POINTS:
        return failed(f"only {len(target_pts)} valid depth points under the mask (need {MIN_POINTS}); "
                      "the base object is too small, occluded or without depth here", preset=params.preset,
                      target_cloud=target_pts, timings=timings)
    scale = scale_problem(target_pts, base.diameter)
    if scale is not None:
        return failed(scale, preset=params.preset, target_cloud=target_pts, timings=timings)
    if prior_T_world_base is None and params.use_orientation_prior:
        prior_T_world_base = np.eye(4)  # the CAD's orientation is the base's orientation in the world
    voxel = params.voxel(base.diameter)
    kw = dict(preset=params.preset, voxel=voxel)
    inner = dict(preset=params.preset)
    try:
        if params.global_source == "raycast":
            return _estimate_paper(target_pts, cam, T_world_camera, base, T_base_part, params, voxel,
                                   prior_T_world_base, trace_iterations, timings, **inner)
        return _estimate_default(target_pts, cam, T_world_camera, base, T_base_part, params, voxel,
                                 prior_T_world_base, trace_iterations, timings, Observation(mask, depth, mask_edge(mask)),
                                 **inner)
    except _Degenerate as e:
        return failed(str(e), target_cloud=target_pts, timings=timings, **kw)


class _Degenerate(Exception):
    pass


def scale_problem(target_pts: np.ndarray, diameter: float) -> str | None:
    """A unit error, in words, when the masked depth is far larger or smaller than the CAD could ever
    look (depth_scale off by 10 or 1000, a model in the wrong unit); None when the sizes are compatible.

    The target's extent is the diagonal of its 5th-95th percentile box; a view of a part never spans
    much more than its diameter (the mask may take in a little clutter), and rarely much less than a
    tenth of it."""
    lo, hi = np.percentile(target_pts, [5, 95], axis=0)
    ratio = float(np.linalg.norm(hi - lo)) / max(diameter, 1e-9)
    if 4.0 < ratio:
        k = 10 ** round(np.log10(ratio))
        return (f"the target is {ratio:.0f}x the base object's diameter ({diameter * 1000:.3g} mm): depth looks about "
                f"{k}x too far; is depth_scale {k}x too large (1.0 instead of 0.1?), or the CAD's units too small?")
    if ratio < 0.1:
        k = 10 ** round(-np.log10(max(ratio, 1e-12)))
        return (f"the target spans only {ratio:.3f}x the base object's diameter ({diameter * 1000:.3g} mm): depth looks "
                f"about {k}x too near; is depth_scale {k}x too small, or the CAD's units too large?")
    return None


def _stage(name, T, target, source_base, threshold) -> Stage:
    f, r = fitness_rmse(target, se3.transform_points(T, source_base), threshold)
    return Stage(name, T, f, r)


def _estimate_paper(target_pts, cam, T_world_camera, base, T_base_part, p: Params, voxel, prior, trace_iterations,
                    timings, **kw) -> RegistrationResult:
    """The authors' pipeline: translate the CAD to the target, ray-cast it, FPFH + RANSAC, ICP."""
    t = time.perf_counter()
    centre = target_pts.mean(axis=0)
    R_prior = prior[:3, :3] if prior is not None else None
    T_world_source = place_source(base, centre, R_prior)
    src_world, _ = raycast_source(base, T_world_source, T_world_camera, p.source_camera or cam, look_at=centre)
    timings["rcast"] = time.perf_counter() - t
    if len(src_world) < MIN_POINTS:
        raise _Degenerate("the camera cannot see the base mesh placed at the target (ray-cast gave "
                          f"{len(src_world)} points)")
    src_base = se3.transform_points(se3.inv(T_world_source), src_world)
    t = time.perf_counter()
    source, target = _cloud(src_world), _cloud(target_pts)
    if p.downsample:
        source, target = source.voxel_down_sample(voxel), target.voxel_down_sample(voxel)
    cam_pos = T_world_camera[:3, 3]
    f_s = _normals_fpfh(source, voxel, p, cam_pos)
    f_t = _normals_fpfh(target, voxel, p, cam_pos)
    timings["features"] = time.perf_counter() - t
    t = time.perf_counter()
    T_g = global_registration(source, target, f_s, f_t, voxel, p)
    timings["global"] = time.perf_counter() - t
    t = time.perf_counter()
    trace: list | None = [] if trace_iterations else None
    T_i = icp(source, target, T_g, p.icp_threshold_factor * voxel, p.icp_max_iterations, trace)
    timings["icp"] = time.perf_counter() - t
    thr = p.icp_threshold_factor * voxel
    T_world_base = T_i @ T_world_source
    stages = [_stage("initial", T_world_source, target_pts, src_base, thr),
              _stage("global", T_g @ T_world_source, target_pts, src_base, thr)]
    stages += [_stage(f"icp {k + 1}", T @ T_world_source, target_pts, src_base, thr) for k, T in enumerate(trace or [])]
    final = _stage("final", T_world_base, target_pts, src_base, thr)
    stages.append(final)
    T_world_part = T_world_base @ T_base_part
    cand = Candidate(T_world_base, T_world_part, final.fitness, float("nan"), final.inlier_rmse, final.fitness, 0)
    return RegistrationResult(True, "", T_world_base, T_world_part, T_world_source, target_pts, src_base, stages,
                              final.fitness, final.inlier_rmse, timings, [cand], False, voxel=voxel, **kw)


def _facing(points: np.ndarray, normals: np.ndarray, T_world_base: np.ndarray, cam_pos: np.ndarray) -> np.ndarray:
    """Model points (base frame) whose outward normal faces the camera when the base is at T_world_base."""
    eye = se3.transform_points(se3.inv(T_world_base), cam_pos[None])[0]
    return points[np.einsum("ij,ij->i", normals, eye - points) > 0]


class Observation(NamedTuple):
    """What a frame shows of the base: its mask, the depth (metres) and the mask's outline (`mask_edge`)."""

    mask: np.ndarray
    depth: np.ndarray
    edge: np.ndarray


def _pixels(points_world: np.ndarray, T_world_camera, cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(v, u, z, inside) of world points: integer pixel, depth along the camera's axis, and whether the
    pixel is in the image in front of the camera (v and u are 0 where not)."""
    pc = se3.transform_points(se3.inv(T_world_camera), points_world)
    u, v = cam.project(pc)
    with np.errstate(invalid="ignore"):
        u, v = np.round(u), np.round(v)
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return np.where(inside, v, 0).astype(int), np.where(inside, u, 0).astype(int), pc[:, 2], inside


def _visible_agreement(points_world: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics,
                       depth_obs: np.ndarray, mask: np.ndarray, tol: float, edge: np.ndarray | None = None) -> float:
    """Share of model points seen at a candidate pose that the observation confirms (inside the mask,
    at the observed depth within `tol`). With `edge` (pixels within a couple of pixels of the mask's
    outline), points there and points on pixels without depth (sensor dropout) are left out: the
    observation can neither confirm nor deny them."""
    if len(points_world) == 0:
        return 0.0
    v, u, z, inside = _pixels(points_world, T_world_camera, cam)
    d = depth_obs[v, u]
    ok = inside & mask[v, u] & (np.abs(d - z) < tol)
    if edge is None:
        return float(ok.mean())
    known = ~(inside & (edge[v, u] | ~(np.isfinite(d) & (d > 0))))
    return float(ok[known].mean()) if known.any() else 0.0


MASK_MARGIN_PX = 2  # mask edges are a pixel or two off: a model point further outside contradicts its pose


def mask_edge(mask: np.ndarray, px: int = MASK_MARGIN_PX) -> np.ndarray:
    """Pixels within `px` of the mask's outline, on either side (where depth and mask are mixed)."""
    import cv2

    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    m = mask.astype(np.uint8)
    return (cv2.dilate(m, k) > 0) & ~(cv2.erode(m, k) > 0)


def _score_pose(T_world_base, base, T_base_part, fine_pts, T_world_camera, cam, observation, voxel, thr,
                symmetry: int = 0) -> tuple[Candidate, np.ndarray, np.ndarray]:
    """A candidate at a refined pose: what the camera would see of the base there (world points and
    normals, also returned), the target share it explains, and the share of it the depth confirms."""
    src_w, src_n = raycast_source(base, T_world_base, T_world_camera, cam)
    cand, src_w = _score_seen(T_world_base, src_w, T_base_part, fine_pts, T_world_camera, cam, observation, voxel, thr,
                              symmetry)
    return cand, src_w, src_n


def _score_seen(T_world_base, src_w, T_base_part, fine_pts, T_world_camera, cam, observation, voxel, thr,
                symmetry: int = 0) -> tuple[Candidate, np.ndarray]:
    """_score_pose with what the camera sees of the base at T_world_base given (world points). One
    query gives the fitness and RMSE (within thr) and the coverage (within 2 voxels)."""
    loose = max(thr, 2 * voxel)
    d = quick_tree(src_w).query(fine_pts, distance_upper_bound=loose)[0] if len(src_w) and len(fine_pts) \
        else np.full(len(fine_pts), np.inf)
    inl = d < thr
    fit, rmse = (float(inl.mean()), float(np.sqrt(np.mean(d[inl] ** 2)))) if inl.any() else (0.0, 0.0)
    coverage = float(np.mean(d < loose)) if len(d) else 0.0
    agree = _visible_agreement(src_w, T_world_camera, cam, observation.depth, observation.mask, max(2 * voxel, 0.002))
    return Candidate(T_world_base, T_world_base @ T_base_part, fit, agree, rmse, 0.5 * (fit + agree), symmetry,
                     coverage), src_w


def _trace_stages(T_world_source, start_name: str, T_start, trace, cand: Candidate, src_b, fine_pts, thr) -> list[Stage]:
    """The replay: initial (TFORM) -> the start ICP began from -> every ICP iteration -> final. Without a
    trace (trace_iterations=False: batch evaluation) only the final stage's fitness is computed."""
    if trace is None:
        return [Stage("initial", T_world_source, float("nan"), float("nan")),
                Stage(start_name, T_start, float("nan"), float("nan")),
                Stage("final", cand.T_world_base, cand.fitness, cand.inlier_rmse)]
    stages = [_stage("initial", T_world_source, fine_pts, src_b, thr), _stage(start_name, T_start, fine_pts, src_b, thr)]
    stages += [_stage(f"icp {k + 1}", T, fine_pts, src_b, thr) for k, T in enumerate(trace or [])]
    return stages + [Stage("final", cand.T_world_base, cand.fitness, cand.inlier_rmse)]


PRIOR_ACCEPT = 0.95  # the prior's pose is kept without a global search when both shares reach this
UPRIGHT_YAW_STEP_DEG = 10.0
UPRIGHT_STARTS = 4  # the best-screened yaws refined by coarse ICP (4 and 6 reach the same recall; 4 is 7 % faster)
UPRIGHT_TWINS = 3  # at most this many (near-)symmetric turns of the best upright pose are refined too
TWIN_MARGIN = 0.1  # a twin refined only when its coarse fit is within this of the best start's
UPRIGHT_FALLBACK = 0.6  # below this share explained by the best upright start, the base is not upright: search freely


def table_normal(depth: np.ndarray, mask: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray,
                 min_inlier_share: float = 0.3) -> np.ndarray | None:
    """World unit normal of the plane the base stands on (pointing at the camera), fitted by RANSAC
    to the depth outside the base's mask; None when no plane holds min_inlier_share of those points."""
    step = max(1, int(np.sqrt(mask.size / 5000)))  # about 5000 pixels on a regular grid are plenty for a plane
    d = depth[::step, ::step]
    vs, us = np.nonzero(~mask[::step, ::step] & np.isfinite(d) & (d > 0))
    if len(vs) < 200:
        return None
    pts = se3.transform_points(T_world_camera, cam.backproject(us * step, vs * step, d[vs, us]))
    tol = 0.004 * float(np.median(np.linalg.norm(pts - T_world_camera[:3, 3], axis=1)))
    (a, b, c, d), inliers = _cloud(pts).segment_plane(tol, 3, 300)
    if len(inliers) < min_inlier_share * len(pts):
        return None
    n = np.array([a, b, c]) / np.linalg.norm([a, b, c])
    return n if n @ T_world_camera[:3, 3] + d / np.linalg.norm([a, b, c]) > 0 else -n


def upright_starts(base: "BaseObject", up: np.ndarray, target_pts: np.ndarray, cam_pos: np.ndarray,
                   model_pts: np.ndarray, model_nrm: np.ndarray) -> list:
    """(0, T_world_base) starts with the CAD's +z along `up`, one per yaw step about it, each moved so
    the part of the model facing the camera is centred on the target."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, up)
    if np.linalg.norm(axis) > 1e-9:  # the turn that takes the CAD's +z onto the table's normal
        R_up = se3.axis_angle_matrix(axis, float(np.arccos(np.clip(z @ up, -1.0, 1.0))))
    else:  # already along it, or exactly opposite (a half turn about x)
        R_up = np.eye(3) if up[2] > 0 else np.diag([1.0, -1.0, -1.0])
    centre = target_pts.mean(axis=0)
    R = se3.axis_angle_matrix(up, np.radians(np.arange(0.0, 360.0, UPRIGHT_YAW_STEP_DEG))) @ R_up  # (n, 3, 3)
    poses = place_source(base, centre, R)
    t = poses[:, :3, 3]
    eyes = np.einsum("nji,nj->ni", R, cam_pos - t)  # the camera in the base frame, per yaw
    facing = (eyes @ model_nrm.T) > np.einsum("ij,ij->i", model_nrm, model_pts)[None]  # n . (eye - p) > 0
    count = facing.sum(axis=1)
    seen_mean = (facing.astype(float) @ model_pts) / np.maximum(count, 1)[:, None]  # base frame
    shift = centre - (np.einsum("nij,nj->ni", R, seen_mean) + t)
    poses[:, :3, 3] += np.where(count[:, None] > 0, shift, 0.0)  # the part facing the camera centred on the target
    return [(0, T) for T in poses]


def _poses_within(A: np.ndarray, B: np.ndarray, metres: float, degrees: float) -> bool:
    """A and B are less than `metres` and `degrees` apart."""
    return bool(np.linalg.norm(A[:3, 3] - B[:3, 3]) < metres and se3.rotation_angle_deg(A[:3, :3].T @ B[:3, :3]) < degrees)


def _keeps_up(T: np.ndarray, T_ref: np.ndarray, max_deg: float = 5.0) -> bool:
    """T's base +z points where T_ref's does (a turn about the table's normal, not a tip-over)."""
    return float(T[:3, 2] @ T_ref[:3, 2]) > np.cos(np.radians(max_deg))


POLISH_ITERATIONS = 6


def _polish(T_world_base: np.ndarray, base: BaseObject, T_world_camera, cam: CameraIntrinsics, target_full,
            voxel: float, p: Params, trace: list | None, seen_world: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The last refinement: the target, down-sampled finely, registered by point-to-plane ICP onto what
    the camera sees of the model at T_world_base, using the model's exact normals. With RealSense-like
    noise the target's own normals are noisy and bias the fit; the model's are not (scene-to-model).
    Returns the refined T_world_base and the seen model points moved with it (world): the pose moves by
    a fraction of a millimetre, so what the camera sees is not cast again. `seen_world`: (points, normals)
    the camera sees at T_world_base, when already cast."""
    src_w, src_n = seen_world if seen_world is not None else raycast_source(base, T_world_base, T_world_camera, cam)
    if len(src_w) < MIN_POINTS:
        return T_world_base, src_w
    T_base_world = se3.inv(T_world_base)
    seen = _cloud(se3.transform_points(T_base_world, src_w), src_n @ T_base_world[:3, :3].T)
    v = voxel * p.polish_voxel_factor
    steps: list | None = [] if trace is not None else None
    T = icp(target_full.voxel_down_sample(v), seen.voxel_down_sample(v), T_base_world,
            p.polish_threshold_factor * voxel, POLISH_ITERATIONS, steps)
    if trace is not None:
        trace.extend(se3.inv(S) for S in steps)
    T_new = se3.inv(T)
    return T_new, se3.transform_points(T_new @ T_base_world, src_w)


def _try_prior(tp, target_full, fine, fine_pts, cam, T_world_camera, base, T_base_part, p: Params, voxel, prior, trace_iterations,
               timings, observation, **kw) -> RegistrationResult | None:
    """Early exit when the caller knows the base's orientation: put the CAD in that orientation where
    what the camera would see of it lands on the target's centre, refine with ICP from coarse to fine,
    and accept when the model explains the target and the depth confirms the model (both >= 95 %).
    Otherwise None, and the full search runs (the prior still breaks its ties)."""
    t = time.perf_counter()
    thr = p.icp_threshold_factor * voxel
    T_world_source = place_source(base, tp.mean(axis=0), prior[:3, :3])
    src_w, _ = raycast_source(base, T_world_source, T_world_camera, cam)
    if len(src_w) < MIN_POINTS:
        return None
    T0 = T_world_source.copy()
    T0[:3, 3] += tp.mean(axis=0) - src_w.mean(axis=0)  # the visible part's centre on the target's centre
    src = _cloud(se3.transform_points(se3.inv(T_world_source), src_w)).voxel_down_sample(voxel)
    trace: list | None = [] if trace_iterations else None
    T = T0
    for factor in (8.0, 4.0, 2.0):
        T = icp(src, fine, T, factor * voxel, 10, trace)
    if p.polish_voxel_factor > 0:
        T, src_w = _polish(T, base, T_world_camera, cam, target_full, voxel, p, trace)
    else:
        src_w, _ = raycast_source(base, T, T_world_camera, cam)  # what the camera sees at the refined pose
        src = _cloud(se3.transform_points(se3.inv(T), src_w)).voxel_down_sample(voxel)
        T = icp(src, fine, T, thr, p.icp_max_iterations, trace)
        src_w, _ = raycast_source(base, T, T_world_camera, cam)
    cand, src_w = _score_seen(T, src_w, T_base_part, fine_pts, T_world_camera, cam, observation, voxel, thr)
    # the depth's word on the model, leaving out what it cannot judge: the mask's outline (mixed
    # pixels) and dropouts; with RealSense-like noise those alone cost 5-7 % of the agreement
    confirmed = _visible_agreement(src_w, T_world_camera, cam, observation.depth, observation.mask,
                                   max(2 * voxel, 0.002), observation.edge)
    timings["prior"] = time.perf_counter() - t
    if cand.coverage < PRIOR_ACCEPT or confirmed < PRIOR_ACCEPT:
        return None
    src_b = se3.transform_points(se3.inv(T), src_w)
    stages = _trace_stages(T_world_source, "prior", T0, trace, cand, src_b, fine_pts, thr)
    return RegistrationResult(True, "", T, cand.T_world_part, T_world_source, fine_pts, src_b, stages, cand.fitness,
                              cand.inlier_rmse, timings, [cand], False, voxel=voxel, coverage=cand.coverage, **kw)


def _estimate_default(target_pts, cam, T_world_camera, base, T_base_part, p: Params, voxel, prior, trace_iterations,
                      timings, observation, **kw) -> RegistrationResult:
    import open3d as o3d

    cam_pos = T_world_camera[:3, 3]
    vg = voxel * p.global_voxel_factor
    t = time.perf_counter()
    target_full = _cloud(target_pts)
    target = target_full.voxel_down_sample(vg)
    if len(target.points) >= 40:  # flying pixels and speckle: drop points far from their neighbours
        target, _ = target.remove_statistical_outlier(nb_neighbors=12, std_ratio=3.0)
    if len(target.points) < 10:
        raise _Degenerate(f"the target is degenerate: {len(target.points)} points after down-sampling to "
                          f"{vg * 1000:.2f} mm (a flat speck or a few pixels?)")
    tp = np.asarray(target.points)
    if np.linalg.svd(tp - tp.mean(axis=0), compute_uv=False)[1] < 0.05 * vg:
        raise _Degenerate("the target is degenerate: its points lie on a line")
    fine = target_full.voxel_down_sample(voxel)
    fine.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=p.normal_radius_factor * voxel, max_nn=30))
    fine.orient_normals_towards_camera_location(cam_pos)
    fine_pts = np.asarray(fine.points)
    fine_tree = quick_tree(fine_pts)
    if prior is not None and p.prior_fast_path:
        timings["features"] = time.perf_counter() - t
        quick = _try_prior(tp, target_full, fine, fine_pts, cam, T_world_camera, base, T_base_part, p, voxel, prior,
                           trace_iterations, timings, observation, **kw)
        if quick is not None:
            return quick
        t = time.perf_counter()
    # the whole model (features cached per step): no assumption about the side seen or the orientation
    model, f_m = base.model_features(vg, p)
    _normals(target, vg, p, cam_pos)  # ICP needs them whatever the search
    target_features: list = []

    def f_t():  # the target's FPFH, computed only when a RANSAC needs it (the upright search does not)
        if not target_features:
            target_features.append(_normals_fpfh(target, vg, p, cam_pos))
        return target_features[0]
    timings["features"] = timings.get("features", 0.0) + time.perf_counter() - t

    t = time.perf_counter()
    centre = tp.mean(axis=0)
    R_prior = prior[:3, :3] if prior is not None else None
    T_world_source = place_source(base, centre, R_prior)  # TFORM, kept as the replay's starting point
    up = None
    if p.upright and prior is None:
        up = table_normal(observation.depth, observation.mask, cam, T_world_camera)
    if up is None:
        T_g = global_registration(model, target, f_m, f_t(), vg, p)  # T_world_base directly (model is in base frame)

    prior_starts = []
    if R_prior is not None:
        # the paper's way, on down-sampled clouds: the CAD in the prior orientation, seen from the camera,
        # registered to the target; plus the plain translated CAD
        src_w, _ = raycast_source(base, T_world_source, T_world_camera, cam)
        if len(src_w) >= MIN_POINTS:
            src = _cloud(src_w).voxel_down_sample(vg)
            T_p = global_registration(src, target, _normals_fpfh(src, vg, p, cam_pos), f_t(), vg, p)
            prior_starts.append((-1, T_p @ T_world_source))
        prior_starts.append((-1, T_world_source))
    grid = base.near_grid(vg, p)
    model_pts, model_nrm = np.asarray(model.points), np.asarray(model.normals)

    tp_few = tp[np.random.default_rng(p.seed).choice(len(tp), min(len(tp), 500), replace=False)]

    def near(poses: list) -> np.ndarray:  # per pose: share of (500 of the) target points near the model's outer surface
        if not poses:
            return np.zeros(0)
        T_base_world = np.linalg.inv(np.stack(poses))  # (n, 4, 4)
        pts = tp_few @ T_base_world[:, :3, :3].transpose(0, 2, 1) + T_base_world[:, None, :3, 3]
        return grid.contains(pts.reshape(-1, 3)).reshape(len(poses), -1).mean(axis=1)

    def coarse_starts(T_g, extra: list, starts: list | None = None) -> list:
        """(explained share, symmetry index, start pose, pose after a few coarse ICP iterations) per start:
        the global result, its half turns (partial views often match upside down), the base's
        (near-)symmetries and `extra` (or the given `starts`); screened cheaply, the best few refined
        by coarse ICP."""
        if starts is None:
            starts = [(0, T_g @ F) for F in base.flips()] if p.use_flips else [(0, T_g)]
            if p.use_symmetries:  # (the symmetries proper need no start: their twins are derived at the end)
                starts += [(0, T_g @ S) for S in base.near_symmetries]
        all_starts = starts + extra
        share = near([T for _, T in all_starts])
        screened = [all_starts[i] for i in np.argsort(-share, kind="stable")]
        n_try = p.max_starts if up is None else UPRIGHT_STARTS
        out = []
        for k, T0 in screened[:n_try] + [s_ for s_ in screened[n_try:] if s_[0] == -1]:
            # cheap view of the model for screening: its outer surface, back faces culled (no occlusion)
            src = _cloud(_facing(model_pts, model_nrm, T0, cam_pos))
            if len(src.points) < MIN_POINTS:
                continue
            T = icp(src, target, T0, 2.0 * vg, 8, None)
            seen = se3.transform_points(T, _facing(model_pts, model_nrm, T, cam_pos))
            f_quick = float(np.mean(fine_tree.query(seen, distance_upper_bound=vg)[0] < np.inf)) if len(seen) else 0.0
            out.append((f_quick, k, T0, T))
        return sorted(out, key=lambda x: -x[0])

    twins: list = []  # the best upright pose turned by the base's (near-)symmetries about the table's normal
    if up is not None:  # upright on the table: every yaw about its normal, no RANSAC
        coarse = coarse_starts(None, [], upright_starts(base, up, tp, cam_pos, model_pts, model_nrm))
        if coarse and coarse[0][0] >= UPRIGHT_FALLBACK and p.use_symmetries:
            # a nearly symmetric base (a motor block whose connector alone breaks its 4-fold turn) gives
            # near-equal yaws a quarter turn apart; the screening cannot tell them apart, the refined
            # scores and the discrimination can: each twin of the best is refined, whatever it screens at
            best = coarse[0]
            T_best = best[3]
            sym = [(0, T_best @ S) for S in base.near_symmetries]  # (the symmetries' twins are derived at the end)
            sym = [(k, T) for k, T in sym if _keeps_up(T, T_best)][:UPRIGHT_TWINS]  # the closest-fitting turns
            twins = coarse_starts(None, [], sym) if sym else []
            coarse = sorted(coarse + twins, key=lambda x: -x[0])
            twins = [best] + twins  # the best itself too: a twin may now screen higher and crowd it out
        if not coarse or coarse[0][0] < UPRIGHT_FALLBACK:  # nothing fits upright: it is not; search freely
            up = None
            T_g = global_registration(model, target, f_m, f_t(), vg, p)
            coarse = sorted(coarse + coarse_starts(T_g, []), key=lambda x: -x[0])
    else:
        coarse = coarse_starts(T_g, prior_starts)
    if up is None and p.ransac_retry_iterations and (not coarse or coarse[0][0] < p.retry_below):  # the fast RANSAC missed: try harder
        T_g = global_registration(model, target, f_m, f_t(), vg,
                                  replace(p, ransac_max_iterations=p.ransac_retry_iterations, seed=p.seed + 1))
        coarse = sorted(coarse + coarse_starts(T_g, []), key=lambda x: -x[0])  # the prior's starts are in already
    timings["global"] = time.perf_counter() - t

    t = time.perf_counter()
    thr = p.icp_threshold_factor * voxel
    def new(c) -> bool:  # a coarse pose not (nearly) one already kept
        return not any(_poses_within(c[3], q[3], 2 * voxel, 10.0) for q in keep)

    keep = []  # the best few *distinct* poses: several starts often converge to one (possibly wrong) pose
    for c in coarse:
        if len(keep) == 3 or c[0] < coarse[0][0] - 0.1:
            break
        if new(c):
            keep.append(c)
    if p.use_symmetries:
        for c in twins:  # one at a time: a twin that lands on one kept just before is not new
            if new(c) and c[0] >= coarse[0][0] - TWIN_MARGIN:
                keep.append(c)
    prior_best = [c for c in coarse if c[1] == -1][:1]  # the prior's best start is always refined and scored
    keep += [c for c in prior_best if not any(c is q for q in keep)]
    cands, traces = [], []  # traces[i]: (start pose, ICP trace, seen world points, their normals) of cands[i]
    for _, k, T0, T1 in keep:
        trace: list | None = [] if trace_iterations else None
        src_w, src_n = raycast_source(base, T1, T_world_camera, cam)  # what the camera would see at this pose
        src = _cloud(se3.transform_points(se3.inv(T1), src_w)).voxel_down_sample(voxel)
        T = icp(src, fine, T1, vg, p.icp_max_iterations, trace)
        if any(_poses_within(T, c_.T_world_base, voxel, 2.0) for c_ in cands):
            continue  # converged onto a pose already refined: nothing new to score
        if p.polish_voxel_factor <= 0:  # else no ICP at thr: only the chosen pose needs the last tenth of a
            # millimetre, and the polish gives it that (on the yaw renders 10 % faster, 0.004 mm more mean ADI)
            T = icp(src, fine, T, thr, p.icp_max_iterations, trace)
        # scored on what the camera sees at the coarse pose, moved with the refinement (small after the coarse
        # ICP): one ray-cast per candidate instead of two, same recall on the yaw renders (benchmarks/tune.py)
        D = T @ se3.inv(T1)
        cand, src_w = _score_seen(T, se3.transform_points(D, src_w), T_base_part, fine_pts, T_world_camera, cam,
                                  observation, voxel, thr, k)
        src_n = src_n @ D[:3, :3].T
        cands.append(cand)
        traces.append((T0, trace, src_w, src_n))
    if p.use_symmetries and cands:
        _add_symmetric_twins(cands, traces, base, T_base_part, fine_pts, T_world_camera, cam, observation, voxel, thr)
    timings["icp"] = time.perf_counter() - t
    if not cands:
        raise _Degenerate("the camera cannot see the base mesh at any candidate pose")

    best_score = max(c.score for c in cands)
    close = [i for i, c in enumerate(cands) if c.score >= best_score - TIE_MARGIN]
    if R_prior is None and len(close) > 1:  # look where the placements differ: the evidence there decides
        close = _discriminate(close, cands, traces, fine_pts, T_world_camera, cam, observation, voxel, thr)
    # several placements explain the data equally: the prior (if any) decides, else the best score
    if R_prior is not None and len(close) > 1:
        chosen = min(close, key=lambda i: se3.rotation_angle_deg(cands[i].T_world_base[:3, :3].T @ R_prior))
    else:
        chosen = max(close, key=lambda i: cands[i].score)
    T0, trace, src_w, src_n = traces[chosen]
    if p.polish_voxel_factor > 0:
        t = time.perf_counter()
        T, seen = _polish(cands[chosen].T_world_base, base, T_world_camera, cam, target_full, voxel, p, trace,
                          (src_w, src_n))
        cands[chosen], src_w = _score_seen(T, seen, T_base_part, fine_pts, T_world_camera, cam, observation, voxel, thr,
                                           cands[chosen].symmetry)
        timings["icp"] += time.perf_counter() - t
    c = cands[chosen]
    src_b = se3.transform_points(se3.inv(c.T_world_base), src_w)
    stages = _trace_stages(T_world_source, "global", T0, trace, c, src_b, fine_pts, thr)
    order = sorted(range(len(cands)), key=lambda i: -cands[i].score)
    coverage = c.coverage
    placements = _distinct_placements([c] + [cands[i] for i in close if i != chosen], voxel)
    ambiguous = bool(len(placements) > 1 and coverage >= CONFIDENT_COVERAGE)
    result = RegistrationResult(True, "", c.T_world_base, c.T_world_part, T_world_source, fine_pts, src_b, stages,
                                c.fitness, c.inlier_rmse, timings, [cands[i] for i in order], ambiguous,
                                placements[1:] if ambiguous else [], voxel=voxel, coverage=float(coverage), **kw)
    if up is not None and not result.confident:
        # a table was seen, but the base does not stand on it as modelled (lying on its side, held in a
        # hand, on a fixture): search freely too, keep the better, and count the time of both
        free_timings: dict[str, float] = {}
        free = _estimate_default(target_pts, cam, T_world_camera, base, T_base_part, replace(p, upright=False), voxel,
                                 prior, trace_iterations, free_timings, observation, **kw)
        for k_, v_ in timings.items():
            free_timings[k_] = free_timings.get(k_, 0.0) + v_
        if free.coverage > result.coverage:
            return free
        result.timings = free_timings
    return result


def _add_symmetric_twins(cands: list[Candidate], traces: list, base: BaseObject, T_base_part, fine_pts, T_world_camera,
                         cam, observation, voxel, thr) -> None:
    """The best candidate turned by each of the base's symmetries, scored (and traced) as it: a turn
    that maps the base onto itself maps the refined pose onto the pose ICP would refine the turned
    start to, so the twin needs no registration of its own. Each is scored on what the camera would
    see of it, so that a symmetry that is not quite one (a connector) can still be told apart."""
    b = max(range(len(cands)), key=lambda i: cands[i].score)
    T_b = cands[b].T_world_base
    T0_b, trace_b = traces[b][:2]
    for k, S in enumerate(base.symmetries[1:], start=1):
        T = T_b @ S
        if any(_poses_within(T, c.T_world_base, voxel, 2.0) for c in cands):
            continue
        cand, src_w, src_n = _score_pose(T, base, T_base_part, fine_pts, T_world_camera, cam, observation, voxel, thr, k)
        cands.append(cand)
        traces.append((T0_b @ S, None if trace_b is None else [T_ @ S for T_ in trace_b], src_w, src_n))


DISCRIMINATE_MIN_POINTS = 10  # fewer distinguishing points than this on both sides: the placements are symmetric twins


def _evidence(points_world: np.ndarray, T_world_camera, cam: CameraIntrinsics, depth_obs: np.ndarray,
              mask: np.ndarray, outside: np.ndarray, tol: float) -> tuple[int, int]:
    """(confirmed, contradicted) among model points a candidate pose shows: confirmed where the mask
    holds the observed surface at that depth; contradicted where the camera sees past the claimed
    surface (farther depth, or background outside the mask by more than MASK_MARGIN_PX). Points
    behind something nearer are neither: an occluder hides them."""
    if len(points_world) == 0:
        return 0, 0
    v, u, z, inside = _pixels(points_world, T_world_camera, cam)
    v, u, z = v[inside], u[inside], z[inside]
    d = depth_obs[v, u]
    valid = np.isfinite(d) & (d > 0)
    m = mask[v, u]
    confirmed = m & valid & (np.abs(d - z) < tol)
    contradicted = valid & (d > z + tol) & (m | outside[v, u])
    return int(confirmed.sum()), int(contradicted.sum())


def _discriminate(close: list[int], cands: list[Candidate], traces: list, fine_pts: np.ndarray, T_world_camera,
                  cam: CameraIntrinsics, observation: Observation, voxel: float, thr: float) -> list[int]:
    """Break near-ties between placements by their differences only (a nearly symmetric motor block
    differs in one connector). For each pair, the evidence for a placement is: the points it shows
    that the other does not and that the depth confirms, the points the other shows where the camera
    sees past them (background, or a farther surface), and the target points only it explains (the
    other missing them by more than 2 voxels). A placement that loses to another by a clear margin
    (at least DISCRIMINATE_MIN_POINTS and 1.5x) is dropped; the rest (true symmetric twins among
    them) stay tied."""
    tol = max(2 * voxel, 0.002)
    mask_img, depth_img = observation.mask, observation.depth
    outside = ~(mask_img | observation.edge)
    seen = {i: traces[i][2] for i in close}
    trees = {i: quick_tree(seen[i]) if len(seen[i]) else None for i in close}
    # target points each placement explains (within thr), and those it misses by more than tol: a point
    # only one explains counts for it when the other misses it clearly (not by a sub-millimetre shift)
    dist = {i: trees[i].query(fine_pts, distance_upper_bound=tol)[0] if trees[i] is not None
            else np.full(len(fine_pts), np.inf) for i in close}
    near_target = {i: dist[i] < thr for i in close}
    far_target = {i: dist[i] == np.inf for i in close}
    pix = {i: _pixels(seen[i], T_world_camera, cam) for i in close}  # (v, u, z, inside) of each point seen
    # a depth buffer per placement, over the image window all of them cover
    vin = np.concatenate([pix[i][0][pix[i][3]] for i in close] + [np.zeros(1, int)])
    uin = np.concatenate([pix[i][1][pix[i][3]] for i in close] + [np.zeros(1, int)])
    v0, u0 = (int(vin.min()), int(uin.min())) if len(vin) > 1 else (0, 0)
    shape = (int(vin.max()) - v0 + 1, int(uin.max()) - u0 + 1)
    zbuf = {}
    for i in close:
        v, u, z, inside = pix[i]
        zbuf[i] = np.full(shape, np.inf)
        zbuf[i][v[inside] - v0, u[inside] - u0] = z[inside]

    def only(a, b):  # what a shows that b does not: the pixel depths differ, and no point of b is near
        v, u, z, inside = pix[a]
        zb = zbuf[b][np.clip(v - v0, 0, shape[0] - 1), np.clip(u - u0, 0, shape[1] - 1)]
        differ = ~(inside & (np.abs(zb - z) < 0.9 * tol))  # the same ray within 0.9 tol: certainly near
        pts = seen[a][differ]
        return pts[trees[b].query(pts, distance_upper_bound=tol)[0] == np.inf] if len(pts) else pts

    lost = set()
    for a_pos, a in enumerate(close):
        for b in close[a_pos + 1:]:
            if trees[a] is None or trees[b] is None:
                continue
            only_a, only_b = only(a, b), only(b, a)
            if len(only_a) < DISCRIMINATE_MIN_POINTS and len(only_b) < DISCRIMINATE_MIN_POINTS:
                continue  # twins: nothing to tell them apart
            conf_a, contra_a = _evidence(only_a, T_world_camera, cam, depth_img, mask_img, outside, tol)
            conf_b, contra_b = _evidence(only_b, T_world_camera, cam, depth_img, mask_img, outside, tol)
            ev_a = conf_a + contra_b + float(np.sum(near_target[a] & far_target[b]))
            ev_b = conf_b + contra_a + float(np.sum(near_target[b] & far_target[a]))
            if ev_a >= 1.5 * ev_b and ev_a - ev_b >= DISCRIMINATE_MIN_POINTS:
                lost.add(b)
            elif ev_b >= 1.5 * ev_a and ev_b - ev_a >= DISCRIMINATE_MIN_POINTS:
                lost.add(a)
    kept = [i for i in close if i not in lost]
    return kept or close


def _distinct_placements(cands: list[Candidate], voxel: float) -> list[Candidate]:
    """The clearly different part placements (more than 3 voxels or 5 degrees apart) among the
    candidates, the first one first."""
    reps: list[Candidate] = []
    for c in cands:
        if not any(_poses_within(c.T_world_part, r.T_world_part, 3 * voxel, 5.0) for r in reps):
            reps.append(c)
    return reps
