"""The paper's Alg. 1, read from the top: PROJ3D -> TFORM/RCAST -> search -> refine -> score -> compose.

`estimate` is the whole method for one frame; `estimate_default` is our pipeline after PROJ3D, each
line a named stage from the modules beside this one (the paper's own pipeline is `paper.py`).
Frames: T_<to>_<from>, metres.
"""

from __future__ import annotations

import time
from dataclasses import replace

import cv2
import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.camera import box_region, mask_pixels
from apose_studio.geometry.nn import NearestTree
from apose_studio.geometry.noise import estimate_depth_noise
from apose_studio.geometry.raycast import raycast_depth
from apose_studio.geometry.sensor import nearest_within, quantisation_step
from apose_studio.params import Params
from apose_studio.registration.base import BaseObject, place_source, raycast_source
from apose_studio.registration.hypotheses import both_out, explained, readings
from apose_studio.registration.paper import estimate_paper
from apose_studio.registration.refine import (
    add_chosen_twins,
    add_symmetric_twins,
    base_twins_alike,
    choose,
    neighbour_rivals,
    polish_chosen,
    polish_contenders,
    refine_candidates,
    select_starts,
    settle,
)
from apose_studio.registration.scoring import (
    agreement_tolerance,
    depth_window,
    distinct_placements,
    evidence,
    hidden_share,
    mask_edge,
    pose_spread,
    poses_within,
    score_pose,
    twin_placements,
)
from apose_studio.registration.searches import ModelSearch, search_poses, try_prior
from apose_studio.registration.side_by_side import in_order
from apose_studio.registration.stages import project_to_cloud, trace_stages
from apose_studio.registration.table import table_plane
from apose_studio.registration.task import Task, prepare_task, scale_problem, target_span
from apose_studio.registration.types import (
    CONFIDENT_CONTRADICTION,
    CONFIDENT_COVERAGE,
    CONFIDENT_SPREAD,
    MIN_POINTS,
    Degenerate,
    Found,
    Observation,
    RegistrationResult,
    Stage,
    Start,
    View,
    failed,
    span_hint,
)


def estimate(view: View, base: BaseObject, T_base_part: np.ndarray, params: Params,
             prior_T_world_base: np.ndarray | None = None, trace_iterations: bool = True,
             part_symmetries: np.ndarray | None = None) -> RegistrationResult:
    """T_world_part for one view (its depth, the base's mask, the camera and its pose). Never raises on bad
    data: a degenerate input gives ok=False and a reason. `part_symmetries`: the part's own (T_part_part,
    identity first; PartModel.symmetries): placements of the part that differ by one of them are the same
    placement, so they make no ambiguity.

    The mask as given first; when that estimate does not fit (and `params.mask_hypotheses`), the
    mask's other readings too (hypotheses.readings: without what lies on the base, without what stands
    in front), and the estimate whose model explains the frame best is returned (its `reading` names
    the mask it came from). A confident result also says whether the base's own turn is sure
    (`base_alternatives`: refine.base_twins_alike)."""
    result = estimate_readings(view, base, T_base_part, params, prior_T_world_base, trace_iterations, part_symmetries)
    if not result.confident and not result.input_error and view.mask is not None and view.mask.any():
        result = spanned(result, view, base)
    pb = result.problem
    if not (result.ok and result.confident and isinstance(pb, Task) and params.use_symmetries):
        return result
    t = time.perf_counter()
    alternatives = base_twins_alike(pb, result.T_world_base)
    return replace(result, base_alternatives=alternatives,
                   timings={**result.timings, "base twins": time.perf_counter() - t})


def spanned(result: RegistrationResult, view: View, base: BaseObject) -> RegistrationResult:
    """`result` (not confident, or failed) with `target_span` of the whole mask's depth (not only of the reading that
    won: a reading may leave out what made the mask too wide), and, when it failed and the mask spans more than any
    view of the base or very little of it, the reason saying where to look (`types.span_hint`)."""
    pts = project_to_cloud(view.depth, view.mask, view.camera, np.eye(4))
    span = target_span(pts, base.diameter) if len(pts) >= MIN_POINTS else float("nan")
    result = replace(result, target_span=span)
    hint = span_hint(span)
    if not result.ok and hint and result.reason:
        result = replace(result, reason=f"{result.reason}; {hint}")
    return result


