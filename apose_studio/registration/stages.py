"""The paper's stages as functions: PROJ3D (masked depth -> world cloud), TFORM (the base moved to the
target), RCAST (what a camera sees of it), and PCDREG's pieces (normals, FPFH, RANSAC, ICP); plus the
replay's stage records. Open3D is imported where it is used."""

from __future__ import annotations

import threading

import numpy as np
from scipy.spatial import cKDTree

from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics, valid_mask_pixels
from apose_studio.geometry.metrics import fitness_rmse
from apose_studio.params import Params
from apose_studio.registration.solvers import icp_point_to_plane, icp_point_to_plane_many
from apose_studio.registration.types import Candidate, Stage

_RANSAC = threading.Lock()  # global_registration: Open3D's seeded random engine is shared by every thread


def project_to_cloud(depth: np.ndarray, mask: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray) -> np.ndarray:
    """PROJ3D: masked depth pixels (metres; 0, NaN and inf ignored) back-projected to world points (N, 3)."""
    if depth.shape != mask.shape:
        raise AposeError(f"mask is {mask.shape[1]}x{mask.shape[0]} but depth is {depth.shape[1]}x{depth.shape[0]}")
    vs, us = valid_mask_pixels(mask, depth)
    return se3.transform_points(T_world_camera, cam.backproject(us, vs, depth[vs, us]))


def cloud(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return pc


def down_sample(points: np.ndarray, voxel: float, T_world_frame: np.ndarray):
    """`points` (world) averaged per voxel of a grid fixed to the frame `T_world_frame` (the camera's), as an
    open3d cloud in world coordinates. Open3D lays its grid along the axes the points are given in; laid
    along the world's, the points kept, and so the answer, would change with where the caller's world
    frame happens to be (a renderer's, a table's, a robot's) for the same frame."""
    pc = cloud(se3.transform_points(se3.inv(T_world_frame), points)).voxel_down_sample(voxel)
    return pc.transform(T_world_frame)


def estimate_normals(pc, voxel: float, p: Params, camera_pos: np.ndarray | None) -> None:
    """Estimate normals once (oriented towards the camera when its position is known)."""
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    if not pc.has_normals():
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=p.normal_radius_factor * voxel, max_nn=30))
        if camera_pos is not None:
            pc.orient_normals_towards_camera_location(camera_pos)


def normals_fpfh(pc, voxel: float, p: Params, camera_pos: np.ndarray | None):
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    reg = o3d.pipelines.registration
    estimate_normals(pc, voxel, p, camera_pos)
    return reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=p.feature_radius_factor * voxel, max_nn=100))


def global_registration(source, target, f_source, f_target, voxel: float, p: Params) -> np.ndarray:
    """PCDREG, global part: RANSAC on FPFH matches (Open3D's, seeded with p.seed: it repeats exactly on one
    OpenMP thread, see apose_studio/__init__.py). Returns T_target_source."""
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    reg = o3d.pipelines.registration
    with _RANSAC:  # Open3D's random engine is one for the process: seeded and drawn by one estimate at a time
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
            reg.TransformationEstimationPointToPoint(False), 3, checkers, reg.RANSACConvergenceCriteria(p.ransac_max_iterations, p.ransac_confidence))
        return np.asarray(res.transformation)


def icp(source, target, T_init: np.ndarray, threshold: float, iterations: int, trace: list | None = None,
        deterministic: bool = True, target_tree=None, min_step: float = 0.0) -> np.ndarray:
    """Point-to-plane ICP, L(T) = sum ((p - T q) . n_p)^2 with target normals n_p. Returns T_target_source.

    With `trace`, appends each iteration's T (same result, for replay). `deterministic`: numpy's
    solver (the same result in every process), with `target_tree` (a k-d tree of the target's points)
    reused when given; else Open3D's (multi-threaded, not bit-repeatable). `min_step` (metres, numpy's solver only):
    also stop once a step moves the source by less than this (solvers.icp_point_to_plane).
    """
    if deterministic:
        return icp_point_to_plane(np.asarray(source.points), np.asarray(target.points), np.asarray(target.normals),
                                  T_init, threshold, iterations, trace, target_tree, min_step=min_step)
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

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


def icp_many(sources: list[np.ndarray], target, T_inits: list[np.ndarray], threshold: float, iterations: int,
             traces: list[list | None] | None = None, deterministic: bool = True, target_tree=None) -> list[np.ndarray]:
    """`icp` of each source (points, (N, 3)) from its own start onto one target: with `deterministic`, side by side
    (solvers.icp_point_to_plane_many: one k-d tree query a step for all, the same poses as one `icp` each), else
    Open3D's one at a time. `traces`: per source, a list for each iteration's T, or None."""
    traces = traces if traces is not None else [None] * len(sources)
    if deterministic:
        return icp_point_to_plane_many(sources, np.asarray(target.points), np.asarray(target.normals), T_inits, threshold,
                                       iterations, target_tree, traces)
    return [icp(cloud(s), target, T, threshold, iterations, tr, False) for s, T, tr in zip(sources, T_inits, traces)]


def stage(name, T, target, source_base, threshold) -> Stage:
    f, r = fitness_rmse(target, se3.transform_points(T, source_base), threshold)
    return Stage(name, T, f, r)


def trace_stages(T_world_source, start_name: str, T_start, trace, cand: Candidate, src_b, fine_pts, thr) -> list[Stage]:
    """The replay: initial (TFORM) -> the start ICP began from -> every ICP iteration -> final. Without a
    trace (trace_iterations=False: batch evaluation) only the final stage's fitness is computed."""
    if trace is None:
        return [Stage("initial", T_world_source, float("nan"), float("nan")),
                Stage(start_name, T_start, float("nan"), float("nan")),
                Stage("final", cand.T_world_base, cand.fitness, cand.inlier_rmse)]
    stages = [stage("initial", T_world_source, fine_pts, src_b, thr), stage(start_name, T_start, fine_pts, src_b, thr)]
    stages += [stage(f"icp {k + 1}", T, fine_pts, src_b, thr) for k, T in enumerate(trace or [])]
    return stages + [Stage("final", cand.T_world_base, cand.fitness, cand.inlier_rmse)]
