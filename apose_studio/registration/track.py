"""Tracking: the next frame's pose from the last confident one, at camera rate.

A camera moving over a placement (an eye-in-hand approach, `apose render --trajectory`) sees the base
where it was a moment ago. `track` starts there instead of searching: the base's surface samples at the
last pose (moved into the new camera, whose pose the robot knows; without one the base is assumed to
stay put in the camera's frame) say which depth pixels may be the base; those near the model at that
pose (within `track_motion` of the base's diameter) are registered onto what the camera sees of the
model there (ray cast, with the model's exact normals), by a short point-to-plane ICP whose correspondence
distance shrinks from that motion to the depth's noise on a few hundred of them, then, on all of them
(`track_points`), at the estimator's polish distance; then the pose is judged by the estimator's own rules
(`pipeline.judge`: coverage, contradiction, the spread the data allows, the table, the outline), on the
depth down-sampled as the estimator's (one point per voxel), so that the spread reads alike. A tracked
pose that does not fit is *lost*; the caller (estimation.Tracker) detects the base anew, and says so. No
search, no mask: the model at the last pose is the mask.

Deterministic like the rest: the ICP is numpy's (solvers.icp_point_to_plane), the pixels taken are a
fixed grid. Frames: T_<to>_<from>, metres.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import cv2
import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.nn import NearestTree
from apose_studio.geometry.sensor import nearest_within
from apose_studio.params import Params
from apose_studio.registration.base import BaseObject, raycast_source
from apose_studio.registration.pipeline import judged
from apose_studio.registration.scoring import NOISE_SIGMAS, agreement_tolerance, depth_window, pixel_box, pixels
from apose_studio.registration.solvers import icp_point_to_plane
from apose_studio.registration.stages import down_sample
from apose_studio.registration.table import table_plane
from apose_studio.registration.types import MIN_POINTS, RegistrationResult, Stage, View, failed

COARSE_POINTS = 300  # the rounds before the last one (wide reach, a rough fit) register this many of the points
OVERSAMPLE = 1.5  # readings of the grid per point kept (then n_points of them, evenly spread)
STEP_FRACTION = 0.02  # an ICP iteration that moves the base by less than this share of a voxel ends its round
JUDGE_MARGIN_PX = 16  # the judge's window: the model's pixels and this many around (its outline ring reaches 5)
START_SPREAD = 3.0  # the ICP starts at this many times the median distance of the depth to the predicted model
SHRINK_PX = 3  # the depth registered lies this far inside the base's predicted outline: clutter touching it stays out
TRUST_SHARE = 0.6  # a tracked pose that moved the base's farthest point by more than this share of the tracker's
# reach (track_motion x diameter) since the last frame is not trusted: the depth it registered was cut at that reach
# (a camera without poses closing in at 10 Hz: 26 mm moved, 19 mm found, the part 7.9 mm off and judged confident)
TABLE_RING = 0.3  # the table is looked for around the base's predicted window, this share of the window wider a side
TABLE_HOLD = 0.3  # the table is still where it was when this share of the depth around the base lies on it
TABLE_TOLERANCES = 2.0  # ... within this many final ICP distances


POLISH_SHRINK_PX = 1  # the polish's points lie this far inside the predicted outline (the rough fit's: SHRINK_PX):
# at the polish's distance clutter touching the base is left out anyway, and the outline's pixels pin the turn (a small
# bracket's p90 error 0.37 -> 0.10 mm under RealSense-like noise)
RECAST_VOXELS = 0.5  # a tracked pose this many voxels from where the model was cast is cast again for the judge
POLISH_ROUND = 4  # ICP iterations kept for the polish (the last round), of track_iterations
FULL_RES_PX = 12_000  # a base predicted over more pixels than this is cast and judged on every other pixel and row
# (half_resolution; the depth registered is still the full image's): the ray cast, the scoring and the judge
# grow with the pixels the base covers, and a base filling the view at the end of an approach took 15-17 ms a frame
# at full resolution (benchmarks/track.py)


def half_resolution(depth: np.ndarray, cam: CameraIntrinsics) -> tuple[np.ndarray, CameraIntrinsics]:
    """Every other pixel and row of a depth image, and the camera of those pixels (pixel (i, j) is the full image's
    (2i, 2j): the same rays, the focal lengths and principal point halved)."""
    h = depth[::2, ::2]
    return h, CameraIntrinsics(h.shape[1], h.shape[0], cam.fx / 2, cam.fy / 2, cam.cx / 2, cam.cy / 2)


@dataclass(frozen=True)
class Prediction:
    """Where the base should be in the new frame: T_world_base, the depth its surface would show in the
    pixel window that holds it (inf where it shows none), and that window (v0, v1, u0, u1), or None when
    it is out of the image. `hidden`: the window's pixels where something stood over the base in the frame the
    pose came from (hidden_window), or None when not known."""

    T_world_base: np.ndarray
    zbuf: np.ndarray  # (v1 - v0, u1 - u0): the window's pixels
    window: tuple[int, int, int, int] | None
    hidden: np.ndarray | None = None


def predict(last: RegistrationResult, T_world_camera: np.ndarray, cam: CameraIntrinsics,
            hidden: np.ndarray | None = None) -> Prediction:
    """The base at the last pose seen from the new camera: what the camera saw of it then (the last
    result's source cloud, one point per pixel), splatted into the new image, its gaps closed (the
    window's depth, `Prediction.zbuf`). `hidden`: the source's points (base frame) that something stood over in
    the last frame (hidden_points), splatted alike into the same window (`Prediction.hidden`)."""
    seen = se3.transform_points(last.T_world_base, last.source_cloud)
    zbuf, window = depth_window(seen, T_world_camera, cam, 1)
    if window is None or min(zbuf.shape) < 3:
        return Prediction(last.T_world_base, zbuf.astype(np.float32), None)
    zbuf = nearest_within(zbuf, 1)  # the nearest of each 3x3: the splat's gaps closed
    covered = None
    if hidden is not None and len(hidden):
        covered = hidden_window(se3.transform_points(last.T_world_base, hidden), T_world_camera, cam, window)
    return Prediction(last.T_world_base, zbuf, window, covered)


def hidden_window(points_world: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics,
                  window: tuple[int, int, int, int]) -> np.ndarray:
    """(v1 - v0, u1 - u0) bool: the window's pixels the points fall in, their gaps closed (3 x 3), specks narrower
    than HIDDEN_MIN_PX dropped (a morphological opening) and the rest a pixel wider (the mixed pixels along the
    edge of what stood there). A few scattered points that Kinect-like noise put behind the depth are no object: cut
    from the region with the tracker's inward margin round each, they let a desk object's pose wander 1.6-7.3 mm over
    five repeats of one still frame (0.2-1.9 mm without them)."""
    v0, v1, u0, u1 = window
    v, u, z, inside = pixels(points_world, T_world_camera, cam)
    inside &= (v >= v0) & (v < v1) & (u >= u0) & (u < u1) & (z > 0)
    splat = np.zeros((v1 - v0, u1 - u0), np.uint8)
    splat[v[inside] - v0, u[inside] - u0] = 1
    closed = cv2.dilate(splat, np.ones((3, 3), np.uint8))
    k = np.ones((HIDDEN_MIN_PX + 2,) * 2, np.uint8)  # + 2: the closing's pixel each side
    return cv2.dilate(cv2.erode(closed, k), k) > 0


HIDDEN_MIN_PX = 3  # hidden_window: a region of hidden points narrower than this many pixels is taken for noise
HIDDEN_TOLERANCES = 1.0  # hidden_points: a point whose pixel's depth lies more than this many of the tracker's
# final distances (final_distance) in front of it is hidden


def hidden_points(result: RegistrationResult, depth: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray,
                  tol: float) -> np.ndarray:
    """The result's source points (base frame: what the camera sees of the model at its pose) that something nearer
    hides in this frame: those whose pixel's depth lies more than `tol` in front of them. A flat object lying on the
    base, or one standing in front, stands over the points it hides; tracked from them, its depth lies within the
    tracker's reach of the base's predicted surface and was registered as the base's (a desk object under a flat
    one 14-21 mm above its top: the next frame's pose pulled 22-29 mm up, and the base detected anew on every frame
    of a camera holding still). The next frame's region leaves out where they fall (hidden_window)."""
    pts = result.source_cloud
    if len(pts) == 0:
        return pts
    world = se3.transform_points(result.T_world_base, pts)
    v, u, z, inside = pixels(world, T_world_camera, cam)
    inside &= z > 0
    own, window = depth_window(world, T_world_camera, cam, 0)  # the model's own nearest surface per pixel
    if window is None:
        return pts[:0]
    front = np.zeros(len(pts), bool)  # a point the model itself hides from this camera (a fused result's source holds
    # what another camera saw) is not hidden by anything else
    front[inside] = z[inside] <= own[v[inside] - window[0], u[inside] - window[2]] + tol
    d = depth[v, u]
    with np.errstate(invalid="ignore"):
        hidden = front & np.isfinite(d) & (d > 0) & (d < z - tol)
    return pts[hidden]


