"""From coarse poses to the chosen one: which coarse poses are refined, the fine ICP of each against
what the camera would see of the model there, the symmetric twins of the best (and of the chosen), the
choice among near-ties, the polish of the chosen pose, and, for a mostly hidden base, the neighbours on
the table that fit as well (its rivals)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.nn import NearestTree
from apose_studio.geometry.plane import table_axes
from apose_studio.registration.base import raycast_source
from apose_studio.registration.scoring import (
    agreement_tolerance,
    discriminate,
    icp_source,
    is_twin,
    pixels,
    poses_within,
    same_placement,
    score_pose,
    score_seen,
)
from apose_studio.registration.solvers import icp_point_to_plane
from apose_studio.registration.stages import cloud, icp, icp_many
from apose_studio.registration.types import (
    CONFIDENT_COVERAGE,
    MIN_POINTS,
    TIE_MARGIN,
    TWIN_TIE_MARGIN,
    Candidate,
    Found,
    Start,
)

POLISH_ITERATIONS = 6
KEEP_DISTINCT = 3  # refine at most this many distinct coarse poses (several starts often converge to one)
KEEP_MARGIN = 0.1  # ... each explaining at least the best's share less this
TWIN_MARGIN = 0.1  # a twin refined only when its coarse fit is within this of the best start's


@dataclass
class Refined:
    """A refined candidate and what its replay and scoring need: the pose ICP started from, the ICP
    iterations (None without a trace), and what the camera sees of the base at the pose (world)."""

    candidate: Candidate
    T_start: np.ndarray
    trace: list | None
    seen: np.ndarray
    seen_normals: np.ndarray


def select_starts(found: Found, voxel: float, use_symmetries: bool) -> list[Start]:
    """The coarse poses worth a fine refinement: the best few distinct ones, the best's (near-)symmetric
    twins that fit nearly as well, and the prior's best start (always refined and scored)."""
    coarse = found.coarse
    keep: list[Start] = []
    for c in coarse:
        if len(keep) == KEEP_DISTINCT or c.explained < coarse[0].explained - KEEP_MARGIN:
            break
        if is_new(c, keep, voxel):
            keep.append(c)
    if use_symmetries:
        for c in found.twins:  # one at a time: a twin that lands on one kept just before is not new
            if is_new(c, keep, voxel) and c.explained >= coarse[0].explained - TWIN_MARGIN:
                keep.append(c)
    prior_best = [c for c in coarse if c.symmetry == -1][:1]
    return keep + [c for c in prior_best if not any(c is q for q in keep)]


def is_new(c: Start, keep: list[Start], voxel: float) -> bool:
    """A coarse pose not (nearly) one already kept."""
    return not any(poses_within(c.T_coarse, q.T_coarse, 2 * voxel, 10.0) for q in keep)


def refine_candidates(pb, starts: list[Start], trace_iterations: bool) -> list[Refined]:
    """Fine ICP of each start against what the camera would see of the base at its coarse pose, and its
    score; a start that converges onto a pose already refined adds nothing."""
    p, voxel, out = pb.params, pb.voxel, []
    views = []  # per start: (what the camera would see of the base there, its normals, the ICP's source)
    for s in starts:
        if views and pb.out_of_time("refining the other starting poses"):
            break
        src_w, src_n = raycast_source(pb.base, s.T_coarse, pb.T_world_camera, pb.cam)  # what the camera would see
        shown = icp_source(pb, src_w)  # less what stands in front of a mostly hidden base
        views.append((src_w, src_n, cloud(se3.transform_points(se3.inv(s.T_coarse), src_w[shown])).voxel_down_sample(voxel)))
    traces: list[list | None] = [[] if trace_iterations else None for _ in views]
    Ts = icp_many([np.asarray(v[2].points) for v in views], pb.fine, [s.T_coarse for s in starts[:len(views)]], pb.vg,
                  p.icp_max_iterations, traces, p.deterministic, pb.fine_tree)  # side by side: one query a step for all
    for s, (src_w, src_n, src), T, trace in zip(starts, views, Ts, traces):
        if any(poses_within(T, r.candidate.T_world_base, voxel, 2.0) for r in out):
            continue  # converged onto a pose already refined: nothing new to score
        if p.polish_voxel_factor <= 0:  # else no ICP at thr: only the chosen pose needs the last tenth of a
            # millimetre, and the polish gives it that (on the yaw renders 10 % faster, 0.004 mm more mean ADI)
            T = icp(src, pb.fine, T, pb.thr, p.icp_max_iterations, trace, p.deterministic, pb.fine_tree)
        # scored on what the camera sees at the coarse pose, moved with the refinement (small after the coarse
        # ICP): one ray-cast per candidate instead of two, same recall on the yaw renders (benchmarks/tune.py)
        D = T @ se3.inv(s.T_coarse)
        cand, src_w = score_seen(pb, T, se3.transform_points(D, src_w), s.symmetry)
        out.append(Refined(cand, s.T_start, trace, src_w, src_n @ D[:3, :3].T))
    return out


