"""The searches for the base's pose, from the cheapest to the most general:

- the prior fast path: the caller knows the orientation; ICP from it, accepted when it fits;
- the upright yaw search: a table is seen, so the base stands on it as modelled; every yaw about the
  table's normal is screened, the best few refined coarsely (and the best's near-symmetric turns);
- the free search: RANSAC on FPFH matches against the whole model (with a longer retry when the fast
  one explains too little), its result turned by half turns and near-symmetries.

Each yields coarse poses (`Start`s, best first) for refine.py; none of them decides alone.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.nn import NearestTree
from apose_studio.geometry.plane import table_axes
from apose_studio.registration.base import place_source, raycast_source
from apose_studio.registration.refine import polish
from apose_studio.registration.scoring import agreement_tolerance, icp_source, score_seen, visible_agreement
from apose_studio.registration.stages import (
    cloud,
    estimate_normals,
    global_registration,
    icp,
    icp_many,
    normals_fpfh,
    trace_stages,
)
from apose_studio.registration.types import MIN_POINTS, Found, RegistrationResult, Start

PRIOR_ACCEPT = 0.95  # the prior's pose is kept without a global search when both shares reach this
UPRIGHT_YAW_STEP_DEG = 10.0
UPRIGHT_STARTS = 4  # the best-screened yaws refined by coarse ICP (4 and 6 reach the same recall; 4 is 7 % faster)
UPRIGHT_APART = 3  # the refined upright yaws lie at least this many yaw steps apart (spread_yaws)
UPRIGHT_TWINS = 3  # at most this many (near-)symmetric turns of the best upright pose are refined too
UPRIGHT_FALLBACK = 0.6  # below this share explained by the best upright start, the base is not upright: search freely
RESTING_BELOW = 0.8  # below this share explained by the best upright start, the resting starts are tried too, and
# the best pose turned round (turned_round)
SCREEN_POINTS = 500  # target points the screening looks up per starting pose
SCREEN_MODEL_POINTS = 200  # model points it projects per slid start (ModelSearch.seen_past)


def try_prior(pb, prior: np.ndarray, trace_iterations: bool, timings: dict, from_pose: bool = False,
              **kw) -> RegistrationResult | None:
    """Early exit when the caller knows the base's orientation: put the CAD in that orientation where
    what the camera would see of it lands on the target's centre, refine with ICP from coarse to fine,
    and accept when the model explains the target and the depth confirms the model (both >= 95 %).
    Otherwise None, and the full search runs (the prior still breaks its ties). `from_pose`: `prior` is a
    pose the base is near already (pipeline.refit): ICP from it at 2 voxels, then as above, and no
    acceptance test (the judge that follows decides).

    From the orientation, the coarse fits (8, 4 and 2 voxels) bring the target onto what the camera sees of the
    model, with the model's exact normals, as the polish does (`prior_fits`): the target's own normals are then
    never estimated on this path."""
    base, cam, T_world_camera, p, voxel = pb.base, pb.cam, pb.T_world_camera, pb.params, pb.voxel
    fine_pts, observation, tp = pb.fine_pts, pb.observation, pb.coarse_pts
    t = time.perf_counter()
    thr = pb.thr
    T_world_source = prior.copy() if from_pose else place_source(base, tp.mean(axis=0), prior[:3, :3])
    src_w, src_n = raycast_source(base, T_world_source, T_world_camera, cam)
    if len(src_w) < MIN_POINTS:
        return None
    T0 = T_world_source.copy()
    if not from_pose:
        T0[:3, 3] += tp.mean(axis=0) - src_w.mean(axis=0)  # the visible part's centre on the target's centre
    trace: list | None = [] if trace_iterations else None
    if from_pose:
        src = cloud(se3.transform_points(se3.inv(T_world_source), src_w)).voxel_down_sample(voxel)
        T = icp(src, pb.fine, T0, 2.0 * voxel, 10, trace, p.deterministic, pb.fine_tree)
    else:
        T = prior_fits(pb, T0, T_world_source, src_w, src_n, trace)
    if p.polish_voxel_factor > 0:
        T, src_w = polish(pb, T, trace)
    else:
        src_w, _ = raycast_source(base, T, T_world_camera, cam)  # what the camera sees at the refined pose
        src = cloud(se3.transform_points(se3.inv(T), src_w)).voxel_down_sample(voxel)
        T = icp(src, pb.fine, T, thr, p.icp_max_iterations, trace, p.deterministic, pb.fine_tree)
        src_w, _ = raycast_source(base, T, T_world_camera, cam)
    cand, src_w = score_seen(pb, T, src_w)
    # the depth's word on the model, leaving out what it cannot judge: the mask's outline (mixed
    # pixels) and dropouts; with RealSense-like noise those alone cost 5-7 % of the agreement
    accept = from_pose or (cand.coverage >= PRIOR_ACCEPT and visible_agreement(
        src_w, T_world_camera, cam, observation.depth, observation.mask, agreement_tolerance(voxel, observation.noise),
        observation.edge) >= PRIOR_ACCEPT)
    timings["prior"] = time.perf_counter() - t
    if not accept:
        return None
    src_b = se3.transform_points(se3.inv(T), src_w)
    stages = trace_stages(T_world_source, "prior", T0, trace, cand, src_b, fine_pts, thr)
    return RegistrationResult(ok=True, T_world_base=T, T_world_part=cand.T_world_part, T_world_source=T_world_source,
                              target_cloud=fine_pts, source_cloud=src_b, stages=stages, fitness=cand.fitness,
                              inlier_rmse=cand.inlier_rmse, timings=timings, candidates=[cand], voxel=voxel,
                              coverage=cand.coverage, **kw)


def prior_fits(pb, T0: np.ndarray, T_world_source: np.ndarray, seen_w: np.ndarray, seen_n: np.ndarray,
               trace: list | None) -> np.ndarray:
    """T_world_base fitted from T0 at 8, 4 and then 2 voxels, 10 ICP steps each: the target (its coarse points for the
    first two, its fine ones for the last) onto what the camera sees of the model at T_world_source (`seen_w`,
    `seen_n`: world points and normals), down-sampled at the fine voxel, with the model's exact normals: the scene
    onto the model, as the polish fits (refine.polish). The model's view is cast once, at the start: these fits move
    the base by millimetres. `trace`: each step's T_world_base is appended.

    Model onto scene instead (the model's view onto the target, with the target's normals) took the target's
    normals, estimated for it alone: 3.9 ms of a frame's 46 on benchmarks/tune.py's fixed protocol."""
    p, voxel = pb.params, pb.voxel
    T_source_world = se3.inv(T_world_source)
    seen = cloud(se3.transform_points(T_source_world, seen_w), seen_n @ T_source_world[:3, :3].T).voxel_down_sample(voxel)
    tree = NearestTree(np.asarray(seen.points)) if p.deterministic else None
    steps: list | None = [] if trace is not None else None
    T = se3.inv(T0)  # T_base_world
    coarse, fine = cloud(pb.coarse_pts), cloud(pb.fine_pts)
    for factor, scene in ((8.0, coarse), (4.0, coarse), (2.0, fine)):
        T = icp(scene, seen, T, factor * voxel, 10, steps, p.deterministic, tree)
    if trace is not None:
        trace.extend(se3.inv(S) for S in steps)
    return se3.inv(T)


def upright_starts(base, up: np.ndarray, target_pts: np.ndarray, T_world_camera: np.ndarray,
                   model_pts: np.ndarray, model_nrm: np.ndarray) -> list:
    """(0, T_world_base) starts with the CAD's +z along `up`, one per yaw step about it, each moved so
    the part of the model facing the camera is centred on the target. Yaw 0 lays the CAD's +x along the
    image's x on the table (plane.table_axes): the yaws are fixed to the camera, not to the world frame."""
    e1, e2 = table_axes(up, T_world_camera)
    R_up = np.stack([e1, e2, up], axis=1)  # the CAD's x, y, z onto the table's axes and normal
    cam_pos = T_world_camera[:3, 3]
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