def estimate_readings(view: View, base: BaseObject, T_base_part: np.ndarray, params: Params,
                      prior_T_world_base: np.ndarray | None = None, trace_iterations: bool = True,
                      part_symmetries: np.ndarray | None = None) -> RegistrationResult:
    """`estimate` but the base's twins: the mask as given, then its other readings when that does not fit.

    The mask as given is searched upright first; the free search it may be due after that (the upright pose does not
    fit) runs only when no reading of the mask is confident: a box prompt's mask that also holds what lies on or
    beside the base fits no pose, upright or free, and one of its readings settles it (an outside tester's desk
    capture: the free search and its second look, 1.1 s, left it unconfident; the first reading settled it). Where no
    reading is confident it runs then, and its result is weighed against the best reading's (docs/ESTIMATOR.md)."""
    hypotheses = params.mask_hypotheses and params.global_source != "raycast"
    deferred: list = []
    first = estimate_mask(view, base, T_base_part, params, prior_T_world_base, trace_iterations, part_symmetries,
                          deferred=deferred if hypotheses else None)
    if first.fits or not hypotheses:  # confident, or only ambiguous: a view problem that no reading can settle
        return settled(deferred[0]() if deferred else first, view, base, T_base_part, params, part_symmetries)
    t = time.perf_counter()
    table = table_plane(view.depth, view.mask, view.camera, view.T_world_camera, seed=params.seed,
                        base_size=base.diameter) if params.upright else None
    tol = agreement_tolerance(params.voxel(base.diameter), first.depth_noise)
    todo = readings(view, base, table, tol)
    region = np.logical_or.reduce([view.mask, *(m for _, m in todo)])  # every pixel some reading holds
    first_score = explained(first, view, base, region)
    best, best_score, best_mask = first, first_score, view.mask
    # each reading once, upright where a table is seen; the chosen one gets the second look below
    quick = replace(params, second_look=False, free_after_upright=table is None)

    def estimated(reading: tuple[str, np.ndarray]) -> RegistrationResult:
        return estimate_mask(replace(view, mask=reading[1]), base, T_base_part, quick, prior_T_world_base,
                             trace_iterations, part_symmetries)

    for round_ in range(2):
        # side by side on params.threads, taken in this order: the same answer as one after the other
        with in_order(estimated, todo, params.threads) as others:
            for (name, mask), other in zip(todo, others):
                score = explained(other, view, base, region)
                if (other.ok, uncontradicted(other), score) > (best.ok, uncontradicted(best), best_score):
                    best, best_score, best_mask = replace(other, reading=name), score, mask
                if best.confident and best_score >= first_score:
                    break  # a confident reading that explains the frame at least as well: the others cannot do better
        if round_ or best.confident:
            break
        if best is first:  # no reading beat the mask as given: each may have left out one of two things; both out
            todo = both_out(todo)
            continue
        # a mask with two things in it (a tin on the base and a box in front): the best reading read again, by
        # depth only (hypotheses.py: what colour splits now is mostly the base's own colours)
        prefix = best.reading
        todo = [(f"{prefix}, {name}", m) for name, m in readings(replace(view, mask=best_mask), base, table, tol,
                                                                  colour=False, box=False)]
    as_given = best is first  # the mask as given: its second look is done
    t_free = 0.0
    if deferred and not best.confident:  # no reading settled it: the mask as given, searched freely too
        t_free = time.perf_counter()
        full = deferred[0]()
        t_free = time.perf_counter() - t_free
        if as_given or full.fits or (full.ok, uncontradicted(full), explained(full, view, base, region)) > \
                (best.ok, uncontradicted(best), best_score):
            best, best_mask, as_given = full, view.mask, True
    if not as_given and best.ok and not best.confident and params.second_look:
        best = replace(second_look(best, replace(view, mask=best_mask), base, T_base_part, params, prior_T_world_base,
                                   trace_iterations, part_symmetries), reading=best.reading)
    seconds = time.perf_counter() - t - t_free
    best = replace(best, timings={**best.timings, "other readings": seconds})
    return settled(best, replace(view, mask=best_mask), base, T_base_part, params, part_symmetries, region)


def uncontradicted(result: RegistrationResult) -> bool:
    """The depth contradicts (sees past) no more of what the model shows than a confident result allows. Among the
    readings of a mask, such a result beats one the depth contradicts, whatever each explains: a pose raised onto
    a plate lying on the base explains the plate's pixels too, and only its sides, seen past, give it away."""
    return bool(result.ok and not result.contradiction > CONFIDENT_CONTRADICTION)


SETTLE_SIGMAS = 1.5  # settled: what lies more than this many sigmas of the depth's noise (at least a voxel) in front of
# the model's surface is left out


def settled(result: RegistrationResult, view: View, base: BaseObject, T_base_part: np.ndarray, params: Params,
            part_symmetries: np.ndarray | None = None, region: np.ndarray | None = None) -> RegistrationResult:
    """`result`, or, where it is not confident and the depth contradicts it (params.settle), its pose refitted on the
    view's mask without the depth lying in front of the model's surface (refine.settle: something lying on the base,
    one depth patch with it, tilts the fit towards itself, and the camera then sees past the model's sides), judged
    as any pose; the refitted one is kept when it explains the frame better, as the mask's readings are compared
    (`uncontradicted` first, then `explained` over `region`, default the view's mask). Its rivals (`ambiguous`,
    `alternatives`) are the result's: the refit moves the pose by millimetres, not to another placement. Not for a
    region of a larger part: the rest of that part lies in front of the region's surface by nature, and its
    estimate is judged by what hides it (`sunk`) and by the rest of the part (`body_past`)."""
    if not (params.settle and base.region is None and result.ok and not result.confident
            and result.contradiction > CONFIDENT_CONTRADICTION):
        return result
    t = time.perf_counter()
    out = result
    pb = view_task(view, base, T_base_part, params, part_symmetries, noise=result.depth_noise)
    T = settle(pb, result.T_world_base, max(pb.voxel, SETTLE_SIGMAS * result.depth_noise)) if pb is not None else None
    if T is not None:
        cand, seen, _ = score_pose(pb, T)
        moved = replace(result, T_world_base=T, T_world_part=cand.T_world_part, target_cloud=pb.fine_pts,
                        source_cloud=se3.transform_points(se3.inv(T), seen), fitness=cand.fitness,
                        inlier_rmse=cand.inlier_rmse, coverage=cand.coverage, candidates=[cand, *result.candidates],
                        stages=[*result.stages, Stage("settled", T, cand.fitness, cand.inlier_rmse)], problem=pb,
                        model_mask=None, second_look=None)
        again = judged(moved, view, base, params, pb.table)
        if (again.ok, uncontradicted(again), explained(again, view, base, region)) > \
                (result.ok, uncontradicted(result), explained(result, view, base, region)):
            out = replace(again, model_mask=cut_to_model(again, view, base))
    return replace(out, timings={**out.timings, "settle": time.perf_counter() - t})