TWIN_CONTENDERS = 2  # the twins of this many candidates tied with the best are added


def add_symmetric_twins(pb, refined: list[Refined]) -> None:
    """The candidates tied with the best (within TWIN_TIE_MARGIN, at most TWIN_CONTENDERS) turned by each
    of the base's symmetries and close twins, scored (and traced) as they: a turn that maps the base
    (nearly) onto itself maps a refined pose onto the pose ICP would refine the turned start to, so a twin
    needs no registration of its own. Each is scored on what the camera would see of it: a close twin (a
    motor turned so its connector is elsewhere) ties when the view hides the connector (the result is then
    ambiguous) and loses when the view shows it. A twin that becomes the best has its own twins added in
    a second round: a hole punch's right pose, left 10 mm off by the search, was beaten by its polished
    half-turned twin, whose own twin is the right pose fitted (benchmarks/captures.py, hidden)."""
    done: set[int] = set()
    for _ in range(2):
        best = max(r.candidate.score for r in refined)
        order = sorted(range(len(refined)), key=lambda i: -refined[i].candidate.score)
        todo = [i for i in order if refined[i].candidate.score >= best - TWIN_TIE_MARGIN][:TWIN_CONTENDERS]
        todo = [i for i in todo if i not in done]
        if not todo:
            return
        for i in todo:
            done.add(i)
            _add_twins_of(pb, refined, refined[i])


def _add_twins_of(pb, refined: list[Refined], best: Refined) -> None:
    exact = len(pb.base.symmetries) - 1
    T_b = best.candidate.T_world_base
    turns = list(pb.base.symmetries[1:]) + list(pb.base.close_twins)

    def known(T: np.ndarray) -> bool:
        return any(poses_within(T, r.candidate.T_world_base, pb.voxel, 2.0) for r in refined)

    # a close twin maps the base only nearly onto itself (a turn a few degrees off): refined as a start is, then
    # polished where the preset has a polish, before it is scored (refine_and_polish's fit; a hole punch's right pose,
    # derived 3 mm and 7 degrees off, lost to its half-turned twin). Their ICPs run side by side, each the pose its
    # own gives (refine_from_many); one whose turn lands on a twin added below is refined for nothing, and skipped
    due = [k for k in range(exact + 1, len(turns) + 1) if not known(T_b @ turns[k - 1])]
    fitted = dict(zip(due, refine_from_many(pb, [T_b @ turns[k - 1] for k in due])))
    for k, S in enumerate(turns, start=1):
        T = T_b @ S
        if known(T):
            continue
        if k > exact:
            T = polished(pb, fitted[k])
        cand, src_w, src_n = score_pose(pb, T, k)
        trace = None if best.trace is None else [T_ @ S for T_ in best.trace]
        refined.append(Refined(cand, best.T_start @ S, trace, src_w, src_n))


def refine_and_polish(pb, Ts: list[np.ndarray]) -> list[np.ndarray]:
    """Each T_world_base refined as a start is (refine_from_many), then polished where the preset has a polish: how a
    pose derived by a turn a few degrees off the one that fits (a close twin) is fitted before it is scored.
    (_add_twins_of fits its close twins so too, each polished only when it does not skip it.)"""
    return [polished(pb, T) for T in refine_from_many(pb, Ts)]


def polished(pb, T_world_base: np.ndarray) -> np.ndarray:
    """T_world_base polished (`polish`, no replay) where the preset has a polish; else as it is."""
    return polish(pb, T_world_base, None)[0] if pb.params.polish_voxel_factor > 0 else T_world_base