def resting_starts(starts: list, plane: tuple[np.ndarray, float], model_pts: np.ndarray, diameter: float,
                   T_world_camera: np.ndarray) -> list:
    """Upright starts moved to stand on the table (the model's lowest point on the plane) and slid over it
    on a grid (RESTING_SHIFTS steps of RESTING_STEP of the diameter each way): for a base that is mostly
    hidden, where the part of it the camera sees is not the middle of what faces the camera, so centring
    the one on the other leaves every start a third of the base off (a gearbox casing behind a box: 36 mm
    on a 108 mm casing, no start near the truth)."""
    n, d = plane
    e1, e2 = table_axes(n, T_world_camera)  # the grid fixed to the camera, as the yaws are
    steps = RESTING_STEP * diameter * np.arange(-RESTING_SHIFTS, RESTING_SHIFTS + 1)
    shifts = (steps[:, None, None] * e1 + steps[None, :, None] * e2).reshape(-1, 3)
    k = np.arange(-RESTING_SHIFTS, RESTING_SHIFTS + 1)
    rings = (k[:, None] ** 2 + k[None, :] ** 2).reshape(-1)  # in grid steps, exact: ties broken alike in every frame
    shifts = shifts[np.argsort(rings, kind="stable")]  # the unshifted first: ties go to it
    height = -d - float(model_pts[:, 2].min())  # n . t for the base's frame origin with its lowest point on the plane
    out = []
    for _, T in starts:
        t = T[:3, 3] + n * (height - n @ T[:3, 3])
        for s in shifts:
            Ts = T.copy()
            Ts[:3, 3] = t + s
            out.append((0, Ts))
    return out