def estimate_mask(view: View, base: BaseObject, T_base_part: np.ndarray, params: Params,
                  prior_T_world_base: np.ndarray | None = None, trace_iterations: bool = True,
                  part_symmetries: np.ndarray | None = None, starts: list | None = None,
                  deferred: list | None = None) -> RegistrationResult:
    """`estimate` on the view's mask as it is: PROJ3D, the searches, the judge, the second look. `starts`
    ((score, T_world_base), best first; first_look_starts): refine these instead of searching (the second look's).
    `deferred` (a list): where the upright pose does not fit and the free search after it is due, that search is not
    run; a function is appended that runs it and returns the result it gives (estimate_readings calls it only when no
    reading of the mask is confident)."""
    depth, mask, cam, T_world_camera = view.depth, view.mask, view.camera, view.T_world_camera
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if mask is None or not np.any(mask):
        return failed("empty mask: no pixels of the base object in this frame", preset=params.preset)
    camera_pts = project_to_cloud(depth, mask, cam, np.eye(4))  # PROJ3D: the target cloud, in the camera's frame
    target_pts = se3.transform_points(T_world_camera, camera_pts)
    timings["proj3d"] = time.perf_counter() - t0
    if len(target_pts) < MIN_POINTS:
        return failed(f"only {len(target_pts)} valid depth points under the mask (need {MIN_POINTS}); "
                      "the base object is too small, occluded or without depth here", preset=params.preset,
                      target_cloud=target_pts, timings=timings)
    unit_error = scale_problem(target_pts, base.diameter)  # depth_scale or CAD units off by 10x, 1000x
    if unit_error is not None and mask.mean() > 0.5:  # not a unit error: the mask holds the whole scene
        unit_error = (f"the mask covers {100 * mask.mean():.0f}% of the image and spans far more than the base object "
                      f"({base.diameter * 1000:.3g} mm across); prompt a box around the object, or check the mask file")
    if unit_error is not None:
        return failed(unit_error, preset=params.preset, target_cloud=target_pts, timings=timings, input_error=True)
    if prior_T_world_base is None and params.use_orientation_prior:
        prior_T_world_base = np.eye(4)  # the CAD's orientation is the base's orientation in the world
    voxel = params.voxel(base.diameter)
    deadline = t0 + params.max_seconds if params.max_seconds > 0 else float("inf")
    observation = observe(depth, mask)
    noise = observation.noise
    pb, free_due = None, False
    try:
        if params.global_source == "raycast":  # the paper: TFORM + RCAST of the CAD as oriented, then PCDREG
            result = estimate_paper(target_pts, cam, T_world_camera, base, T_base_part, params, voxel,
                                    prior_T_world_base, trace_iterations, timings, preset=params.preset)
        else:
            t = time.perf_counter()
            pb = prepare_task(target_pts, cam, T_world_camera, base, T_base_part, params, voxel, observation, deadline,
                              part_symmetries=part_symmetries, camera_pts=camera_pts)
            timings["features"] = time.perf_counter() - t
            result, free_due = search_and_choose(pb, prior_T_world_base, trace_iterations, timings, starts)
            if free_due and not params.second_look:  # nothing to try before the free search
                result, free_due = better_of_free_search(result, pb, prior_T_world_base, trace_iterations)[0], False
    except Degenerate as e:
        return failed(str(e), target_cloud=target_pts, timings=timings, preset=params.preset, voxel=voxel)

    def supported(r: RegistrationResult) -> RegistrationResult:
        """ok only when the data supports the pose (the table fitted once per frame, where the search fitted
        it), with the base's exact twins; then, not confident, the second look, but for a result that fits and is
        ambiguous (another placement fits as well): it explains most of its mask already, and the cut, one placement's
        view, seldom tells its twins apart (captures.py, 528 frames: of the 79 second looks on an ambiguous result, 1
        came back confident, at 12.6 s in all; docs/BENCHMARKS.md). A region of a larger part keeps it: its mask is
        the box's depth, much of it the rest of the part, which the cut takes out (on the engine head's seats under
        Kinect-like noise it made 2 of 45 right, ambiguous views confident: benchmarks/seats.py). (The best of the
        mask's other readings keeps its second look whenever it is not confident: estimate_readings.)"""
        r = judged(replace(r, depth_noise=noise), view, base, params, pb.table if pb is not None else _FIT)
        if params.second_look and r.ok and not r.confident and not (r.fits and r.ambiguous and base.region is None):
            r = second_look(r, view, base, T_base_part, params, prior_T_world_base, trace_iterations, part_symmetries)
        return r

    upright, result = result, supported(result)

    def with_free_search(result: RegistrationResult) -> RegistrationResult:
        try:
            free, won = better_of_free_search(upright, pb, prior_T_world_base, trace_iterations)
        except Degenerate:  # the free search saw nothing: the upright pose stands
            free, won = upright, False
        # the time of both searches, and of the upright pose's second look
        return supported(replace(free, timings={**result.timings, **free.timings})) if won else \
            replace(result, timings={**result.timings, **free.timings})

    def with_cut(result: RegistrationResult) -> RegistrationResult:
        if not result.ok:
            return result
        t = time.perf_counter()
        cut = cut_to_model(result, view, base)
        return replace(result, model_mask=cut, timings={**result.timings, "mask cut": time.perf_counter() - t})

    if free_due and not result.confident:  # the upright pose did not fit, and its second look did not settle it
        if deferred is not None:
            before = result
            deferred.append(lambda: with_cut(with_free_search(before)))
        else:
            result = with_free_search(result)
    return with_cut(result)


def cut_to_model(result: RegistrationResult, view: View, base: BaseObject) -> np.ndarray | None:
    """The result's `model_mask`: its mask (the second look's where that gave it) cut to the model's view at its pose
    (model_cut_mask, within the prompt's box or the mask's reach), or None when fewer than MIN_POINTS pixels are left."""
    cut = model_cut_mask(result, view if result.second_look is None else replace(view, mask=result.second_look), base,
                         reach=mask_reach(view))
    return cut if cut.sum() >= MIN_POINTS else None