def refine_from_many(pb, Ts: list[np.ndarray]) -> list[np.ndarray]:
    """Each pose T refined as refine_candidates refines a start: ICP of what the camera would see of the base at T
    onto the target, at the coarse threshold. The ICPs run side by side (stages.icp_many: one k-d tree query a step
    for all, each pose the one its own ICP gives). A pose the camera would see too little of stays as it is."""
    out = [np.array(T, dtype=float) for T in Ts]
    sources, todo = [], []
    for k, T in enumerate(Ts):
        src_w, _ = raycast_source(pb.base, T, pb.T_world_camera, pb.cam)
        if len(src_w) >= MIN_POINTS:
            sources.append(np.asarray(cloud(se3.transform_points(se3.inv(T), src_w)).voxel_down_sample(pb.voxel).points))
            todo.append(k)
    p = pb.params
    for k, T in zip(todo, icp_many(sources, pb.fine, [Ts[k] for k in todo], pb.vg, p.icp_max_iterations, None,
                                   p.deterministic, pb.fine_tree)):
        out[k] = T
    return out


def tied(base, cands: list[Candidate], voxel: float) -> list[int]:
    """The candidates tied with the best score: within TIE_MARGIN, or a twin of the best (turned by a
    symmetry or near-symmetry) within TWIN_TIE_MARGIN: clutter in the mask where the wrong twin puts its
    connector can lift that twin's score past the right one's."""
    best = max(cands, key=lambda c: c.score)
    return [i for i, c in enumerate(cands) if c.score >= best.score - TIE_MARGIN
            or (c.score >= best.score - TWIN_TIE_MARGIN and is_twin(base, best.T_world_base, c.T_world_base, voxel))]


def choose(pb, refined: list[Refined], R_prior: np.ndarray | None) -> tuple[int, list[int]]:
    """(the chosen candidate, the candidates tied with the best score). Near-ties are looked at where
    the placements differ (the evidence there decides); what stays tied goes to the prior's orientation
    when there is one, else to the best score."""
    cands = [r.candidate for r in refined]
    close = tied(pb.base, cands, pb.voxel)
    if R_prior is None and len(close) > 1:
        traces = [(r.T_start, r.trace, r.seen, r.seen_normals) for r in refined]
        close = discriminate(pb, close, cands, traces)
    if R_prior is not None and len(close) > 1:
        return min(close, key=lambda i: se3.rotation_angle_deg(cands[i].T_world_base[:3, :3].T @ R_prior)), close
    return max(close, key=lambda i: cands[i].score), close


POLISH_MARGIN = 0.1  # candidates scoring within this of the best are polished before any is chosen
POLISH_MAX = 3  # ... at most this many


def polish_contenders(pb, refined: list[Refined]) -> set[int]:
    """Polish (and score on their own views, cast anew) the candidates that could win: those within
    POLISH_MARGIN of the best score, at most POLISH_MAX. Near-ties must be compared at their best: a right
    pose left 1 mm and 1 degree off lost to a polished twin turned half round (benchmarks/captures.py,
    a casing mostly hidden behind a box). Returns the indices polished."""
    if pb.params.polish_voxel_factor <= 0 or not refined:
        return set()
    best = max(r.candidate.score for r in refined)
    order = sorted(range(len(refined)), key=lambda i: -refined[i].candidate.score)
    chosen = [i for i in order if refined[i].candidate.score >= best - POLISH_MARGIN][:POLISH_MAX]
    for i in chosen:
        polish_chosen(pb, refined, i, recast=True)
    return set(chosen)


