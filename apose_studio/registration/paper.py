"""The paper's pipeline as published (preset `paper`): translate the CAD to the target's centre (its
orientation trusted), ray-cast it from the camera (RCAST), FPFH + RANSAC, then ICP."""

from __future__ import annotations

import time

import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.nn import NearestTree
from apose_studio.params import Params
from apose_studio.registration.base import place_source, raycast_source
from apose_studio.registration.stages import cloud, global_registration, icp, normals_fpfh, stage
from apose_studio.registration.types import MIN_POINTS, Candidate, Degenerate, RegistrationResult


def estimate_paper(target_pts, cam, T_world_camera, base, T_base_part, p: Params, voxel, prior, trace_iterations,
                   timings, **kw) -> RegistrationResult:
    """The authors' pipeline: translate the CAD to the target, ray-cast it, FPFH + RANSAC, ICP."""
    t = time.perf_counter()
    centre = target_pts.mean(axis=0)
    R_prior = prior[:3, :3] if prior is not None else None
    T_world_source = place_source(base, centre, R_prior)
    src_world, _ = raycast_source(base, T_world_source, T_world_camera, p.source_camera or cam, look_at=centre)
    timings["rcast"] = time.perf_counter() - t
    if len(src_world) < MIN_POINTS:
        raise Degenerate("the camera cannot see the base mesh placed at the target (ray-cast gave "
                          f"{len(src_world)} points)")
    src_base = se3.transform_points(se3.inv(T_world_source), src_world)
    t = time.perf_counter()
    source, target = cloud(src_world), cloud(target_pts)
    if p.downsample:
        source, target = source.voxel_down_sample(voxel), target.voxel_down_sample(voxel)
    cam_pos = T_world_camera[:3, 3]
    f_s = normals_fpfh(source, voxel, p, cam_pos)
    f_t = normals_fpfh(target, voxel, p, cam_pos)
    timings["features"] = time.perf_counter() - t
    t = time.perf_counter()
    T_g = global_registration(source, target, f_s, f_t, voxel, p)
    timings["global"] = time.perf_counter() - t
    t = time.perf_counter()
    trace: list | None = [] if trace_iterations else None
    T_i = icp(source, target, T_g, p.icp_threshold_factor * voxel, p.icp_max_iterations, trace,
              p.deterministic)
    timings["icp"] = time.perf_counter() - t
    thr = p.icp_threshold_factor * voxel
    T_world_base = T_i @ T_world_source
    stages = [stage("initial", T_world_source, target_pts, src_base, thr),
              stage("global", T_g @ T_world_source, target_pts, src_base, thr)]
    stages += [stage(f"icp {k + 1}", T @ T_world_source, target_pts, src_base, thr) for k, T in enumerate(trace or [])]
    final = stage("final", T_world_base, target_pts, src_base, thr)
    stages.append(final)
    T_world_part = T_world_base @ T_base_part
    # coverage as ours reports it: the share of target points within 2 voxels of the model as the camera sees it
    seen = se3.transform_points(T_world_base, src_base)
    coverage = float(np.mean(NearestTree(seen).query(target_pts, distance_upper_bound=max(thr, 2 * voxel))[0] < np.inf))
    cand = Candidate(T_world_base, T_world_part, final.fitness, float("nan"), final.inlier_rmse, final.fitness, 0,
                     coverage)
    return RegistrationResult(ok=True, T_world_base=T_world_base, T_world_part=T_world_part,
                              T_world_source=T_world_source, target_cloud=target_pts, source_cloud=src_base,
                              stages=stages, fitness=final.fitness, inlier_rmse=final.inlier_rmse, timings=timings,
                              candidates=[cand], voxel=voxel, coverage=coverage, **kw)