def region_points(depth: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray, pred: Prediction,
                  motion: float, n_points: int, shrink: int = SHRINK_PX) -> np.ndarray:
    """World points of the depth the base may show now: pixels `shrink` inside its predicted outline whose
    depth lies within `motion` of the predicted surface (not an object in front, not the table seen past
    it). A pixel grid fine enough for OVERSAMPLE x n_points readings; at most n_points kept, evenly spread.
    The table round the base's foot is not cut away: the ICP registers onto what the camera sees of the model
    at the polish's distance, which the table lies beyond, and a cut a few millimetres above the table kept
    the points that noise lifted and dropped those it lowered (a far casing was lifted 2.4 mm)."""
    v0, v1, u0, u1 = pred.window
    z = pred.zbuf
    inside = cv2.erode(np.isfinite(z).astype(np.uint8), np.ones((2 * shrink + 1,) * 2, np.uint8)) > 0
    if pred.hidden is not None:  # not where something stood over the base in the last frame
        inside &= ~pred.hidden
    d = depth[v0:v1, u0:u1]
    with np.errstate(invalid="ignore"):
        ok = inside & np.isfinite(d) & (d > 0) & (np.abs(d - z) < motion)
    area = int(ok.sum())
    stride = max(1, int(np.sqrt(area / (OVERSAMPLE * n_points))))
    grid = np.zeros_like(ok)
    grid[::stride, ::stride] = True
    vs, us = np.nonzero(ok & grid)
    pts_c = cam.backproject((us + u0).astype(float), (vs + v0).astype(float), d[vs, us].astype(float))
    pts_w = se3.transform_points(T_world_camera, pts_c)
    if len(pts_w) > n_points:
        pts_w = pts_w[np.linspace(0, len(pts_w) - 1, n_points).astype(int)]
    return pts_w


