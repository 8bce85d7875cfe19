"""One frame's registration problem, built once: the target cloud at the resolutions the searches use,
the camera, the observation, the base object and the step's T_base_part. Every stage after PROJ3D
reads it instead of a clump of positional arguments."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.nn import NearestTree
from apose_studio.params import Params
from apose_studio.registration.base import BaseObject
from apose_studio.registration.stages import cloud, down_sample, estimate_normals
from apose_studio.registration.table import table_plane
from apose_studio.registration.types import DEPTH_SCALE_WHERE, Degenerate, Observation


@dataclass(frozen=True, eq=False)
class Task:
    base: BaseObject
    T_base_part: np.ndarray  # the step's pose of the part in the frame of base[0]
    params: Params
    cam: CameraIntrinsics
    T_world_camera: np.ndarray
    observation: Observation
    voxel: float  # the fine resolution (metres); the searches work at voxel x params.global_voxel_factor
    target_pts: np.ndarray  # (N, 3) every masked depth point, world frame
    coarse_pts: np.ndarray  # (M, 3) the target down-sampled at the coarse voxel, outliers removed, world frame
    fine_pts: np.ndarray  # (K, 3) the target down-sampled at the fine voxel, world frame (`fine`: with normals)
    fine_tree: object  # k-d tree of fine_pts
    deadline: float = float("inf")  # time.perf_counter() by which the searches stop (params.max_seconds)
    notes: list = field(default_factory=list)  # what the time budget cut short
    part_symmetries: np.ndarray | None = None  # (n, 4, 4) T_part_part of the part to place, identity first: twins of
    # the base that place the part alike (modulo these) are one placement, not an ambiguity
    target_cam: object = None  # open3d PointCloud: `coarse_pts` in the camera's frame (the global search's RANSAC
    # runs there); its normals are estimated when a search first needs them (`target`)
    fine_cam: object = None  # open3d PointCloud: `fine_pts` in the camera's frame, as down-sampled there
    _down: dict = field(default_factory=dict, repr=False)  # voxel -> target_at(voxel)
    _fine: dict = field(default_factory=dict, repr=False)  # "fine": `fine`, built once (a replace()d copy shares it)

    @property
    def fine(self):
        """open3d PointCloud of `fine_pts` with normals facing the camera (estimated in the camera's frame, then
        carried into the world, as the points were), for the ICPs onto the target. Built when first asked for: the
        prior's fast path fits the target onto the model (searches.try_prior) and needs none (3.9 ms a frame on
        benchmarks/tune.py's fixed protocol)."""
        pc = self._fine.get("fine")
        if pc is None:
            import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

            pc = o3d.geometry.PointCloud(self.fine_cam)
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=self.params.normal_radius_factor * self.voxel,
                                                                     max_nn=30))
            pc.orient_normals_towards_camera_location(np.zeros(3))
            pc = self._fine["fine"] = pc.transform(self.T_world_camera)
        return pc

    def target_at(self, voxel: float):
        """Every masked depth point down-sampled at `voxel` on a grid fixed to the camera (stages.down_sample),
        an open3d cloud in world coordinates; built once per voxel size."""
        if voxel not in self._down:
            self._down[voxel] = down_sample(self.target_pts, voxel, self.T_world_camera)
        return self._down[voxel]

    def out_of_time(self, what: str) -> bool:
        """Past the deadline: note that `what` was cut short, and say so."""
        if time.perf_counter() < self.deadline:
            return False
        if what not in self.notes:
            self.notes.append(what)
        return True

    @cached_property
    def target(self):
        """open3d PointCloud of `coarse_pts` with normals facing the camera, for the searches' coarse ICP and
        RANSAC. Built when a search first asks: the prior's fast path, the most frequent one where a caller knows
        the orientation, reads only the points (0.9 ms a frame on benchmarks/tune.py's fixed protocol)."""
        import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

        estimate_normals(self.target_cam, self.vg, self.params, np.zeros(3))  # in the camera's frame, as RANSAC's
        return o3d.geometry.PointCloud(self.target_cam).transform(self.T_world_camera)

    @cached_property
    def target_tree(self):
        """k-d tree of the coarse target's points (built once, for the coarse ICPs)."""
        return NearestTree(self.coarse_pts)

    @cached_property
    def table(self) -> tuple[np.ndarray, float] | None:
        """The plane the base stands on (table.table_plane of the observation), or None: fitted once per
        frame for the upright search and the judge."""
        obs = self.observation
        return table_plane(obs.depth, obs.mask, self.cam, self.T_world_camera, seed=self.params.seed,
                           base_size=self.base.diameter)

    @property
    def vg(self) -> float:
        """The coarse (global search) voxel."""
        return self.voxel * self.params.global_voxel_factor

    @property
    def thr(self) -> float:
        """ICP's and the fitness's correspondence distance at the fine resolution."""
        return self.params.icp_threshold_factor * self.voxel

    @property
    def cam_pos(self) -> np.ndarray:
        return self.T_world_camera[:3, 3]


