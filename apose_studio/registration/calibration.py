"""Is the depth's scale right? A check of the camera's calibration from one confident result.

A `depth_scale` a little off (0.15 for 0.1 mm a unit), or intrinsics for another resolution, scales the
whole scene about the camera's centre. The images cannot tell: the colour image is the same, the mask is
the same, and the model fits the scaled scene nearly as well a little nearer or farther, so the other
checks pass and a confident pose lies 10-50 % too near or too far. Only the model's known size can tell,
and it does through the pixels: at the true scale the model, seen where it is, covers the prompted pixels
it should and no others. So the depth is scaled about the camera by each of SCALE_PROBES, the model refitted
from the pose scaled alike (ICP, no search), and each fit scored by `hypotheses.explained` on the prompted
mask (pixel counts, which a scaled scene leaves comparable). When a scaled depth is explained clearly
better (by more than SCALE_GAIN), the depth's scale is in doubt and the result is not confident. A base mostly
hidden under or behind other objects shows too little of its outline for this (docs/ESTIMATOR.md has the numbers).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.nn import NearestTree
from apose_studio.params import Params
from apose_studio.registration.base import BaseObject, raycast_source
from apose_studio.registration.hypotheses import explained
from apose_studio.registration.pipeline import view_task
from apose_studio.registration.solvers import icp_point_to_plane
from apose_studio.registration.stages import cloud
from apose_studio.registration.task import Task
from apose_studio.registration.types import MIN_POINTS, RegistrationResult, View

SCALE_PROBES = (1 / 1.12, 1.12)  # the depth's scale tried beside the one given: 12 % either way
SCALE_GAIN = 0.025  # a scaled depth explained by more than this share better than the depth as given puts its scale
# in doubt. benchmarks/captures.py: at most 0.006 on the 392 right, confident frames as rendered; with every depth 10 %
# too far or too near, 0.011-0.038 on the mostly hidden bases it told least, over 0.1 on most others


def scaled_pose(T_world_camera: np.ndarray, T_world_base: np.ndarray, f: float) -> np.ndarray:
    """T_world_base with its position in the camera's frame scaled by `f` (the scene scaled about the camera)."""
    T_camera_base = np.linalg.solve(T_world_camera, T_world_base)
    T_camera_base[:3, 3] *= f
    return T_world_camera @ T_camera_base


def refitted(pb: Task, base: BaseObject, T_world_camera: np.ndarray, T_start: np.ndarray, f: float) -> np.ndarray | None:
    """T_world_base refitted to `pb`'s fine target scaled by `f` about the camera (normals unchanged), from T_start:
    point-to-plane ICP of what the camera sees of the model there, at 2 voxels and then at the fine threshold, as
    a refit from a pose does (searches.try_prior, from_pose). None where the camera sees too little of the model.
    All the model's points, also in the first fit: thinned to a quarter there (as try_prior's fits from an
    orientation are), a fidget casing 30 % visible under a stacked object, its depth 10 % too far, refitted from
    its scaled pose onto the wrong surface, and the check missed it (benchmarks/captures.py --depth-scale 1.1)."""
    centre = T_world_camera[:3, 3]
    target = centre + f * (pb.fine_pts - centre)
    normals = np.asarray(pb.fine.normals)
    tree = NearestTree(target)
    seen, _ = raycast_source(base, T_start, T_world_camera, pb.cam)
    if len(seen) < MIN_POINTS:
        return None
    src = np.asarray(cloud(se3.transform_points(se3.inv(T_start), seen)).voxel_down_sample(pb.voxel).points)
    T = icp_point_to_plane(src, target, normals, T_start, 2.0 * pb.voxel, 10, tgt_tree=tree)
    return icp_point_to_plane(src, target, normals, T, pb.thr, pb.params.icp_max_iterations, tgt_tree=tree)


def scale_checked(result: RegistrationResult, view: View, base: BaseObject, params: Params) -> RegistrationResult:
    """`result`, with `depth_scale_better` set where a depth scaled by one of SCALE_PROBES is explained clearly
    better at the model refitted there (the module's doc). Only a confident result is checked: an unconfident one
    claims nothing a wrong scale could make false; and not a frame whose depth scale the renderer wrote
    (`view.depth_scale_known`: a dataset apose rendered, where the scale is exact by construction)."""
    if not (params.scale_check and result.ok and result.confident and result.T_world_base is not None
            and not view.depth_scale_known):
        return result
    t = time.perf_counter()
    # the result's own prepared target; the orientation prior's fast path keeps none, so the view's is prepared
    pb = result.problem if isinstance(result.problem, Task) else view_task(view, base, np.eye(4), params,
                                                                               noise=result.depth_noise)
    if pb is None:
        return result
    own = explained(result, view, base, view.mask)
    best_f, best = 1.0, float("-inf")  # the best explained scaled depth
    if own > 0:
        for f in SCALE_PROBES:
            T = refitted(pb, base, view.T_world_camera, scaled_pose(view.T_world_camera, result.T_world_base, f), f)
            if T is None:
                continue
            scaled = replace(view, depth=view.depth * np.float32(f))
            score = explained(replace(result, T_world_base=T, depth_noise=result.depth_noise * f), scaled, base, view.mask)
            if score > best:
                best_f, best = f, score
    gain = best / own - 1.0 if own > 0 and np.isfinite(best) else float("nan")
    better = best_f if gain > SCALE_GAIN else 1.0
    return replace(result, depth_scale_better=float(better), depth_scale_gain=float(gain),
                   timings={**result.timings, "scale check": time.perf_counter() - t})