RESTING_STEP = 0.1  # the resting starts' grid step, as a share of the base's diameter
RESTING_SHIFTS = 3  # grid steps each way (7 x 7 shifts per yaw)


def keeps_up(T: np.ndarray, T_ref: np.ndarray, max_deg: float = 5.0) -> bool:
    """T's base +z points where T_ref's does (a turn about the table's normal, not a tip-over)."""
    return float(T[:3, 2] @ T_ref[:3, 2]) > np.cos(np.radians(max_deg))


def facing(points: np.ndarray, normals: np.ndarray, T_world_base: np.ndarray, cam_pos: np.ndarray) -> np.ndarray:
    """Model points (base frame) whose outward normal faces the camera when the base is at T_world_base."""
    eye = se3.transform_points(se3.inv(T_world_base), cam_pos[None])[0]
    return points[np.einsum("ij,ij->i", normals, eye - points) > 0]


class ModelSearch:
    """The whole model against the target, at the coarse voxel: the model's features (cached per step),
    the target's FPFH (computed only when a RANSAC needs it: the upright search does not), and the
    near-surface grid that screens starting poses."""

    def __init__(self, pb):
        p = pb.params
        self.pb = pb
        self.model, self.f_model = pb.base.model_features(pb.vg, p)
        estimate_normals(pb.target, pb.vg, p, pb.cam_pos)  # ICP needs them whatever the search
        self._f_target = None
        self.grid = pb.base.near_grid(pb.vg, p)
        self.model_pts, self.model_nrm = np.asarray(self.model.points), np.asarray(self.model.normals)
        tp = pb.coarse_pts
        self.tp_few = tp[np.random.default_rng(p.seed).choice(len(tp), min(len(tp), SCREEN_POINTS), replace=False)]
        m = len(self.model_pts)
        self.model_few = np.random.default_rng(p.seed).choice(m, min(m, SCREEN_MODEL_POINTS), replace=False)

    def target_features(self):
        """The coarse target's FPFH, in the camera's frame (Task.target_cam)."""
        if self._f_target is None:
            self._f_target = normals_fpfh(self.pb.target_cam, self.pb.vg, self.pb.params, np.zeros(3))
        return self._f_target

    def ransac(self, p=None) -> np.ndarray:
        """T_world_base straight from RANSAC on FPFH matches (the model is in the base frame), run on the target
        in the camera's frame: the same draws and the same pose whatever the caller's world frame is."""
        pb = self.pb
        T_camera_base = global_registration(self.model, pb.target_cam, self.f_model, self.target_features(), pb.vg,
                                            p or pb.params)
        return pb.T_world_camera @ T_camera_base

    def explained(self, poses: list) -> np.ndarray:
        """Per pose: the share of (SCREEN_POINTS of) the target points near the model's outer surface."""
        if not poses:
            return np.zeros(0)
        T_base_world = np.linalg.inv(np.stack(poses))  # (n, 4, 4)
        pts = self.tp_few @ T_base_world[:, :3, :3].transpose(0, 2, 1) + T_base_world[:, None, :3, 3]
        return self.grid.contains(pts.reshape(-1, 3)).reshape(len(poses), -1).mean(axis=1)

    def seen_past(self, poses: list) -> np.ndarray:
        """Per pose: the share of (SCREEN_MODEL_POINTS of) the model's points facing the camera (back faces
        culled, no occlusion) that land on a pixel with depth beyond them by more than two coarse voxels:
        where the camera sees past the model. A point hidden behind the model's own front or behind something
        in front has depth nearer than it, so a mostly hidden base is not charged for what it hides; a pose
        that puts the base where there is table behind is. Poses sharing a rotation (the slid starts) turn
        the points once."""
        if not poses:
            return np.zeros(0)
        pb = self.pb
        obs, cam = pb.observation, pb.cam
        P, N = self.model_pts[self.model_few].astype(np.float32), self.model_nrm[self.model_few].astype(np.float32)
        T = np.stack(poses)
        T_camera_world = se3.inv(pb.T_world_camera)
        T_c = np.einsum("ij,njk->nik", T_camera_world, T).astype(np.float32)  # T_camera_base per pose
        R, t = T_c[:, :3, :3], T_c[:, :3, 3]
        rots, which = np.unique(R.reshape(len(R), 9), axis=0, return_inverse=True)
        rots = rots.reshape(-1, 3, 3)
        c = np.einsum("rij,mj->rmi", rots, P)[which.ravel()] + t[:, None]  # (n, m, 3) camera frame
        nc = np.einsum("rij,mj->rmi", rots, N)[which.ravel()]
        facing_ = np.einsum("nmi,nmi->nm", c, nc) < 0  # the normal points back at the camera (at the origin)
        z = c[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(cam.fx * c[..., 0] / z + cam.cx)
            v = np.round(cam.fy * c[..., 1] / z + cam.cy)
        h, w_ = obs.depth.shape
        inside = facing_ & (z > 0) & (u >= 0) & (u < w_) & (v >= 0) & (v < h)
        d = np.zeros(z.shape, np.float32)
        d[inside] = obs.depth[v[inside].astype(np.intp), u[inside].astype(np.intp)]
        valid = inside & np.isfinite(d) & (d > 0)
        past = valid & (d > z + 2.0 * pb.vg)
        return past.sum(axis=1) / np.maximum(valid.sum(axis=1), 1)

    def view_explained(self, T_world_base: np.ndarray) -> float:
        """The share of what the camera sees of the model at T_world_base (ray cast: its own front hides its
        back) that lies within a coarse voxel of the target. A coarse start's own score (`Start.explained`) counts
        every point facing the camera, hidden by the model itself or not, which is quick enough to rank starts
        but reads low on a right pose of a base that hides part of itself: a fidget casing with its wheel on
        it scored 0.75 where this is 1.0, and so took the road of a mostly hidden base (the slid and turned
        starts and the neighbours' polishes: 150-200 ms more a frame). What something else stands in front of
        still counts against it: a mostly hidden base still reads low."""
        pb = self.pb
        return near_target_share(pb, raycast_source(pb.base, T_world_base, pb.T_world_camera, pb.cam)[0])

    def around(self, T_g: np.ndarray) -> list:
        """(symmetry, pose) starts from a global result: it, its half turns (partial views often match
        upside down) and the base's near-symmetries (the symmetries proper need no start: their twins
        are derived at the end)."""
        p, base = self.pb.params, self.pb.base
        starts = [(0, T_g @ F) for F in base.flips()] if p.use_flips else [(0, T_g)]
        if p.use_symmetries:
            starts += [(0, T_g @ S) for S in base.near_symmetries]
        return starts

    def coarse(self, starts: list, n_try: int, share: np.ndarray | None = None) -> list[Start]:
        """Screen the (symmetry, pose) starts cheaply (`share`: their screening, where the caller has it),
        refine the best `n_try` (and every start of the prior's) by a few coarse ICP iterations, best first."""
        pb = self.pb
        vg, cam_pos = pb.vg, pb.cam_pos
        share = self.explained([T for _, T in starts]) if share is None else share
        screened = [starts[i] for i in np.argsort(-share, kind="stable")]
        todo = []
        for k, T0 in screened[:n_try] + [s_ for s_ in screened[n_try:] if s_[0] == -1]:
            # cheap view of the model for screening: its outer surface, back faces culled (no occlusion)
            src_b = facing(self.model_pts, self.model_nrm, T0, cam_pos)
            src_b = src_b[icp_source(pb, se3.transform_points(T0, src_b))]  # (what stands in front of a
            # mostly hidden base leaves ICP nothing to match)
            if len(src_b) >= MIN_POINTS:
                todo.append((k, T0, src_b))
        Ts = icp_many([s_ for _, _, s_ in todo], pb.target, [T0 for _, T0, _ in todo], 2.0 * vg, 8, None,
                      pb.params.deterministic, pb.target_tree)  # side by side: one k-d tree query a step for all
        seen = [se3.transform_points(T, facing(self.model_pts, self.model_nrm, T, cam_pos)) for T in Ts]
        shares = near_target_shares(pb, seen)
        return sorted([Start(e, k, T0, T) for (k, T0, _), T, e in zip(todo, Ts, shares)], key=lambda x: -x.explained)


def near_target_share(pb, points_world: np.ndarray) -> float:
    """The share of the model points (world) that lie within a coarse voxel of the (fine) target; 0 for none."""
    return near_target_shares(pb, [points_world])[0]


def near_target_shares(pb, clouds: list[np.ndarray]) -> list[float]:
    """near_target_share of each cloud, in one k-d tree query for all (each point is answered on its own: the
    same shares as one query each)."""
    if not clouds:
        return []
    near = pb.fine_tree.query(np.concatenate(clouds), distance_upper_bound=pb.vg)[0] < np.inf
    out, o = [], 0
    for c in clouds:
        out.append(float(np.mean(near[o:o + len(c)])) if len(c) else 0.0)
        o += len(c)
    return out


def prior_starts(pb, ms: ModelSearch, T_world_source: np.ndarray) -> list:
    """The paper's way, on down-sampled clouds: the CAD in the prior's orientation, seen from the camera,
    registered to the target by RANSAC; plus the plain translated CAD. Marked -1: always refined."""
    out = []
    src_w, _ = raycast_source(pb.base, T_world_source, pb.T_world_camera, pb.cam)
    if len(src_w) >= MIN_POINTS:  # (in the camera's frame, as ModelSearch.ransac)
        T_camera_world = se3.inv(pb.T_world_camera)
        src = cloud(se3.transform_points(T_camera_world, src_w)).voxel_down_sample(pb.vg)
        T_p = global_registration(src, pb.target_cam, normals_fpfh(src, pb.vg, pb.params, np.zeros(3)),
                                  ms.target_features(), pb.vg, pb.params)
        out.append((-1, pb.T_world_camera @ T_p @ T_camera_world @ T_world_source))
    out.append((-1, T_world_source))
    return out


def spread_yaws(share: np.ndarray, n: int, apart: int) -> list[int]:
    """The n best-screened of a ring of yaws (`share` per yaw step, in order round the circle), each at least
    `apart` steps from those picked before it: the best few yaws are mostly neighbours in one basin, and a
    near-round base (a watering can) then never has the turn that fits as well refined, and a wrong turn
    was called confident. Fewer than n when the ring is too small to hold them apart."""
    k = len(share)
    picked: list[int] = []
    for i in np.argsort(-share, kind="stable"):
        if all(min(abs(int(i) - j), k - abs(int(i) - j)) >= apart for j in picked):
            picked.append(int(i))
            if len(picked) == n:
                break
    return picked


def turned_round(pb, ms: ModelSearch, T_world_base: np.ndarray, up: np.ndarray) -> tuple[list, np.ndarray]:
    """(starts, their screening): starts turned about `up` through the base's centre at T_world_base (the best coarse pose), one per yaw step,
    screened there, the best UPRIGHT_STARTS of them at least UPRIGHT_APART steps apart and from the pose itself.
    The first screening centres the model on what is seen of it, which clutter beside the base pulls off;
    the best coarse pose stands where the base is, so there the screening tells the yaws apart: a watering
    can's right turn screened 0.83 around it and below every first start, and a turn 48 degrees off was
    called confident."""
    c = se3.transform_points(T_world_base, pb.base.centre[None])[0]
    angles = np.radians(np.arange(0.0, 360.0, UPRIGHT_YAW_STEP_DEG))
    poses = se3.turn_about(up, angles, c) @ T_world_base
    share = ms.explained(list(poses))
    share[0] = np.inf  # the pose itself, refined already: picked first, so the others keep apart from it
    picked = spread_yaws(share, UPRIGHT_STARTS + 1, UPRIGHT_APART)[1:]
    return [(0, poses[i]) for i in picked], share[picked]


def search_upright(pb, ms: ModelSearch, up: np.ndarray) -> Found | None:
    """Every yaw about the table's normal `up`, no RANSAC; None when nothing fits upright. When no yaw
    fits with what is seen centred, the yaws again standing on the table, slid over it (`resting_starts`)."""
    p, base = pb.params, pb.base
    starts = upright_starts(base, up, pb.coarse_pts, pb.T_world_camera, ms.model_pts, ms.model_nrm)
    share = ms.explained([T for _, T in starts])
    picked = spread_yaws(share, UPRIGHT_STARTS, UPRIGHT_APART)
    coarse = ms.coarse([starts[i] for i in picked], UPRIGHT_STARTS, share[picked])
    slid = False
    fit = ms.view_explained(coarse[0].T_coarse) if coarse else 0.0  # the best start's share of its view explained
    if fit < RESTING_BELOW and pb.table is not None:
        rest = resting_starts(starts, pb.table, ms.model_pts, base.diameter, pb.T_world_camera)
        slid = True
        # screened less what the camera sees past: a small patch of a mostly hidden base is explained as
        # well by hundreds of the slid starts (a gearbox casing's top behind a box: the start nearest the truth,
        # the part on it 3 % of the part's diameter off, ranked 580th of 1764); most stand where the camera sees table behind
        rest_share = ms.explained([T for _, T in rest]) - ms.seen_past([T for _, T in rest])
        resting = ms.coarse(rest, UPRIGHT_STARTS, rest_share)
        coarse = sorted(coarse + resting, key=lambda x: -x.explained)
        fit = ms.view_explained(coarse[0].T_coarse) if coarse else 0.0
    if not coarse or coarse[0].explained < UPRIGHT_FALLBACK:
        return None if not coarse else Found(coarse)
    if fit < RESTING_BELOW:  # (a base the first yaws explain well is told apart by them)
        turned, turned_share = turned_round(pb, ms, coarse[0].T_coarse, up)
        coarse = sorted(coarse + ms.coarse(turned, UPRIGHT_STARTS, turned_share), key=lambda x: -x.explained)
    twins: list[Start] = []
    if p.use_symmetries:
        # a nearly symmetric base (a motor block whose connector alone breaks its 4-fold turn) gives
        # near-equal yaws a quarter turn apart; the screening cannot tell them apart, the refined
        # scores and the discrimination can: each twin of the best is refined, whatever it screens at
        best = coarse[0]
        sym = [(0, best.T_coarse @ S) for S in base.near_symmetries]  # (the symmetries' twins are derived at the end)
        sym = [(k, T) for k, T in sym if keeps_up(T, best.T_coarse)][:UPRIGHT_TWINS]  # the closest-fitting turns
        twins = ms.coarse(sym, UPRIGHT_STARTS) if sym else []
        coarse = sorted(coarse + twins, key=lambda x: -x.explained)
        twins = [best] + twins  # the best itself too: a twin may now screen higher and crowd it out
    return Found(coarse, twins, upright=True, slid=slid)


def search_poses(pb, ms: ModelSearch, prior: np.ndarray | None, T_world_source: np.ndarray) -> Found:
    """The coarse poses of this frame: upright on the table when one is seen (and no prior is given),
    else (or when nothing fits upright) the free search; RANSAC again, longer, when the best start
    explains too little."""
    p = pb.params
    up = None
    if p.upright and prior is None:
        up = pb.table[0] if pb.table is not None else None
    if up is None:
        T_g = ms.ransac()
    extra = prior_starts(pb, ms, T_world_source) if prior is not None else []
    if up is not None:
        found = search_upright(pb, ms, up)
        if found is None or not found.upright:  # nothing fits upright: it is not; search freely
            coarse = found.coarse if found is not None else []
            found = Found(sorted(coarse + ms.coarse(ms.around(ms.ransac()), p.max_starts), key=lambda x: -x.explained))
    else:
        found = Found(ms.coarse(ms.around(T_g) + extra, p.max_starts))
    coarse = found.coarse
    if (not found.upright and p.ransac_retry_iterations and (not coarse or coarse[0].explained < p.retry_below)
            and not pb.out_of_time("the longer RANSAC retry")):
        # the fast RANSAC missed: try harder (the prior's starts are in already)
        T_g = ms.ransac(replace(p, ransac_max_iterations=p.ransac_retry_iterations, seed=p.seed + 1))
        found.coarse = sorted(coarse + ms.coarse(ms.around(T_g), p.max_starts), key=lambda x: -x.explained)
    return found