def model_cut_mask(result: RegistrationResult, view: View, base: BaseObject,
                   reach: np.ndarray | None = None) -> np.ndarray:
    """The mask cut to what the model shows at the result's pose: pixels inside its silhouette (2 px
    wider, for the second look, which registers on it: a pose a little off keeps the base's outline), and
    not in front of its surface by more than the agreement tolerance (an occluder). With `reach` ((H, W)
    bool: `mask_reach(view)`), the result's mask: the silhouette exactly (clutter touching the base lies
    in the 2 px), and the pixels there that the mask missed added where the depth lies on the model's
    surface (within the tolerance) or where there is no depth and the nearest depth does (like_nearest_depth):
    what the model shows, not only the share of it the prompt caught. With a colour image, what the depth cannot
    place there (a pixel without depth, the mask's own too, or one the mask missed) stays only where its colour is
    the base's rather than that of what stands in front (as_common_in).

    Every ok result carries it (`model_mask`): on 240 cluttered renders with box prompts
    (benchmarks/captures.py, Kinect-like noise) the cut raised the mask IoU against the renderer's masks
    from 0.85 to 0.93. The exact silhouette and the pixels added back (prompted masks there miss about
    5 % of the base) raised it over its 528 frames from 0.868 to 0.908, and with a flat object on the
    base from 0.809 to 0.868; the holes added back, from 0.914 to 0.925, 0.880 to 0.896 with the flat object,
    0.706 to 0.750 for a mostly hidden base; their colour, from 0.930 to 0.936, 0.896 to 0.913 with the flat object
    (docs/BENCHMARKS.md). The second look registers on the cut alone: pixels
    added for agreeing with the pose would only confirm it."""
    depth, mask, cam, T_world_camera = view.depth, view.mask, view.camera, view.T_world_camera
    seen, _ = raycast_source(base, result.T_world_base, T_world_camera, cam)
    # the window of the image the model shows, 3 px wider than the 2 px the silhouette is widened by: nothing
    # below is true outside it, so the cut is the whole image's
    z, box = depth_window(seen, T_world_camera, cam, 3)
    cut = np.zeros(mask.shape, bool)
    if box is None:
        return cut
    win = np.s_[box[0]:box[1], box[2]:box[3]]
    z = z.astype(np.float32)
    zbuf = z if reach is not None else nearest_within(z, 2)  # 2 px wider, the nearer surface winning
    tol = agreement_tolerance(result.voxel, result.depth_noise)
    d = depth[win]
    with np.errstate(invalid="ignore"):
        in_front = (d > 0) & (d < zbuf - tol)
        cut[win] = mask[win] & np.isfinite(zbuf) & ~in_front
        if reach is not None:
            on_surface, silhouette = np.zeros(mask.shape, bool), np.zeros(mask.shape, bool)
            on_surface[win] = np.abs(d - z) < tol  # (false off the silhouette, where z is inf)
            silhouette[win] = np.isfinite(z)
            cut |= (reach & on_surface) | like_nearest_depth(depth, on_surface, reach & silhouette)
            if view.rgb is not None and view.rgb.ndim == 3 and view.rgb.shape[:2] == mask.shape:
                # what neither the depth nor the prompt vouches for: a pixel without depth (the mask's own too), or
                # one on the surface that the mask missed; it stays where its colour is the base's more than that of
                # what stands in front. In front of the model's depth 2 px wider: a pixel that took the depth of
                # the base's own nearer edge beside it (a Kinect bleeds near surfaces a pixel or two into far ones,
                # between a ring gear's teeth) is not an occluder, and its shadowed colour not an occluder's
                doubtful = (cut[win] & ~((d > 0) & np.isfinite(d))) | (reach[win] & on_surface[win] & ~mask[win])
                front = (d > 0) & (d < nearest_within(z, 2) - tol) & silhouette[win]
                cut[win] &= ~(doubtful & ~as_common_in(view.rgb[win], on_surface[win], front))
    return cut


COLOUR_BINS = 8  # as_common_in's bins per channel (32 levels each: a surface's shading stays in one or two)
COLOUR_MIN_PX = 20  # ... and the fewest pixels of either kind it compares on


