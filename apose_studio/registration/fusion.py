"""Several views of one placement of the base, with known camera poses (an eye-in-hand camera's looks):
one estimate that every view's depth agrees with.

1. The view with the most masked depth is estimated as usual (`pipeline.estimate`): its candidates,
   with the twins of the best under every symmetry and close twin, are the placements to weigh.
2. Every other view is prepared as its own registration problem (its cloud, its camera, its mask and
   depth) and checked against the first: at the first view's pose it must explain most of its own
   target, and ICP on it alone must not move that pose by more than 3 voxels or 3 degrees. Otherwise
   the camera poses disagree (or the base moved between the looks): the result fails and says which
   view and by how much; nothing is fused blindly.
3. Each placement is scored in every view (the score each view gives it, weighted by its target
   points). Near-ties are looked at where the placements differ, view by view: a placement that a
   view tells apart clearly (the connector seen in one view, hidden in the other) loses.
4. The chosen pose gets a last ICP on the fused cloud (every view's target, world frame) onto what
   each camera sees of the model.

Frames: T_<to>_<from>, metres.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from apose_studio.geometry import se3
from apose_studio.params import Params
from apose_studio.registration.base import BaseObject, raycast_source
from apose_studio.registration.pipeline import estimate, judge, observe
from apose_studio.registration.refine import POLISH_ITERATIONS, polish, refine_and_polish, tied
from apose_studio.registration.scoring import discriminate, distinct_placements, poses_within, score_pose, twin_placements
from apose_studio.registration.stages import cloud, icp, project_to_cloud
from apose_studio.registration.task import Task, prepare_task
from apose_studio.registration.types import CONFIDENT_COVERAGE, MIN_POINTS, Degenerate, RegistrationResult, View, failed

DISAGREE_DEGREES = 3.0  # a view whose own ICP turns the pose further than this disagrees with the others
DISAGREE_VOXELS = 3.0  # ... or moves it further than this many voxels
DISAGREE_COVERAGE = 0.5  # ... or of whose target the pose explains less than this share


def estimate_views(views: list[View], base: BaseObject, T_base_part: np.ndarray, params: Params,
                   prior_T_world_base: np.ndarray | None = None,
                   part_symmetries: np.ndarray | None = None) -> RegistrationResult:
    """T_world_part from several views of one placement (see the module's docstring). Never raises on
    bad data: disagreeing camera poses or a view without depth give ok=False and a reason.
    `part_symmetries`: as for `pipeline.estimate`."""
    if len(views) == 1:
        return estimate(views[0], base, T_base_part, params, prior_T_world_base, part_symmetries=part_symmetries)
    t0 = time.perf_counter()
    counts = [int((v.mask & (v.depth > 0)).sum()) for v in views]
    order = sorted(range(len(views)), key=lambda i: -counts[i])
    first_view = views[order[0]]
    first = estimate(first_view, base, T_base_part, params, prior_T_world_base, part_symmetries=part_symmetries)
    if not first.ok:
        return replace(first, reason=f"{_name(first_view, order[0])}: {first.reason}")
    t1 = time.perf_counter()
    problems = {order[0]: first.problem if first.problem is not None else
                _problem(first_view, base, T_base_part, params, first.voxel)}
    for i in order[1:]:
        try:
            problems[i] = _problem(views[i], base, T_base_part, params, first.voxel)
        except Degenerate as e:
            return failed(f"{_name(views[i], i)}: {e}", preset=params.preset, timings=first.timings)
    # the camera poses must agree at one of the first view's placements: its chosen one, or (when it is not
    # confident: a coin flip between twins) one of its rivals; the other views then weigh them all (_weigh)
    disagreement, at_first = "", None
    for T in _placements(first, base):
        at = {i: score_pose(problems[i], T) for i in order}  # each view at this pose of the first
        why = _disagreement(problems, order, T, first.voxel, views, at)
        if not why:
            if T is not first.T_world_base:
                first = replace(first, T_world_base=T, T_world_part=T @ T_base_part)
            at_first = at
            break
        disagreement = disagreement or why
    if at_first is None:
        return failed(disagreement + "; the views are not fused", preset=params.preset, timings=first.timings,
                      T_world_base=first.T_world_base, T_world_part=first.T_world_part)
    result = _weigh(first, problems, order, base, at_first, part_symmetries)
    t2 = time.perf_counter()
    return replace(result, timings={**first.timings, "fusion": t2 - t1, "total fused": t2 - t0}, views=len(views))


def _name(view: View, i: int) -> str:
    return view.name or f"view {i + 1}"


def _problem(view: View, base: BaseObject, T_base_part: np.ndarray, params: Params, voxel: float) -> Task:
    camera_pts = project_to_cloud(view.depth, view.mask, view.camera, np.eye(4))
    if len(camera_pts) < MIN_POINTS:
        raise Degenerate(f"only {len(camera_pts)} valid depth points under its mask (need {MIN_POINTS})")
    return prepare_task(se3.transform_points(view.T_world_camera, camera_pts), view.camera, view.T_world_camera, base,
                        T_base_part, params, voxel, observe(view.depth, view.mask), light=True, camera_pts=camera_pts)


def _disagreement(problems: dict[int, Task], order: list[int], T_world_base: np.ndarray, voxel: float,
                  views: list[View], at_first: dict) -> str:
    """Why the views cannot be of one placement seen from the given camera poses ("" when they can).
    `at_first`: view -> score_pose of the first view's pose there."""
    for i in order[1:]:
        pb = problems[i]
        cand, seen, normals = at_first[i]
        if cand.coverage < DISAGREE_COVERAGE:
            return (f"{_name(views[i], i)} disagrees with {_name(views[order[0]], order[0])}: at the pose that view "
                    f"gives, the model explains only {cand.coverage:.0%} of its target; are both camera poses "
                    "(cam_R_w2c, cam_t_w2c) in one world frame, and did the base stay put between the looks?")
        # ICP on this view alone (a few voxels' reach): the pose it pulls to
        T, _ = polish(replace(pb, params=replace(pb.params, polish_threshold_factor=3.0, polish_voxel_factor=1.0)),
                      T_world_base, None, (seen, normals))
        D = se3.inv(T_world_base) @ T
        moved, turned = float(np.linalg.norm(D[:3, 3])), se3.rotation_angle_deg(D[:3, :3])
        if moved > DISAGREE_VOXELS * voxel or turned > DISAGREE_DEGREES:
            return (f"{_name(views[i], i)} disagrees with {_name(views[order[0]], order[0])} by {moved * 1000:.1f} mm "
                    f"and {turned:.1f} degrees at the base; are both camera poses in one world frame, and did the "
                    "base stay put between the looks?")
    return ""


WEIGH_MARGIN = 0.15  # the first view's placements scoring within this of its best are weighed in every view
WEIGH_MAX = 6


def _placements(first: RegistrationResult, base: BaseObject) -> list[np.ndarray]:
    """The first view's placements (T_world_base) that every view weighs: its chosen one first; when it is
    not confident, also its rivals within WEIGH_MARGIN (at most WEIGH_MAX) and every twin of the chosen
    (the paper's pipeline keeps no candidates: its one pose is weighed)."""
    voxel = first.voxel
    poses = [first.T_world_base]
    if not first.confident and first.candidates:  # a confident first view stands (one placement fits it)
        top = max(c.score for c in first.candidates)
        placements = [c for c in distinct_placements(first.candidates, voxel) if c.score >= top - WEIGH_MARGIN]
        for T in [c.T_world_base for c in placements[:WEIGH_MAX]] + [
                first.T_world_base @ S for S in list(base.symmetries[1:]) + list(base.close_twins)]:
            if not any(poses_within(T, P, voxel, 2.0) for P in poses):
                poses.append(T)
    return poses


def _weigh(first: RegistrationResult, problems: dict[int, Task], order: list[int],
           base: BaseObject, at_first: dict, part_symmetries: np.ndarray | None = None) -> RegistrationResult:
    """The first view's placements scored in every view; the chosen one polished on the fused cloud."""
    voxel = first.voxel
    pb0 = problems[order[0]]
    poses = _placements(first, base)
    # a rival the first view derived by a close twin's turn (a few degrees off the turn that fits) is fitted to
    # the first view before any view weighs it, as the single view fits its own close twins (refine._add_twins_of):
    # left as turned, a block's true placement scored 0.966 against 0.993 in the first view, was dropped there, and
    # the one placement left standing in both views, a wrong one, came out confident
    poses = poses[:1] + refine_and_polish(pb0, poses[1:])
    weights = {i: len(problems[i].fine_pts) for i in order}
    total = float(sum(weights.values()))
    per_view = {i: [at_first[i] if k == 0 else score_pose(problems[i], T) for k, T in enumerate(poses)]
                for i in order}  # (candidate, seen, normals); poses[0] is the first view's pose
    cands = []
    for k in range(len(poses)):
        c = per_view[order[0]][k][0]
        score = sum(weights[i] * per_view[i][k][0].score for i in order) / total
        cov = min(per_view[i][k][0].coverage for i in order)
        cands.append(replace(c, score=score, coverage=cov))
    close = tied(base, cands, voxel)
    lost: set[int] = set()
    if len(close) > 1:
        for i in order:  # each view looks where the placements differ
            traces = [(None, None, per_view[i][k][1], per_view[i][k][2]) for k in range(len(poses))]
            kept = discriminate(problems[i], close, [per_view[i][k][0] for k in range(len(poses))], traces)
            lost |= set(close) - set(kept)
    kept = [k for k in close if k not in lost] or close
    chosen = max(kept, key=lambda k: cands[k].score)
    seen = {i: per_view[i][chosen][1:] for i in order}
    T = fused_polish(problems, order, poses[chosen], voxel, seen)
    final = cands[chosen]  # scored before the fused polish, which moves the pose by a fraction of a voxel
    ranked = sorted(range(len(cands)), key=lambda k: -cands[k].score)
    rivals = distinct_placements([cands[chosen]] + [cands[k] for k in kept if k != chosen], voxel, base.symmetries,
                                 part_symmetries)
    ambiguous = bool(len(rivals) > 1 and cands[chosen].coverage >= CONFIDENT_COVERAGE)
    result = replace(first, T_world_base=T, T_world_part=T @ pb0.T_base_part, candidates=[cands[k] for k in ranked],
                     ambiguous=ambiguous, alternatives=rivals[1:] if ambiguous else [],
                     coverage=float(final.coverage), fitness=final.fitness,
                     inlier_rmse=final.inlier_rmse, second_look=None, model_mask=None)
    obs = pb0.observation
    result = judge(result, View(obs.depth, obs.mask, pb0.cam, pb0.T_world_camera), base)
    return replace(result, equivalent=twin_placements(T, result.T_world_part, base.symmetries) if result.ok else [])


def fused_polish(problems: dict[int, Task], order: list[int], T_world_base: np.ndarray, voxel: float,
                 seen: dict | None = None) -> np.ndarray:
    """The last refinement on every view at once: all targets (world), down-sampled at the voxel (twice
    the points of one view at half of it, as `refine.polish` uses),
    registered onto what each camera sees of the model at T_world_base (point-to-plane, the model's
    normals), as `refine.polish` does for one view. `seen`: view -> (world points, normals) already cast."""
    T_base_world = se3.inv(T_world_base)
    tgt, src, nrm = [], [], []
    for i in order:
        pb = problems[i]
        w, n = seen[i] if seen is not None else raycast_source(pb.base, T_world_base, pb.T_world_camera, pb.cam)
        if len(w) < MIN_POINTS:
            continue
        src.append(se3.transform_points(T_base_world, w))
        nrm.append(n @ T_base_world[:3, :3].T)
        tgt.append(np.asarray(pb.target_at(voxel).points))
    if not src:
        return T_world_base
    model = cloud(np.concatenate(src), np.concatenate(nrm)).voxel_down_sample(0.5 * voxel)
    p = problems[order[0]].params
    T = icp(cloud(np.concatenate(tgt)), model, T_base_world, p.polish_threshold_factor * voxel, POLISH_ITERATIONS,
            None, p.deterministic)
    return se3.inv(T)