def moved_by(base: BaseObject, T_world_from: np.ndarray, T_world_to: np.ndarray) -> float:
    """How far the base's farthest model sample moves between two poses (metres)."""
    D = se3.inv(T_world_from) @ T_world_to
    pts = base.extremes()
    return float(np.linalg.norm(se3.transform_points(D, pts) - pts, axis=1).max())


def final_distance(params: Params, base: BaseObject, last: RegistrationResult) -> float:
    """The rough fit's last reach (and the table's tolerance): the estimator's polish distance, or NOISE_SIGMAS of
    the depth noise where larger."""
    return max(params.polish_threshold_factor * params.voxel(base.diameter), NOISE_SIGMAS * last.depth_noise)


def table_now(plane: tuple[np.ndarray, float] | None, depth: np.ndarray, cam: CameraIntrinsics,
              T_world_camera: np.ndarray, pred: Prediction, base: BaseObject, tol: float) -> tuple[np.ndarray, float] | None:
    """The table under the base in this frame: `plane` (world) when the depth around the base's predicted
    window still lies on it (TABLE_HOLD of it within `tol`), else fitted anew (table.table_plane, the predicted
    silhouette left out), or None. A plane is kept in the world's frame, which moves with the camera when the
    camera's pose is not known (a live camera without the robot's kinematics: the identity every frame); a
    stale plane would cut the wrong depth and let a pose sunk into the real table pass as resting on it
    (a 31 mm slide was judged confident that way)."""
    if plane is None or pred.window is None:
        return plane
    h_img, w_img = depth.shape
    v0, v1, u0, u1 = pred.window
    mv, mu = int((v1 - v0) * TABLE_RING) + 2, int((u1 - u0) * TABLE_RING) + 2
    V0, V1, U0, U1 = max(v0 - mv, 0), min(v1 + mv, h_img), max(u0 - mu, 0), min(u1 + mu, w_img)
    step = max(1, int(np.sqrt((V1 - V0) * (U1 - U0) / 1500)))
    vs, us = (a.ravel() for a in np.mgrid[V0:V1:step, U0:U1:step])
    silhouette = np.zeros(depth.shape, bool)
    silhouette[v0:v1, u0:u1] = np.isfinite(pred.zbuf)
    d = depth[vs, us]
    with np.errstate(invalid="ignore"):
        keep = ~silhouette[vs, us] & np.isfinite(d) & (d > 0)
    if keep.sum() >= 50:
        pts = se3.transform_points(T_world_camera, cam.backproject(us[keep].astype(float), vs[keep].astype(float),
                                                                    d[keep].astype(float)))
        if np.mean(np.abs(pts @ plane[0] + plane[1]) < tol) >= TABLE_HOLD:
            return plane
    return table_plane(depth, silhouette, cam, T_world_camera, base_size=base.diameter)