def as_common_in(rgb: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose colour (COLOUR_BINS per channel) is at least as common among `a`'s pixels as
    among `b`'s, each counted as a share of its own. All true when either has fewer than COLOUR_MIN_PX pixels: no
    colour is told apart then. The result's mask asks it of what the depth cannot place (model_cut_mask): a
    pixel without depth is the base's when it looks like the pixels on the model's surface rather than like
    those standing in front of it (a dark object in front of a duck, its depth mostly missing, took 431 pixels
    of the duck's mask of 2,709: benchmarks/captures.py, stacked). Shares, not the nearest colours as the prompt's
    masks.prompt._nearer_colour: a few dark pixels in front (a bled edge, a shadow) would make every dark hole of
    the base an occluder's (that test here: the stacked row's IoU 0.913 -> 0.830, docs/BENCHMARKS.md)."""
    na, nb = int(np.count_nonzero(a)), int(np.count_nonzero(b))
    if na < COLOUR_MIN_PX or nb < COLOUR_MIN_PX:
        return np.ones(a.shape, bool)
    q = np.clip(rgb.astype(np.int64) * COLOUR_BINS // 256, 0, COLOUR_BINS - 1)  # (8-bit colour; anything else clipped)
    code = (q[..., 0] * COLOUR_BINS + q[..., 1]) * COLOUR_BINS + q[..., 2]
    n = COLOUR_BINS ** 3
    share_a = np.bincount(code[a], minlength=n) / na
    share_b = np.bincount(code[b], minlength=n) / nb
    return share_a[code] >= share_b[code]


HOLE_SEARCH_PX = 16  # like_nearest_depth looks this far round the pixels asked about for depth


def like_nearest_depth(depth: np.ndarray, which: np.ndarray, where: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of `where` without depth (0 or not finite: a dark or shiny surface, a sensor's
    shadow) whose nearest pixel with depth (within HOLE_SEARCH_PX of `where`'s box) is in `which`. A Kinect-like
    sensor leaves holes on a base's dark faces, which belong to the base where the depth round them lies on its
    surface, and in the shadow beside what stands in front of it, which do not (their nearest depth is that
    object's)."""
    out = np.zeros(depth.shape, bool)
    vs, us = mask_pixels(where)
    if len(vs) == 0:
        return out
    m = HOLE_SEARCH_PX
    v0, v1 = max(int(vs.min()) - m, 0), min(int(vs.max()) + m + 1, depth.shape[0])
    u0, u1 = max(int(us.min()) - m, 0), min(int(us.max()) + m + 1, depth.shape[1])
    d = depth[v0:v1, u0:u1]
    missing = ~(np.isfinite(d) & (d > 0))
    if not missing.any() or missing.all():
        return out
    _, label = cv2.distanceTransformWithLabels(missing.astype(np.uint8), cv2.DIST_L2, 5,
                                               labelType=cv2.DIST_LABEL_PIXEL)
    # label k >= 1 is the k-th pixel with depth in raster order (OpenCV numbers the zero pixels so)
    cls = np.concatenate([[False], which[v0:v1, u0:u1][~missing]])
    out[v0:v1, u0:u1] = missing & cls[label] & where[v0:v1, u0:u1]
    return out


REACH_PX = 3  # without a box, the result's mask may take in pixels this far outside the mask


def mask_reach(view: View) -> np.ndarray:
    """Where the result's mask may take in pixels the mask missed (model_cut_mask): the prompt's box, which the
    user drew around all they see of the base, or else the mask REACH_PX wider."""
    if view.box is not None:
        return box_region(view.mask.shape, view.box)
    k = np.ones((2 * REACH_PX + 1, 2 * REACH_PX + 1), np.uint8)
    return cv2.dilate(view.mask.astype(np.uint8), k).astype(bool)


def second_look(result: RegistrationResult, view: View, base: BaseObject, T_base_part: np.ndarray, params: Params,
                prior, trace_iterations, part_symmetries=None) -> RegistrationResult:
    """A result that is not confident, often from a mask that took in clutter beside the base or an
    object in front of it: estimate again on the mask cut to the model's view at that pose, and keep
    that result only if it is confident (and so, like any result, one placement that the data
    supports). Measured on 240 cluttered renders with box prompts (benchmarks/captures.py): right
    poses called unconfident 56 -> 39, confident-and-wrong 0 -> 0, recall unchanged. The estimate again
    starts from the first look's pose and candidates (first_look_starts) instead of a search of its own, and
    compares their twins and neighbours on the cut: over captures.py's 528 frames, the same rates (confident-and-
    wrong 0) at 106 ms a second look against 188 (docs/BENCHMARKS.md)."""
    t = time.perf_counter()
    cut = model_cut_mask(result, view, base)
    if cut.sum() < MIN_POINTS or cut.sum() >= view.mask.sum():
        return result
    if params.second_look_from_pose and not result.ambiguous:  # ICP from the pose first: a search only where it fails
        quick = refit(replace(view, mask=cut), base, T_base_part, params, result.T_world_base, part_symmetries)
        if quick is not None and quick.confident:
            return replace(quick, second_look=cut, timings={**result.timings, "second look": time.perf_counter() - t})
    again = estimate_mask(replace(view, mask=cut), base, T_base_part, replace(params, second_look=False), prior,
                          trace_iterations, part_symmetries, starts=first_look_starts(result))
    timings = {**result.timings, "second look": result.timings.get("second look", 0.0) + time.perf_counter() - t}
    if not again.confident:
        return replace(result, timings=timings)
    return replace(again, second_look=cut, timings=timings)


def first_look_starts(result: RegistrationResult) -> list[tuple[float, np.ndarray]]:
    """(score, T_world_base) of the result's pose and of its candidates, best first, as the second look's starts: the
    first look searched the whole mask already, and its candidates (the chosen pose, its rivals, their twins) are where
    the cut's pose lies; each is refined on the cut and their twins and neighbours compared there again."""
    top = max([c.score for c in result.candidates], default=1.0)
    out = [(top, result.T_world_base)]
    for c in result.candidates:
        if not any(poses_within(c.T_world_base, T, result.voxel, 2.0) for _, T in out):
            out.append((c.score, c.T_world_base))
    return out


def refit(view: View, base: BaseObject, T_base_part: np.ndarray, params: Params, T_world_base: np.ndarray,
          part_symmetries: np.ndarray | None = None) -> RegistrationResult | None:
    """The base refitted to the view's mask from a pose it is near (searches.try_prior from the pose: ICP at 2 voxels,
    then at the final threshold or the polish), judged as any estimate; None where the camera sees too little of the
    base or the mask too little depth. No search: nothing here looks for rival placements, so a caller uses it only
    on a pose whose rivals were sought already (second_look_from_pose)."""
    pb = view_task(view, base, T_base_part, params, part_symmetries)
    if pb is None:
        return None
    try:
        r = try_prior(pb, T_world_base, False, {}, from_pose=True, preset=params.preset)
    except Degenerate:
        return None
    if r is None:
        return None
    return judged(replace(r, depth_noise=pb.observation.noise, problem=pb), view, base, params, pb.table)


def view_task(view: View, base: BaseObject, T_base_part: np.ndarray, params: Params,
              part_symmetries: np.ndarray | None = None, noise: float | None = None) -> Task | None:
    """The view's mask and depth prepared as a registration Task (prepare_task), in the view's world; None where the
    mask holds too little depth or its target is degenerate. `noise`: the frame's depth noise when already measured
    (else `observe` measures it)."""
    camera_pts = project_to_cloud(view.depth, view.mask, view.camera, np.eye(4))
    if len(camera_pts) < MIN_POINTS:
        return None
    observation = observe(view.depth, view.mask) if noise is None else \
        Observation(view.mask, view.depth, mask_edge(view.mask), noise)
    try:
        return prepare_task(se3.transform_points(view.T_world_camera, camera_pts), view.camera, view.T_world_camera, base,
                            T_base_part, params, params.voxel(base.diameter), observation,
                            part_symmetries=part_symmetries, camera_pts=camera_pts)
    except Degenerate:
        return None


def judged(r: RegistrationResult, view: View, base: BaseObject, params: Params, plane) -> RegistrationResult:
    """`judge`'s verdict on a pose, with the base's exact twins of it (`equivalent`) where symmetries are used."""
    r = judge(r, view, base, plane=plane)
    if r.ok and params.use_symmetries:
        r = replace(r, equivalent=twin_placements(r.T_world_base, r.T_world_part, base.symmetries))
    return r


def observe(depth: np.ndarray, mask: np.ndarray) -> Observation:
    """What the camera saw around the base: the mask, the depth, the mask's edge and the frame's noise."""
    return Observation(mask, depth, mask_edge(mask), frame_noise(depth, mask))


def frame_noise(depth: np.ndarray, mask: np.ndarray) -> float:
    """The depth's error around the object (metres, one sigma): its noise in the mask's box, twice as
    large (second differences), and the sensor's quantisation step q there (a uniform error of
    sigma q / sqrt(12)): sqrt(noise^2 + q^2 / 12). A Kinect's steps (3 mm at 1 m, 7 mm at 1.6 m) leave
    most second differences at zero, so the noise alone reads far too small. 0 when it cannot be
    measured (too few pixels)."""
    ys, xs = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))  # the mask's rows and columns
    h, w = mask.shape
    cy, cx, hy, hx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2, np.ptp(ys) + 1, np.ptp(xs) + 1
    region = np.zeros_like(mask, dtype=bool)
    region[max(int(cy - hy), 0):min(int(cy + hy) + 1, h), max(int(cx - hx), 0):min(int(cx + hx) + 1, w)] = True
    sigma = estimate_depth_noise(depth, region)
    sigma = sigma if np.isfinite(sigma) else 0.0
    box = np.s_[ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1]  # the mask's box: the same pixels, not the whole frame's work
    q = quantisation_step(depth[box], mask[box])
    return float(np.sqrt(sigma ** 2 + q ** 2 / 12.0))