def polish(pb, T_world_base: np.ndarray, trace: list | None, seen_world: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The last refinement: the target, down-sampled finely, registered by point-to-plane ICP onto what
    the camera sees of the model at T_world_base, using the model's exact normals. With RealSense-like
    noise the target's own normals are noisy and bias the fit; the model's are not (scene-to-model).
    Returns the refined T_world_base and the seen model points moved with it (world): the pose moves by
    a fraction of a millimetre, so what the camera sees is not cast again. It stops after POLISH_ITERATIONS steps,
    when its fit stops changing, or once a step moves the base by less than `polish_min_step` voxels (default 0.1:
    benchmarks/tune.py, 7-8 % of a frame, the same recall and ADI; docs/BENCHMARKS.md). `seen_world`: (points, normals)
    the camera sees at T_world_base, when already cast."""
    p, voxel = pb.params, pb.voxel
    src_w, src_n = seen_world if seen_world is not None else raycast_source(pb.base, T_world_base, pb.T_world_camera,
                                                                              pb.cam)
    if len(src_w) < MIN_POINTS:
        return T_world_base, src_w
    T_base_world = se3.inv(T_world_base)
    seen = cloud(se3.transform_points(T_base_world, src_w), src_n @ T_base_world[:3, :3].T)
    v = voxel * p.polish_voxel_factor
    steps: list | None = [] if trace is not None else None
    T = icp(pb.target_at(v), seen.voxel_down_sample(v), T_base_world,
            p.polish_threshold_factor * voxel, POLISH_ITERATIONS, steps, p.deterministic, min_step=p.polish_min_step * voxel)
    if trace is not None:
        trace.extend(se3.inv(S) for S in steps)
    T_new = se3.inv(T)
    return T_new, se3.transform_points(T_new @ T_base_world, src_w)


SETTLE_ROUNDS = 6  # rounds of: what lies in front of the model's surface left out, then ICP of the rest onto it
SETTLE_ITERATIONS = 10  # ICP steps a round
SETTLE_REACH = 2.0  # the settle's correspondence distance, x voxel


def settle(pb, T_world_base: np.ndarray, front: float) -> np.ndarray | None:
    """The pose refitted to the target without what lies in front of the model's surface there: `polish`'s
    fit (the target, down-sampled at the polish voxel, onto what the camera sees of the model, with its exact
    normals), in SETTLE_ROUNDS rounds, each leaving out the target points nearer the camera than the model's
    surface by more than `front` (metres) at the pose the round before found. A plate lying on the base, its
    low end on the base's top, is one depth patch with the base (no jump splits them), so no reading of the
    mask leaves it out; fitted with the rest, it tilts the pose towards itself and the camera then sees past
    the model's sides (benchmarks/captures.py `stacked`: a gearbox casing 7 degrees off, 13 % of it
    contradicted). What lies on the base is in front of its surface, never behind it: left out, the casing's
    own top pulls the pose back down. None when nothing lies in front at the pose given (nothing to settle)
    or the camera sees too little of the model."""
    p, voxel = pb.params, pb.voxel
    v = voxel * (p.polish_voxel_factor if p.polish_voxel_factor > 0 else 1.0)
    target = np.asarray(pb.target_at(v).points)
    T, moved = np.array(T_world_base, dtype=float), False
    for _ in range(SETTLE_ROUNDS):
        src_w, src_n = raycast_source(pb.base, T, pb.T_world_camera, pb.cam)  # normals facing the camera
        if len(src_w) < MIN_POINTS or len(target) < MIN_POINTS:
            return None
        d, i = NearestTree(src_w).query(target, distance_upper_bound=SETTLE_REACH * voxel)
        near = np.isfinite(d)
        j = i[near]
        ahead = np.zeros(len(target), bool)
        ahead[near] = np.einsum("ij,ij->i", target[near] - src_w[j], src_n[j]) > front
        if not ahead.any():
            break  # nothing in front of the surface: this pose stands as it is
        T_base_world = se3.inv(T)
        seen_b, normals_b = se3.transform_points(T_base_world, src_w), src_n @ T_base_world[:3, :3].T
        T_next = se3.inv(icp_point_to_plane(target[~ahead], seen_b, normals_b, T_base_world, SETTLE_REACH * voxel,
                                            SETTLE_ITERATIONS))
        moved = moved or not np.array_equal(T_next, T)
        T = T_next
    return T if moved else None


def polish_chosen(pb, refined: list[Refined], chosen: int, recast: bool = False) -> None:
    """Polish the chosen candidate in place and score it again (with its replay extended). `recast`: score
    it on what the camera sees at the polished pose, cast anew (a candidate refined from a coarse pose far
    off carries what the camera saw there: near-ties are compared on their own views)."""
    r = refined[chosen]
    T, seen = polish(pb, r.candidate.T_world_base, r.trace, (r.seen, r.seen_normals))
    if recast:
        r.candidate, r.seen, r.seen_normals = score_pose(pb, T, r.candidate.symmetry)
    else:
        r.candidate, r.seen = score_seen(pb, T, seen, r.candidate.symmetry)


NEIGHBOUR_HIDDEN = 0.5  # the best pose's neighbours are tried when the depth stands in front of more than this share
# of what the model shows there
NEIGHBOUR_STEP = 0.1  # ... slid this share of the base's diameter each way over the table, and turned about its
# normal by as much at the rim


TURN_BELOW = 0.9  # a chosen pose that explains less of the target than this is also turned all round the table's
# normal (TURN_STEP_DEG apart)
TURN_STEP_DEG = 30.0
TURN_SCREEN = 0.6  # ... and refined only when, turned, it still explains this share of the target (on a watering can
# turned 30 degrees at a time, those that came to tie with the chosen pose explained 0.76-0.85 before their ICP, those
# below 0.6 ended 0.03-0.45 below it)


def hidden_share(pb, seen_world: np.ndarray) -> float:
    """The share of what the camera would see of the base (world points) where the depth lies in front of it:
    something else stands there, so that part of the base is not seen at all."""
    v, u, z, inside = pixels(seen_world, pb.T_world_camera, pb.cam)
    d = pb.observation.depth[v[inside], u[inside]]
    ok = np.isfinite(d) & (d > 0)
    if not ok.any():
        return 0.0
    tol = agreement_tolerance(pb.voxel, pb.observation.noise)
    return float(np.mean(d[ok] < z[inside][ok] - tol))


def neighbour_rivals(pb, refined: list[Refined], chosen: int, slid: bool = False) -> list[int]:
    """When the chosen candidate's view is mostly hidden behind something else (NEIGHBOUR_HIDDEN), its
    neighbours on the table (slid NEIGHBOUR_STEP of the diameter four ways, turned both ways about the
    table's normal by as much at the rim, and twice that) are refined, polished and scored; those that
    explain the data as well as the chosen one (within TIE_MARGIN of its score, or better) and that the
    depth does not rule out (scoring.discriminate) are returned as its rivals (indices into `refined`, to
    which they are added). What is seen of a mostly hidden base may hold it only loosely, and the local
    spread cannot show it: the pose may slide or turn far behind what stands in front (benchmarks/captures.py,
    hidden: a fidget casing turned 18 degrees, the part 11 mm off, judged confident). When the chosen pose
    explains less than TURN_BELOW of the target, it is also turned all round the normal, TURN_STEP_DEG at a
    time, and each turn that still explains TURN_SCREEN of the target is tried alike: a watering can turned
    47 degrees about its round body fitted as well as the right pose. The chosen pose is kept: a rival only
    makes the result ambiguous. `slid`: the search had to slide the base over the table to fit it at all
    (Found.slid): its neighbours are tried as for a hidden one (a watering can 30 % hidden, found slid, ended
    turned 22 degrees and confident; the right turn scored within 0.012 of it)."""
    if not refined or pb.table is None:
        return []
    best = refined[chosen]
    if not best.candidate.coverage >= CONFIDENT_COVERAGE:
        return []  # a pose that explains too little is not confident anyway, and rivals make no result ambiguous
    hidden = slid or hidden_share(pb, best.seen) > NEIGHBOUR_HIDDEN
    weak = best.candidate.coverage < TURN_BELOW
    if not (hidden or weak):
        return []
    if pb.out_of_time("trying the chosen pose's neighbours"):
        return []  # noted: the result is then not confident
    n = pb.table[0]
    e1, e2 = table_axes(n, pb.T_world_camera)  # fixed to the camera: the same neighbours in every world frame
    T_b = best.candidate.T_world_base
    c = se3.transform_points(T_b, pb.base.centre[None])[0]
    s = NEIGHBOUR_STEP * pb.base.diameter
    angle = 2 * NEIGHBOUR_STEP  # radians: the rim (half the diameter away) moves s
    moves = [se3.make_T(t=s * e) for e in (e1, -e1, e2, -e2)] if hidden else []
    turns = [angle, -angle, 2 * angle, -2 * angle] if hidden else []
    moves += [se3.turn_about(n, a, c) for a in turns]
    if weak:  # all round, each turn first scored where it lands: most explain too little to be worth an ICP
        for a in np.radians(np.arange(TURN_STEP_DEG, 360.0, TURN_STEP_DEG)):
            if any(abs(np.angle(np.exp(1j * (a - b)))) <= angle / 2 for b in turns):
                continue
            M = se3.turn_about(n, a, c)
            if score_pose(pb, M @ T_b, best.candidate.symmetry)[0].coverage >= TURN_SCREEN:
                moves.append(M)

    def known(T: np.ndarray) -> bool:  # back where a candidate already is: the data holds the pose there
        return any(poses_within(T, r.candidate.T_world_base, pb.voxel, 2.0) for r in refined)

    new: list[int] = []
    for T in refine_from_many(pb, [M @ T_b for M in moves]):  # their ICPs side by side
        if known(T):
            continue  # (before the polish too: most neighbours of a pose the data pins fall back onto it)
        if pb.params.polish_voxel_factor > 0:
            T = polished(pb, T)
            if known(T):
                continue
        cand, src_w, src_n = score_pose(pb, T, best.candidate.symmetry)
        if cand.score >= best.candidate.score - TIE_MARGIN:
            refined.append(Refined(cand, best.T_start, None if best.trace is None else list(best.trace), src_w,
                                   src_n))
            new.append(len(refined) - 1)
    if not new:
        return []
    cands = [r.candidate for r in refined]
    kept = discriminate(pb, [chosen] + new, cands, [(r.T_start, r.trace, r.seen, r.seen_normals) for r in refined])
    return [i for i in new if i in kept]


def add_chosen_twins(pb, refined: list[Refined], chosen: int) -> bool:
    """The chosen candidate's twins (symmetries and close twins), when not among the candidates yet: the
    twins are added for the best-scoring candidates only, and one chosen below them by the depth's evidence
    (scoring.discriminate) must still be compared with its own twins (benchmarks/captures.py, hidden: a tin
    box chosen half turned, 130 mm off, confident, its twin, the right pose, never scored). True when any
    was added."""
    n = len(refined)
    _add_twins_of(pb, refined, refined[chosen])
    return len(refined) > n


def base_twins_alike(pb, T_world_base: np.ndarray) -> list[np.ndarray]:
    """T_world_base of the base at T_world_base turned by each close twin or near-symmetry that places the part
    alike (scoring.same_placement, modulo the part's own symmetries: a symmetric sun gear on a motor turned half
    round goes to the same place) and that explains the data within TWIN_TIE_MARGIN of the pose itself: as the
    turn gives it, or else refined and polished as a close twin is (a motor's half turn scored 0.554 as the
    near-symmetry gives it and 0.912 refined: the truth's turn). The part's placement is then sure and the base's own turn is not: the view
    hides what tells them apart (benchmarks/captures.py: a planetary motor with its sun gear, half turned, 0.924
    against the truth's 0.912, the gear 0.1 mm off either way, the motor 38 mm by ADD). Only reports: the pose
    and `confident` stay as chosen."""
    base = pb.base
    turns: list[np.ndarray] = []
    for S in list(base.close_twins) + list(base.near_symmetries):  # (a close twin is a near-symmetry too: once)
        if not any(poses_within(S, E, pb.voxel, 2.0) for E in list(base.symmetries) + turns):
            turns.append(S)
    T_part = T_world_base @ pb.T_base_part
    alike = [T_world_base @ S for S in turns
             if same_placement(T_part, T_world_base @ S @ pb.T_base_part, pb.part_symmetries, 3 * pb.voxel, 5.0)]
    if not alike:
        return []
    own = score_pose(pb, T_world_base)[0].score
    out: list[np.ndarray] = []
    for T in alike:
        if score_pose(pb, T)[0].score >= own - TWIN_TIE_MARGIN:  # ties as the turn gives it: no ICP needed to say so
            if not any(poses_within(T, A, pb.voxel, 2.0) for A in out):
                out.append(T)
            continue
        T = refine_from_many(pb, [T])[0]
        if poses_within(T, T_world_base, pb.voxel, 2.0) or any(poses_within(T, A, pb.voxel, 2.0) for A in out):
            continue  # refined back onto the pose (or onto one already found)
        if not same_placement(T_part, T @ pb.T_base_part, pb.part_symmetries, 3 * pb.voxel, 5.0):
            continue
        T = polished(pb, T)
        if score_pose(pb, T)[0].score >= own - TWIN_TIE_MARGIN:
            out.append(T)
    return out