def track(depth: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray, base: BaseObject,
          T_base_part: np.ndarray, params: Params, last: RegistrationResult,
          plane: tuple[np.ndarray, float] | None = None, pred: Prediction | None = None) -> RegistrationResult:
    """The base in a new frame, from `last` (a confident result of the frame before): judged like any
    estimate, `tracked` set. ok=False with the reason when the base left the view or too little of it is
    near where it was. `plane`: the table the base stands on (world; `table_now`'s for this frame). `pred`: the
    prediction for this frame, when the caller has made it. Where the base is predicted over more than
    FULL_RES_PX pixels, the model is cast and the pose judged at half resolution (its mask brought back to full
    size)."""
    t0 = time.perf_counter()
    p = params
    voxel = p.voxel(base.diameter)
    noise = last.depth_noise
    motion = p.track_motion * base.diameter
    pred = predict(last, T_world_camera, cam) if pred is None else pred
    t_pred = time.perf_counter()
    lost = {"preset": p.preset, "tracked": True, "voxel": voxel}
    if pred.window is None:
        return failed("tracking lost: at its last pose the base is out of this view", **lost)
    final = final_distance(p, base, last)
    dense = region_points(depth, cam, T_world_camera, pred, motion, p.track_points, POLISH_SHRINK_PX)
    coarse = region_points(depth, cam, T_world_camera, pred, motion, COARSE_POINTS)
    if len(coarse) < MIN_POINTS:  # a base seen over a few pixels: its outline's ring is all there is
        coarse = dense[::max(1, -(-len(dense) // COARSE_POINTS))]
    t_region = time.perf_counter()
    if len(dense) < MIN_POINTS:
        return failed(f"tracking lost: only {len(dense)} depth points near where the base was (need {MIN_POINTS}); "
                      "it moved further than the tracker follows, or something hides it", target_cloud=dense, **lost)
    shape = depth.shape
    if np.isfinite(pred.zbuf).sum() > FULL_RES_PX:  # a base filling the view: every other pixel is plenty to judge by
        depth, cam = half_resolution(depth, cam)
    # the depth is registered onto what the camera sees of the model where the base should be, with the model's
    # exact normals: the whole model's samples had matched faces hidden behind the visible ones (a casing's
    # flanges and ribs, a few millimetres deeper), which drew a far casing 1-2 mm towards the camera
    seen_w, seen_n = raycast_source(base, pred.T_world_base, T_world_camera, cam)
    if len(seen_w) < MIN_POINTS:
        return failed("tracking lost: the camera sees (almost) nothing of the base where it should be", **lost)
    T = se3.inv(pred.T_world_base)  # T_base_world: the depth registered onto the model (scene to model)
    seen_b, normals_b = se3.transform_points(T, seen_w), seen_n @ T[:3, :3].T
    tree = NearestTree(seen_b)
    t_cast = time.perf_counter()
    thr, left = start_threshold(coarse, T, tree, motion, final), p.track_iterations
    while left > POLISH_ROUND:  # the rough fit: a few of the points, the reach shrinking to the depth's noise
        n = min(3, left - POLISH_ROUND)
        T = icp_point_to_plane(coarse, seen_b, normals_b, T, thr, n, tgt_tree=tree, min_step=STEP_FRACTION * voxel)
        left -= n
        if thr <= final * 1.0001:
            break
        thr = max(final, thr / 3)
    # the polish, as the estimator's (refine.polish): every point, at the polish's distance (three sigmas of
    # Kinect-like noise let in what pulled a far casing towards the camera)
    T = icp_point_to_plane(dense, seen_b, normals_b, T, p.polish_threshold_factor * voxel, max(left, 1), tgt_tree=tree,
                           min_step=STEP_FRACTION * voxel)
    T_world_base = se3.inv(T)
    t_icp = time.perf_counter()
    moved = moved_by(base, last.T_world_base, T_world_base)
    if moved > TRUST_SHARE * motion:
        return failed(f"tracking lost: the base moved {moved * 1000:.0f} mm since the last frame, near the tracker's "
                      f"reach ({motion * 1000:.0f} mm; track_motion): searched for anew", target_cloud=dense, **lost)
    if moved_by(base, pred.T_world_base, T_world_base) > RECAST_VOXELS * voxel:  # what the camera sees has changed
        seen, _ = raycast_source(base, T_world_base, T_world_camera, cam)
        seen_b = se3.transform_points(T, seen)
        tree = NearestTree(seen_b)
    else:  # moved by a fraction of a voxel from where it was cast: the same faces seen
        seen = se3.transform_points(T_world_base, seen_b)
    if len(seen) < MIN_POINTS:
        return failed("tracking lost: the camera sees (almost) nothing of the base at the tracked pose", **lost)
    t_polish = time.perf_counter()
    target = np.asarray(down_sample(dense, voxel, T_world_camera).points)  # the estimator's density (its fine
    # cloud): the pose's spread the judge reads grows as 1/sqrt(points), and 800 had read 2.5x the estimator's
    fit_thr = p.icp_threshold_factor * voxel
    loose = max(fit_thr, 2 * voxel, NOISE_SIGMAS * noise)
    d = tree.query(se3.transform_points(T, target), distance_upper_bound=loose)[0]
    inl = d < fit_thr
    fitness = float(inl.mean())
    rmse = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else 0.0
    # the judge looks at the model's window only (its rules read nothing farther than a few pixels outside the
    # model's silhouette): whole-image filters cost more than the rest of a tracked frame
    depth_w, cam_w, (v0, v1, u0, u1) = window_view(seen, depth, T_world_camera, cam, JUDGE_MARGIN_PX)
    mask_w = observed_mask(seen, depth_w, T_world_camera, cam_w, agreement_tolerance(voxel, noise))
    mask = np.zeros(depth.shape, bool)
    mask[v0:v1, u0:u1] = mask_w
    if mask.shape != shape:  # judged at half resolution: each pixel's mask over its 2x2 of the frame
        mask = mask.repeat(2, axis=0).repeat(2, axis=1)[:shape[0], :shape[1]]
    result = RegistrationResult(
        ok=True, T_world_base=T_world_base, T_world_part=T_world_base @ T_base_part,
        T_world_source=last.T_world_base, target_cloud=target,
        source_cloud=seen_b, fitness=fitness, inlier_rmse=rmse,
        stages=[Stage("last frame's pose", last.T_world_base, float("nan"), float("nan")),
                Stage("final", T_world_base, fitness, rmse)],
        voxel=voxel, coverage=float(np.mean(d < loose)), depth_noise=noise, preset=p.preset, tracked=True,
        model_mask=mask)
    t = time.perf_counter()
    verdict = judged(result, View(depth_w, mask_w, cam_w, T_world_camera), base, p, plane)
    return replace(verdict, timings={"track predict": t_pred - t0, "track region": t_region - t_pred,
                                     "track cast": t_cast - t_region, "track icp": t_icp - t_cast,
                                     "track recast": t_polish - t_icp, "track score": t - t_polish,
                                     "track judge": time.perf_counter() - t})


def window_view(points_world: np.ndarray, depth: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics,
                pad: int) -> tuple[np.ndarray, CameraIntrinsics, tuple[int, int, int, int]]:
    """The depth and camera of the points' pixel box (`pixel_box`): the same pixels and rays, a smaller image.
    (depth window, its camera, (v0, v1, u0, u1)); the whole image when too few points fall in it."""
    found = pixel_box(points_world, T_world_camera, cam, pad)
    v0, v1, u0, u1 = found[3] if found is not None else (0, cam.height, 0, cam.width)
    sub = CameraIntrinsics(u1 - u0, v1 - v0, cam.fx, cam.fy, cam.cx - u0, cam.cy - v0)
    return depth[v0:v1, u0:u1], sub, (v0, v1, u0, u1)


def start_threshold(points: np.ndarray, T_base_world: np.ndarray, tree, motion: float, final: float) -> float:
    """The ICP's first correspondence distance: wide (`motion`) when the prediction is off, narrow when it is
    good. START_SPREAD x the median distance of the points to the model at the predicted pose, within
    [final, motion]; `motion` when fewer than half of them lie within `motion` of it."""
    d = tree.query(se3.transform_points(T_base_world, points), distance_upper_bound=motion)[0]
    near = d[np.isfinite(d)]
    if len(near) < 0.5 * len(d):
        return motion
    return float(np.clip(START_SPREAD * np.median(near), final, motion))


def observed_mask(seen: np.ndarray, depth: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics,
                  tol: float) -> np.ndarray:
    """The base's mask as the tracked pose finds it in the depth: pixels of the model's silhouette (2 px wider,
    as the model-cut mask) where the depth lies within `tol` of the model's surface. What the judge takes as
    the mask: where the camera sees past the model away from this mask's edge contradicts the pose."""
    zbuf, window = depth_window(seen, T_world_camera, cam, 3)
    mask = np.zeros(depth.shape, bool)
    if window is None:
        return mask
    v0, v1, u0, u1 = window
    zbuf = nearest_within(zbuf, 2)
    d = depth[v0:v1, u0:u1]
    with np.errstate(invalid="ignore"):
        mask[v0:v1, u0:u1] = np.isfinite(zbuf) & (d > 0) & (np.abs(d - zbuf) < tol)
    return mask