def estimate_default(pb: Task, prior: np.ndarray | None, trace_iterations: bool, timings: dict) -> RegistrationResult:
    """Ours on the prepared frame (PROJ3D done): `search_and_choose`, then, where the upright search did not
    fit, the free search too (the better of the two kept). `timings` (seconds by stage) is added to."""
    result, free_due = search_and_choose(pb, prior, trace_iterations, timings)
    return better_of_free_search(result, pb, prior, trace_iterations)[0] if free_due else result


def search_and_choose(pb: Task, prior: np.ndarray | None, trace_iterations: bool,
                      timings: dict, starts: list | None = None) -> tuple[RegistrationResult, bool]:
    """The prior fast path, else search -> refine -> choose -> polish -> compose, and whether the free search
    is due: the search was the upright one (a table is seen) and its pose does not fit. `estimate_mask`
    tries the second look before that free search; it seldom wins (docs/ESTIMATOR.md). `starts` ((score,
    T_world_base), best first): these are the coarse poses, no search runs and no free search is due."""
    p, base, voxel = pb.params, pb.base, pb.voxel
    if starts is None and prior is not None and p.prior_fast_path:  # the caller knows the orientation: ICP from it,
        # kept if it fits
        quick = try_prior(pb, prior, trace_iterations, timings, preset=p.preset)
        if quick is not None:
            return quick, False
    t = time.perf_counter()
    R_prior = prior[:3, :3] if prior is not None else None
    T_world_source = place_source(base, pb.coarse_pts.mean(axis=0), R_prior)  # TFORM, kept as the replay's start
    if starts is not None:
        found = Found([Start(score, 0, T, T) for score, T in starts])
    else:
        ms = ModelSearch(pb)  # the whole model against the target: no assumption about the side seen
        timings["features"] = timings.get("features", 0.0) + time.perf_counter() - t
        t = time.perf_counter()
        found = search_poses(pb, ms, prior, T_world_source)  # upright yaw search, or free RANSAC: coarse poses
    timings["global"] = time.perf_counter() - t
    t = time.perf_counter()
    refined = refine_candidates(pb, select_starts(found, voxel, p.use_symmetries), trace_iterations)  # RCAST + ICP
    polished = polish_contenders(pb, refined)  # the ones that could win, each at its best and on its own view
    if p.use_symmetries and refined:
        add_symmetric_twins(pb, refined)  # the best's twins (close twins fitted too)
    timings["icp"] = time.perf_counter() - t
    if not refined:
        raise Degenerate("the camera cannot see the base mesh at any candidate pose")
    chosen, close = choose(pb, refined, R_prior)  # scored; near-ties looked at where the placements differ
    t = time.perf_counter()
    if p.use_symmetries and add_chosen_twins(pb, refined, chosen):  # chosen below the best: its twins compared too
        chosen, close = choose(pb, refined, R_prior)
    if p.polish_voxel_factor > 0 and chosen not in polished:
        polish_chosen(pb, refined, chosen)
    close = close + neighbour_rivals(pb, refined, chosen, found.slid)  # a mostly hidden base: neighbours that fit as well
    timings["icp"] += time.perf_counter() - t
    result = compose(pb, refined, chosen, close, T_world_source, timings,  # T_world_part = T_world_base @ T_base_part
                     "global" if starts is None else "first look")
    free_due = bool(found.upright and not result.fits and p.free_after_upright and
                    not pb.out_of_time("the free search after the upright one"))
    return replace(result, out_of_time="; ".join(pb.notes), problem=pb), free_due


def compose(pb: Task, refined: list, chosen: int, close: list[int], T_world_source: np.ndarray,
            timings: dict, start_name: str = "global") -> RegistrationResult:
    """The result: the chosen pose and its part pose, the replay (its start stage named `start_name`: "global" after a
    search, "first look" where the second look refined the first look's pose), every candidate (best first), and the
    other placements that fit as well when the result is ambiguous."""
    cands = [r.candidate for r in refined]
    c, r = cands[chosen], refined[chosen]
    src_b = se3.transform_points(se3.inv(c.T_world_base), r.seen)
    stages = trace_stages(T_world_source, start_name, r.T_start, r.trace, c, src_b, pb.fine_pts, pb.thr)
    order = sorted(range(len(cands)), key=lambda i: -cands[i].score)
    symmetries = pb.base.symmetries
    placements = distinct_placements([c] + [cands[i] for i in close if i != chosen], pb.voxel, symmetries,
                                     pb.part_symmetries)
    ambiguous = bool(len(placements) > 1 and c.coverage >= CONFIDENT_COVERAGE)  # exact twins are not ambiguity
    return RegistrationResult(ok=True, T_world_base=c.T_world_base, T_world_part=c.T_world_part,
                              T_world_source=T_world_source, target_cloud=pb.fine_pts, source_cloud=src_b,
                              stages=stages, fitness=c.fitness, inlier_rmse=c.inlier_rmse, timings=timings,
                              candidates=[cands[i] for i in order], ambiguous=ambiguous,
                              alternatives=placements[1:] if ambiguous else [], voxel=pb.voxel,
                              coverage=float(c.coverage), preset=pb.params.preset)


def better_of_free_search(result: RegistrationResult, pb: Task, prior,
                          trace_iterations) -> tuple[RegistrationResult, bool]:
    """The base lies on its side, is held in a hand or sits on a fixture: search freely too (on the same
    prepared frame, with its own notes of what the time budget cut), keep the better of the two (by
    coverage; the upright one on a tie), count the time of both. (kept, whether the free one won)"""
    free_timings: dict[str, float] = {}
    free = estimate_default(replace(pb, params=replace(pb.params, upright=False), notes=[]), prior, trace_iterations,
                            free_timings)
    for k, v in result.timings.items():
        free_timings[k] = free_timings.get(k, 0.0) + v
    won = bool(free.coverage > result.coverage)
    return replace(free if won else result, timings=free_timings), won


CONFIDENCE_VOXELS_PER_DIAMETER = 50.0  # confidence is judged at diameter / 50 (ours) whatever the preset's voxel
UNSUPPORTED_SHARE = 0.05  # fitness or coverage below this: the model explains (almost) none of the target
UNSUPPORTED_CONTRADICTION = 0.5  # the camera sees past more than this share of what the model shows