def prepare_task(target_pts: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray, base: BaseObject,
                    T_base_part: np.ndarray, p: Params, voxel: float, observation: Observation,
                    deadline: float = float("inf"), light: bool = False,
                    part_symmetries: np.ndarray | None = None, camera_pts: np.ndarray | None = None) -> Task:
    """The target down-sampled (coarse: flying pixels and speckle removed; fine: its normals estimated when first
    asked for, Task.fine). Raises Degenerate when too little of it is left, or when it is a line. `light`: for scoring
    and polishing only (registration.fusion's other views): no outlier removal. `camera_pts`: the target
in the camera's frame, as PROJ3D back-projected it (target_pts carried back there otherwise, which differs
from it in the last bits)."""
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    # built in the camera's frame, then carried into the world: every step below (the voxel grids, the outlier
    # test, the normals) then gives the same points whatever the caller's world frame is
    vg = voxel * p.global_voxel_factor
    if camera_pts is None:
        camera_pts = se3.transform_points(se3.inv(T_world_camera), target_pts)
    in_camera = cloud(camera_pts)
    target_cam = in_camera.voxel_down_sample(vg)
    if len(target_cam.points) >= 40 and not light:  # flying pixels and speckle: drop points far from their neighbours
        target_cam, _ = target_cam.remove_statistical_outlier(nb_neighbors=12, std_ratio=3.0)
    if len(target_cam.points) < 10:
        raise Degenerate(f"the target is degenerate: {len(target_cam.points)} points after down-sampling to "
                         f"{vg * 1000:.2f} mm (a flat speck or a few pixels?)")
    tp = np.asarray(target_cam.points)
    if np.linalg.svd(tp - tp.mean(axis=0), compute_uv=False)[1] < 0.05 * vg:
        raise Degenerate("the target is degenerate: its points lie on a line")
    fine_cam = in_camera.voxel_down_sample(voxel)
    coarse_pts = np.asarray(o3d.geometry.PointCloud(target_cam).transform(T_world_camera).points)
    fine_pts = np.array(o3d.geometry.PointCloud(fine_cam).transform(T_world_camera).points)  # (as Task.fine carries its)
    return Task(base, T_base_part, p, cam, T_world_camera, observation, voxel, target_pts, coarse_pts, fine_pts,
                NearestTree(fine_pts), deadline, part_symmetries=part_symmetries, target_cam=target_cam,
                fine_cam=fine_cam)


def factor_of(ratio: float) -> int:
    """How many times too far (or near) a depth `ratio` times too wide looks: the power of ten when it is near one
    (a unit mixed up: mm for 0.1 mm, mm for metres), else the ratio itself, rounded."""
    k = 10 ** round(np.log10(ratio))
    return int(k) if abs(np.log10(ratio / k)) < 0.15 else int(round(ratio))


def target_span(target_pts: np.ndarray, diameter: float) -> float:
    """The target's extent over the base's `diameter`: the diagonal of its 5th-95th percentile box (a few flying
    pixels do not count). A view of a part never spans much more than its diameter (the mask may take in a little
    clutter), and rarely much less than a tenth of it. NaN without points."""
    if len(target_pts) == 0:
        return float("nan")
    lo, hi = np.percentile(target_pts, [5, 95], axis=0)
    return float(np.linalg.norm(hi - lo)) / max(diameter, 1e-9)


def scale_problem(target_pts: np.ndarray, diameter: float) -> str | None:
    """A unit error, in words, when the masked depth is far larger or smaller than the CAD could ever
    look (depth_scale off by 10 or 1000, a model in the wrong unit: `target_span` over 4 or under 0.1); None
    when the sizes are compatible."""
    ratio = target_span(target_pts, diameter)
    where = DEPTH_SCALE_WHERE
    if 4.0 < ratio:
        k = factor_of(ratio)
        return (f"the target is {ratio:.0f}x the base object's diameter ({diameter * 1000:.3g} mm): depth looks about "
                f"{k}x too far; is depth_scale {k}x too large{' (1.0 instead of 0.1?)' if k == 10 else ''} (check "
                f"{where}), or the CAD's units too small?")
    if ratio < 0.1:
        k = factor_of(1.0 / max(ratio, 1e-12))
        return (f"the target spans only {ratio:.3f}x the base object's diameter ({diameter * 1000:.3g} mm): depth looks "
                f"about {k}x too near; is depth_scale {k}x too small (check {where}), or the CAD's units too large?")
    return None
