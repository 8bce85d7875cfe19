"""The paper's Alg. 1, read from the top: PROJ3D -> TFORM/RCAST -> search -> refine -> score -> compose.

`estimate` is the whole method for one frame; `estimate_default` is our pipeline after PROJ3D, each
line a named stage from the modules beside this one (the paper's own pipeline is `paper.py`).
Frames: T_<to>_<from>, metres.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .. import se3
from ..config import CameraIntrinsics
from .base import BaseObject
from .paper import estimate_paper
from .presets import Params
from .problem import Problem, prepare_problem, scale_problem
from .refine import add_symmetric_twins, choose, polish_chosen, refine_candidates, select_starts
from .results import CONFIDENT_COVERAGE, MIN_POINTS, Degenerate, RegistrationResult, failed
from .scoring import Observation, distinct_placements, mask_edge
from .searches import ModelSearch, search_poses, try_prior
from .stages import place_source, project_to_cloud, trace_stages


def estimate(depth: np.ndarray, mask: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray,
             base: BaseObject, T_base_part: np.ndarray, params: Params,
             prior_T_world_base: np.ndarray | None = None, trace_iterations: bool = True) -> RegistrationResult:
    """T_world_part for one frame. Never raises on bad data: a degenerate input gives ok=False and a reason."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if mask is None or not np.any(mask):
        return failed("empty mask: no pixels of the base object in this frame", preset=params.preset)
    target_pts = project_to_cloud(depth, mask, cam, T_world_camera)  # PROJ3D: the target cloud
    timings["proj3d"] = time.perf_counter() - t0
    if len(target_pts) < MIN_POINTS:
        return failed(f"only {len(target_pts)} valid depth points under the mask (need {MIN_POINTS}); "
                      "the base object is too small, occluded or without depth here", preset=params.preset,
                      target_cloud=target_pts, timings=timings)
    unit_error = scale_problem(target_pts, base.diameter)  # depth_scale or CAD units off by 10x, 1000x
    if unit_error is not None:
        return failed(unit_error, preset=params.preset, target_cloud=target_pts, timings=timings)
    if prior_T_world_base is None and params.use_orientation_prior:
        prior_T_world_base = np.eye(4)  # the CAD's orientation is the base's orientation in the world
    voxel = params.voxel(base.diameter)
    try:
        if params.global_source == "raycast":  # the paper: TFORM + RCAST of the CAD as oriented, then PCDREG
            return estimate_paper(target_pts, cam, T_world_camera, base, T_base_part, params, voxel,
                                  prior_T_world_base, trace_iterations, timings, preset=params.preset)
        observation = Observation(mask, depth, mask_edge(mask))
        return estimate_default(target_pts, cam, T_world_camera, base, T_base_part, params, voxel,
                                prior_T_world_base, trace_iterations, timings, observation)
    except Degenerate as e:
        return failed(str(e), target_cloud=target_pts, timings=timings, preset=params.preset, voxel=voxel)


def estimate_default(target_pts, cam, T_world_camera, base, T_base_part, p: Params, voxel, prior, trace_iterations,
                     timings: dict, observation: Observation) -> RegistrationResult:
    """Ours after PROJ3D: the prior fast path, else search -> refine -> choose -> polish -> compose."""
    t = time.perf_counter()
    pb = prepare_problem(target_pts, cam, T_world_camera, base, T_base_part, p, voxel, observation)
    if prior is not None and p.prior_fast_path:  # the caller knows the orientation: ICP from it, kept if it fits
        timings["features"] = time.perf_counter() - t
        quick = try_prior(pb, prior, trace_iterations, timings, preset=p.preset)
        if quick is not None:
            return quick
        t = time.perf_counter()
    ms = ModelSearch(pb)  # the whole model against the target: no assumption about the side seen
    timings["features"] = timings.get("features", 0.0) + time.perf_counter() - t
    t = time.perf_counter()
    R_prior = prior[:3, :3] if prior is not None else None
    T_world_source = place_source(base, pb.tp.mean(axis=0), R_prior)  # TFORM, kept as the replay's start
    found = search_poses(pb, ms, prior, T_world_source)  # upright yaw search, or free RANSAC: coarse poses
    timings["global"] = time.perf_counter() - t
    t = time.perf_counter()
    refined = refine_candidates(pb, select_starts(found, voxel, p.use_symmetries), trace_iterations)  # RCAST + ICP
    if p.use_symmetries and refined:
        add_symmetric_twins(pb, refined)
    timings["icp"] = time.perf_counter() - t
    if not refined:
        raise Degenerate("the camera cannot see the base mesh at any candidate pose")
    chosen, close = choose(pb, refined, R_prior)  # scored; near-ties looked at where the placements differ
    if p.polish_voxel_factor > 0:
        t = time.perf_counter()
        polish_chosen(pb, refined, chosen)
        timings["icp"] += time.perf_counter() - t
    result = compose(pb, refined, chosen, close, T_world_source, timings)  # T_world_part = T_world_base @ T_base_part
    if found.upright and not result.confident:  # a table is seen, but the base does not stand on it as modelled
        return better_of_free_search(result, target_pts, pb, prior, trace_iterations, timings)
    return result


def compose(pb: Problem, refined: list, chosen: int, close: list[int], T_world_source: np.ndarray,
            timings: dict) -> RegistrationResult:
    """The result: the chosen pose and its part pose, the replay, every candidate (best first), and the
    other placements that fit as well when the result is ambiguous."""
    cands = [r.candidate for r in refined]
    c, r = cands[chosen], refined[chosen]
    src_b = se3.transform_points(se3.inv(c.T_world_base), r.seen)
    stages = trace_stages(T_world_source, "global", r.T_start, r.trace, c, src_b, pb.fine_pts, pb.thr)
    order = sorted(range(len(cands)), key=lambda i: -cands[i].score)
    placements = distinct_placements([c] + [cands[i] for i in close if i != chosen], pb.voxel)
    ambiguous = bool(len(placements) > 1 and c.coverage >= CONFIDENT_COVERAGE)
    return RegistrationResult(True, "", c.T_world_base, c.T_world_part, T_world_source, pb.fine_pts, src_b, stages,
                              c.fitness, c.inlier_rmse, timings, [cands[i] for i in order], ambiguous,
                              placements[1:] if ambiguous else [], voxel=pb.voxel, coverage=float(c.coverage),
                              preset=pb.params.preset)


def better_of_free_search(result: RegistrationResult, target_pts, pb: Problem, prior, trace_iterations,
                          timings: dict) -> RegistrationResult:
    """The base lies on its side, is held in a hand or sits on a fixture: search freely too, keep the
    better of the two, and count the time of both."""
    free_timings: dict[str, float] = {}
    free = estimate_default(target_pts, pb.cam, pb.T_world_camera, pb.base, pb.T_base_part,
                            replace(pb.params, upright=False), pb.voxel, prior, trace_iterations, free_timings,
                            pb.observation)
    for k, v in timings.items():
        free_timings[k] = free_timings.get(k, 0.0) + v
    if free.coverage > result.coverage:
        return free
    result.timings = free_timings
    return result