TABLE_SLACK = 0.05  # the base's lowest point may lie this share of its diameter (or 3 tolerances) off the table


def off_table(result: RegistrationResult, view: View, base: BaseObject, tol: float,
              plane: tuple[np.ndarray, float] | None) -> float:
    """How far the base at the result's pose lies above (+) or in (-) the table it stands on (`plane`, from
    `table.table_plane`), beyond TABLE_SLACK of its diameter or 3 tolerances: 0 when it rests on it, NaN
    when no table is seen. A wrong pose fitted to an object in front of the base hangs in the air; a twin
    turned over may sink into the table."""
    if plane is None:
        return float("nan")
    normal, offset = plane
    lowest = float(np.min(se3.transform_points(result.T_world_base, base.samples) @ normal + offset))
    slack = max(TABLE_SLACK * base.diameter, 3 * tol)
    return 0.0 if abs(lowest) <= slack else lowest - np.sign(lowest) * slack


OUTLINE_RING_PX = (2, 5)  # the ring around the model's silhouette that outline_continuation looks at


def outline_continuation(seen: np.ndarray, view: View, tol: float, plane: tuple[np.ndarray, float] | None,
                         slack: float) -> float:
    """The share of the ring just outside the model's silhouette (OUTLINE_RING_PX) where the depth goes on at
    the depth of the model's edge beside it (within `tol`), leaving out the table around the base's foot
    (within `slack` of `plane`). A real object's outline is mostly a depth step (background behind, an
    occluder in front); a model laid onto part of a larger surface (a box face in front of the base) has
    that surface running on past its outline all round. The table at the base's foot (within `slack` of
    `plane`) does not count as running on. NaN when the ring has too few pixels with depth."""
    near_px, far_px = OUTLINE_RING_PX
    # the window round the silhouette that the ring and the edge's depth can reach (the same numbers as on the
    # whole image, at a fraction of the cost: dilation and erosion leave pixels beyond their reach unchanged)
    zbuf, box = depth_window(seen, view.T_world_camera, view.camera, 2 * far_px + 2)
    shown = np.isfinite(zbuf)
    if box is None or shown.sum() < MIN_POINTS:
        return float("nan")
    v0, v1, u0, u1 = box
    zbuf, d = zbuf.astype(np.float32), view.depth[v0:v1, u0:u1]
    inner = cv2.dilate(shown.astype(np.uint8), np.ones((2 * near_px + 1,) * 2, np.uint8)) > 0
    outer = cv2.dilate(shown.astype(np.uint8), np.ones((2 * far_px + 1,) * 2, np.uint8)) > 0
    ring = outer & ~inner
    edge_depth = cv2.erode(np.where(shown, zbuf, np.float32(1e6)), np.ones((2 * far_px + 3,) * 2, np.uint8))
    valid = ring & np.isfinite(d) & (d > 0) & (edge_depth < 1e5)
    if valid.sum() < MIN_POINTS:
        return float("nan")
    runs_on = valid & (np.abs(d - edge_depth) < tol)
    if plane is not None:  # the table at the base's foot runs on past its outline by nature
        vs, us = np.nonzero(runs_on)
        pts = se3.transform_points(view.T_world_camera, view.camera.backproject(us + u0, vs + v0, d[vs, us]))
        foot = pts @ plane[0] + plane[1] < slack
        runs_on[vs[foot], us[foot]] = False
    return float(runs_on.sum()) / float(valid.sum())


BODY_EDGE_PX = 3  # body_evidence leaves out the body's silhouette this far in (mixed depth at its outline)
BODY_FAR = 0.08  # ... and counts the camera seeing past the body by more than this share of the body's size (at least
# BODY_TOLERANCES agreement tolerances): background where the part should be, not a small turn of the region's pose
# carried to the part's far end (a right seat 5 mm off tilts an engine head's far end by ~20 mm)
BODY_TOLERANCES = 3
BODY_STRIDE = 4  # body_evidence looks at every 4th pixel each way: the larger part fills the image, and nine casts of
# it at full size (a seat and its seven twins) took longer than the seat's own estimate
BODY_MARGIN = 0.02  # region_twin: another region of the part is as likely as this one unless the rest of the part fits
# better here by this share of the pixels it covers (at least BODY_MARGIN_PX full-size pixels)
BODY_MARGIN_PX = 100


def body_evidence(body, T_world_base: np.ndarray, view: View, tol: float) -> tuple[int, int, int]:
    """(confirmed, seen past, pixels with a depth reading) of a larger part ray-cast whole at T_world_base, on every
    BODY_STRIDE-th pixel each way, its rim (BODY_EDGE_PX) left out: seen past where the depth lies farther than the
    part by BODY_FAR of its size (table or background where the part should be). A region fitted right has the rest
    of its part where the depth sees it (a part hidden behind something nearer is not seen past); a region laid onto
    another object (a seat's pad on a sphere) has the part standing where the camera sees the bench."""
    k, cam = BODY_STRIDE, view.camera
    coarse = replace(cam, width=cam.width // k, height=cam.height // k, fx=cam.fx / k, fy=cam.fy / k,
                     cx=(cam.cx - k // 2) / k, cy=(cam.cy - k // 2) / k)  # pixel (u, v) here is (k u + k/2, k v + k/2)
    z = raycast_depth(body, T_world_base, view.T_world_camera, coarse)
    shown = np.isfinite(z)
    if not shown.any():
        return 0, 0, 0
    edge = max(1, -(-BODY_EDGE_PX // k))
    inner = cv2.erode(shown.astype(np.uint8), np.ones((2 * edge + 1,) * 2, np.uint8)) > 0
    d = view.depth[k // 2::k, k // 2::k][:coarse.height, :coarse.width]
    read = inner & np.isfinite(d) & (d > 0)
    far = max(BODY_TOLERANCES * tol, BODY_FAR * float(np.linalg.norm(body.extents)))
    return int((read & (np.abs(d - z) <= far)).sum()), int((read & (d > z + far)).sum()), int(read.sum())


def region_twin(base: BaseObject, T_world_base: np.ndarray, view: View, tol: float, here: tuple[int, int, int]) -> str:
    """For a base that is a region of a part with other regions alike to it (`Region.twins`: seats of one engine
    head): the name of one that the data fits as well as this one, or better, "" when none does. The box holds one
    seat; which seat it is only the rest of the part tells, placed as it would stand were the seat in the box that
    other one: the part's pixels that the depth confirms less those it sees past (body_evidence; `here`: this pose's),
    with a margin (BODY_MARGIN). Where the part's ends are out of view, the seats are alike and the answer is that
    twin."""
    if not base.region.twins:
        return ""
    confirmed, past, read = here
    margin = max(BODY_MARGIN_PX / BODY_STRIDE ** 2, BODY_MARGIN * read)  # full-size pixels, counted on every k-th
    best, best_score = "", confirmed - past - margin
    for name, S in base.region.twins:
        c, p_, _ = body_evidence(base.region.body, T_world_base @ se3.inv(S), view, tol)
        if c - p_ >= best_score:
            best, best_score = name, c - p_
    return best


_FIT = object()  # judge's `plane` not given: fit it


def judge(result: RegistrationResult, view: View, base: BaseObject, plane=_FIT) -> RegistrationResult:
    """`ok` means a pose that the data supports. A result whose model explains (almost) none of the
    target, that the depth contradicts on most of what it shows (the camera sees past it: a part placed
    where there is table), or that puts the base where the camera cannot have seen it (behind it,
    outside the image, beyond the farthest depth) becomes ok=False with the reason; its pose stays in
    the result for inspection. The judged copy also carries `contradiction`, which `confident` reads.
    `plane`: the table (table.table_plane of this view), when the caller has fitted it.

    Measured on 50 RealSense-like renders (benchmarks/tune.py frames): right poses contradict 0-2 % of
    their view; a base placed on the wrong object 7-100 % (CONFIDENT_CONTRADICTION is 5 %)."""
    if not result.ok:
        return result
    depth, mask, cam, T_world_camera = view.depth, view.mask, view.camera, view.T_world_camera
    coverage, contradiction = result.coverage, result.contradiction
    seen = se3.transform_points(result.T_world_base, result.source_cloud) if len(result.source_cloud) else None
    scale_voxel = base.diameter / CONFIDENCE_VOXELS_PER_DIAMETER
    tol = agreement_tolerance(min(result.voxel, scale_voxel), result.depth_noise)
    if result.voxel > 1.01 * scale_voxel:  # a coarse preset (the paper's fixed 8 mm): its fit is judged at the
        # scale-aware tolerance, on what the camera sees of the model at the final pose, like ours

        seen, _ = raycast_source(base, result.T_world_base, T_world_camera, cam)
        target = result.target_cloud[base.belongs(result.target_cloud, result.T_world_base, tol)]
        if len(seen) and len(target):
            d = NearestTree(seen).query(target, distance_upper_bound=tol)[0]
            coverage = float(np.mean(d < tol))
    if seen is not None and len(seen):
        confirmed, contradicted = evidence(seen, T_world_camera, cam, depth, mask, ~(mask | mask_edge(mask)), tol,
                                           view.outside_box())
        contradiction = contradicted / max(confirmed + contradicted, 1)
    reason = None
    centre = se3.transform_points(se3.inv(T_world_camera) @ result.T_world_base, base.centre[None])[0]
    farthest = float(np.max(depth, where=np.isfinite(depth) & (depth > 0), initial=-np.inf))  # -inf: no depth at all
    if centre[2] <= 0:
        reason = "the pose puts the base behind the camera"
    elif np.isfinite(farthest) and centre[2] > farthest + base.diameter:
        reason = (f"the pose puts the base {centre[2]:.2f} m away, beyond the farthest depth the camera saw "
                  f"({farthest:.2f} m)")
    else:
        u, v = cam.project(centre[None])
        margin = cam.fx * base.diameter / centre[2]  # the base's size in pixels: its centre may lie that far out
        if not (-margin <= float(u[0]) <= cam.width + margin and -margin <= float(v[0]) <= cam.height + margin):
            reason = "the pose puts the base outside the image"
    if reason is None and (result.fitness < UNSUPPORTED_SHARE or coverage < UNSUPPORTED_SHARE):
        reason = (f"the model explains almost none of the target (fitness {result.fitness:.2f}, coverage "
                  f"{coverage:.2f}): the mask holds something else, or too little of the base")
    if reason is None and contradiction > UNSUPPORTED_CONTRADICTION:
        reason = (f"the depth contradicts {contradiction:.0%} of what the model shows at this pose (the camera "
                  "sees past it): the mask holds something else")
    # the points' error: the frame's depth error, or the fit's own residual where larger (the model is not the
    # object to the last millimetre), at least the tolerance's own scale (quantised or noise-free depth)
    sigma = max(result.depth_noise, result.inlier_rmse, 0.25 * tol)
    spread = pose_spread(result.target_cloud, result.T_world_base, base, sigma, tol)
    if base.region is not None and base.region.plain:  # a plain region: nothing it shows can pin the pose
        spread = float("inf")
    if plane is _FIT:  # the table the base stands on (Task.table, when the caller has it)
        plane = table_plane(depth, mask, cam, T_world_camera, base_size=base.diameter)
    whole = base.region is None  # a region of a larger part neither stands on the table nor has an outline of its
    # own: the part's surface runs on past the roi's cut by nature, so neither is judged (NaN); the rest of the part is
    body = None if whole or base.region.body is None else body_evidence(base.region.body, result.T_world_base, view, tol)
    judged = replace(result, coverage=coverage, contradiction=contradiction, spread=spread,
                     spread_allowed=CONFIDENT_SPREAD * base.diameter,
                     off_table=off_table(result, view, base, tol, plane) if whole else float("nan"),
                     continuation=outline_continuation(seen, view, tol, plane, max(TABLE_SLACK * base.diameter, 3 * tol))
                     if whole and seen is not None and len(seen) else float("nan"),
                     sunk=hidden_share(seen, T_world_camera, cam, depth, tol) if not whole and seen is not None
                     else float("nan"),
                     body_past=body[1] / body[2] if body is not None and body[2] else float("nan"))
    if body is not None and reason is None and judged.fits:  # which seat the box holds matters only to a pose that fits
        judged = replace(judged, region_twin=region_twin(base, result.T_world_base, view, tol, body))
    return judged if reason is None else replace(judged, ok=False, reason=reason + "; no pose is reported")
