"""One call for robot code: the assembly pose from one RGB-D frame held in arrays.

    from apose_studio.api import estimate_pose
    est = estimate_pose(rgb, depth_m, K, "assembly.yaml", step=2, box=(210, 140, 420, 330))
    if est.ok and est.confident:
        robot.place(est.T_world_part)        # 4x4, metres; T_camera_part without extrinsics

Masks, in order of preference: the caller's `mask`; a prompt (`box` x0,y0,x1,y1 or `point` u,v in
pixels: `prompt.prompted_mask`); else depth alone (`segment.depth_mask`, the object nearest the image
centre). Without `T_world_camera`, the world frame lies on the table (z up) when one is seen.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from apose_studio.assembly.grasps import Grasp
from apose_studio.assembly.model import Assembly
from apose_studio.data.dataset import check_camera_entry, world_frame
from apose_studio.errors import AposeError
from apose_studio.estimation import (
    StepContext,
    array_mask,
    check_colour,
    check_mask,
    colour_registered,
    estimate_pick,
    estimate_view,
    step_context,
)
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.masks.prompt import check_box
from apose_studio.registration import Params, doubts, resolve_params
from apose_studio.registration.types import RegistrationResult, View
from apose_studio.robot.handeye import HandEye, read_hand_eye
from apose_studio.robot.targets import Targets, add_pick, place_targets

__all__ = ["PoseEstimate", "camera_from_K", "check_mask", "estimate_pose", "pose_estimate", "read_hand_eye",
           "robot_targets", "run_registration", "step_context"]


@dataclass
class PoseEstimate:
    ok: bool
    reason: str
    T_world_camera: np.ndarray
    T_world_base: np.ndarray | None
    T_world_part: np.ndarray | None
    T_camera_part: np.ndarray | None
    confident: bool
    coverage: float
    ambiguous: bool
    alternatives: list[np.ndarray]  # T_world_part of the other placements that fit as well
    mask: np.ndarray
    mask_source: str  # "given", "box", "point", "depth", "gt", "MASK.png", a model path
    timings: dict[str, float] = field(default_factory=dict)  # seconds: mask, registration, total
    result: object = None  # the full registration.RegistrationResult
    doubts: str = ""
    equivalent: list[np.ndarray] = field(default_factory=list)  # T_world_part of the placements an exact symmetry of
    # the base makes the same assembly (the part may equally go there)
    T_world_part_approach: np.ndarray | None = None  # where the step's `approach` starts (None: the step has none)
    targets: object = None  # robot.targets.Targets: gripper poses in the robot's frame, when a hand-eye calibration
    # was given (robot_targets)
    base_alternatives: list[np.ndarray] = field(default_factory=list)  # T_world_base of the base turned another way
    # that places the part alike and fits as well: the part's place is sure, the base's own turn is not
    depth_shift_px: tuple[int, int] = (0, 0)  # how far the depth lay shifted (right, down) against the colour image,
    # moved back: around the prompt before the mask (align_depth, estimation.colour_registered), or after a first
    # estimate whose colour check found it off (estimation.estimate_view, `move_depth_to_colour`)
    world: str = ""  # what T_world_camera's world is, in words (data.dataset.world_frame; a dataset's Frame.world)
    prompt_box: tuple[int, int, int, int] | None = None  # the box that prompted the mask, as given (None: no box)
    depth_scale_better: float = 1.0  # a factor on the depth that the model explains clearly better: the depth_scale or
    # the intrinsics look off, and the pose with them (registration.calibration); 1.0: none, or not checked

    def to_json(self) -> dict:
        def m(T):
            return None if T is None else np.asarray(T).tolist()

        cov = self.coverage if np.isfinite(self.coverage) else None
        return {"ok": self.ok, "reason": self.reason, "T_world_base": m(self.T_world_base),
                "T_world_part": m(self.T_world_part), "T_world_part_approach": m(self.T_world_part_approach),
                "T_camera_part": m(self.T_camera_part),
                "T_world_camera": m(self.T_world_camera), "world": self.world, "confident": self.confident,
                "coverage": cov,
                "doubts": self.doubts, "ambiguous": self.ambiguous, "alternatives": [m(T) for T in self.alternatives],
                "equivalent": [m(T) for T in self.equivalent],
                "base_confident": bool(self.confident and not self.base_alternatives),
                "base_alternatives": [m(T) for T in self.base_alternatives],
                "mask": {"source": self.mask_source, "pixels": int(self.mask.sum()), **({} if self.prompt_box is None else {
                    "prompt_box": [int(v) for v in self.prompt_box],  # and as used: within the image
                    "prompt_box_used": [int(v) for v in check_box(self.prompt_box, self.mask.shape)]})},
                "timings_s": {k: round(v, 4) for k, v in self.timings.items()},
                "depth_shift_px": [int(v) for v in self.depth_shift_px],
                "depth_scale_better": round(float(self.depth_scale_better), 4),
                **(self.targets.to_json() if self.targets is not None else {})}


def camera_from_K(K, width: int, height: int) -> CameraIntrinsics:
    """The intrinsics of a `width` x `height` image from K (3x3, or its 9 numbers row by row), checked as a capture's
    camera.json is (data.dataset.check_camera_entry: a pinhole matrix without skew, focal lengths a camera can have,
    the principal point one of this image's). AposeError naming K otherwise."""
    try:
        K = np.asarray(K, float)
    except (TypeError, ValueError):
        raise AposeError(f"K must be a 3x3 intrinsic matrix of numbers (or its 9 numbers), got {type(K).__name__}") from None
    if K.shape == (9,):
        K = K.reshape(3, 3)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise AposeError(f"K must be a 3x3 intrinsic matrix with positive fx, fy; got {np.asarray(K).tolist()}"[:200])
    return check_camera_entry({"cam_K": K.reshape(-1).tolist(), "depth_scale": 1.0}, "K", width, height)[0]


def pixel_numbers(value, n: int, name: str) -> tuple[int, ...] | None:
    """`value` (a box: n=4, x0, y0, x1, y1; a point: n=2, u, v) as whole pixels, None for None; AposeError naming
    `name` for anything else (text, NaN, the wrong count)."""
    if value is None:
        return None
    try:
        nums = [float(v) for v in value]
    except (TypeError, ValueError):
        raise AposeError(f"{name} must be {n} pixel numbers, got {str(value)[:60]!r}") from None
    if len(nums) != n or not all(np.isfinite(nums)):
        raise AposeError(f"{name} must be {n} finite pixel numbers, got {str(value)[:60]!r}")
    return tuple(int(round(v)) for v in nums)


def estimate_pose(rgb: np.ndarray, depth: np.ndarray, K, assembly, step: int, *, T_world_camera=None,
                  mask=None, box=None, point=None, preset: str = "default", orientation_prior: bool = False,
                  hand_eye=None, grasp: str | None = None, pick_box=None, pick_point=None, T_robot_flange=None,
                  align_depth: bool = False, **params) -> PoseEstimate:
    """The assembly pose of `step`'s part from one frame. rgb (H, W, 3) uint8 (RGBA loses its alpha, a grey (H, W)
    image is taken as each channel; a float or 16-bit image is refused with the fix); depth (H, W) metres (0 or
    NaN where missing); K 3x3. Raises AposeError on bad input; a failed estimate is ok=False with a reason.

    With `hand_eye` (a HandEye, or the path of a calibration file: robot.handeye) the estimate also carries
    `targets`: the gripper's poses in the robot's frame for `grasp` (default: the part's first), and with a
    `pick_box` / `pick_point` around the loose part in the same frame, where to pick it (robot_targets).

    `align_depth` (with a box or point): the depth moved back onto the colour image when, around the prompt, it
    lies shifted against it (estimation.colour_registered; `depth_shift_px` says how far it lay). Without it, the
    colour check after the estimate does the same when it finds the depth's edges clearly off the colour's, less
    the object's own (parameters `colour_check`, `move_depth_to_colour`: estimation.estimate_view)."""
    t0 = time.perf_counter()
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)):
        raise AposeError(f"step must be a whole number (1 for the first step), got {step!r}"[:120])
    box, point = pixel_numbers(box, 4, "box"), pixel_numbers(point, 2, "point")
    pick_box, pick_point = pixel_numbers(pick_box, 4, "pick_box"), pixel_numbers(pick_point, 2, "pick_point")
    depth = np.asarray(depth, np.float32)
    if depth.ndim != 2:
        raise AposeError(f"depth must be an (H, W) image in metres, got shape {depth.shape}")
    rgb = check_colour(rgb, depth.shape)
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    cam = camera_from_K(K, depth.shape[1], depth.shape[0])
    asm, ctx = step_context(assembly, step)  # cached: the second call for this file and step costs nothing
    p = resolve_params(preset, asm.registration, **params)
    ctx.base.warm_up(p)
    t_load = time.perf_counter() - t0
    t1 = time.perf_counter()
    depth, shift = colour_registered(rgb, depth, box, point) if align_depth else (depth, (0, 0))
    T_world_camera, world = world_frame(T_world_camera, depth, cam, "given (T_world_camera)")
    m, source = array_mask(rgb, depth, cam, mask, box, point, region=ctx.base.region is not None)
    view = View(depth, m, cam, np.asarray(T_world_camera, float), rgb=rgb, box=box)
    est = run_registration(view, source, ctx, p, orientation_prior, t0, time.perf_counter() - t1, t_load=t_load)
    if est.result is not None and est.result.input_error:  # the input's fault, found at the estimate (units 10x off,
        # a mask of the whole scene): bad input, raised as every other is (`apose estimate` exits 2 on it)
        raise AposeError(est.reason)
    est.world = world
    if shift != (0, 0):  # moved before the mask, as asked (the estimate then found none left to move)
        est.depth_shift_px = shift
    if hand_eye is None:
        return est
    pick = None
    if pick_box is not None or pick_point is not None:
        t_pick = time.perf_counter()
        pick_mask, _ = array_mask(rgb, depth, cam, box=pick_box, point=pick_point)
        pick = estimate_pick(View(depth, pick_mask, cam, view.T_world_camera, rgb=rgb, box=pick_box), ctx.part, p)
        est.timings["pick"] = time.perf_counter() - t_pick  # its mask and registration; not in "total" (the place's)
    est.targets = robot_targets(est, asm, ctx, hand_eye, grasp, pick, T_robot_flange)
    return est


def grasp_of(asm: Assembly, part: str, name: str | None, key: str = "--grasp") -> Grasp | None:
    """The part's grasp called `name` (None: its first; None when it has none); AposeError for an unknown name,
    which starts with `key` (the flag or request key that gave it)."""
    grasps = asm.parts[part].grasps
    if name is None:
        return grasps[0] if grasps else None
    for g in grasps:
        if g.name == name:
            return g
    have = ", ".join(g.name for g in grasps) if grasps else "none (add parts.<id>.grasps to the assembly file)"
    raise AposeError(f"{key} {name}: {part} has no grasp of that name; its grasps: {have}"[:300])


def robot_targets(est: PoseEstimate, asm: Assembly, ctx: StepContext, hand_eye, grasp: str | None = None,
                  pick: RegistrationResult | None = None, T_robot_flange=None) -> Targets:
    """The pick-and-place targets of an estimate in the robot's frame (robot.targets): `hand_eye` a HandEye
    or a calibration file's path; `grasp` a grasp name of the step's part (default its first); `pick` the
    part's own estimate where it lies (estimation.estimate_pick) in the same frame; `T_robot_flange` the arm's
    pose at the capture (eye-in-hand)."""
    he = hand_eye if isinstance(hand_eye, HandEye) else read_hand_eye(hand_eye)
    g = grasp_of(asm, ctx.view.part, grasp)
    T_robot_camera = he.T_robot_camera(T_robot_flange)
    T_camera_world = se3.inv(est.T_world_camera)
    if est.ok:
        t = place_targets(T_robot_camera, T_camera_world @ est.T_world_base, est.T_camera_part, g, ctx.view.approach,
                          asm.parts[ctx.view.part].symmetry, [T_camera_world @ E for E in est.equivalent],
                          he.robot_frame, he.camera_frame)
    else:
        t = Targets(he.robot_frame, he.camera_frame, T_robot_camera, grasp=g.name if g else None,
                    notes=["no assembly pose in this frame: no place targets"])
    t.notes += list(he.notes)
    if pick is not None:
        t.pick = {"ok": bool(pick.ok), "confident": bool(pick.confident), "reason": pick.reason,
                  "doubts": "" if pick.confident or not pick.ok else doubts(pick)}
        if pick.ok:
            add_pick(t, T_robot_camera @ T_camera_world @ pick.T_world_base, g)
    return t


def run_registration(view: View, source: str, ctx: StepContext, params: Params, orientation_prior: bool, t0: float,
                     t_mask: float, trace_iterations: bool = False, t_load: float = 0.0) -> PoseEstimate:
    """The registration step of estimate_pose (and of `apose estimate`) on a view whose mask is found, as
    the robot-facing record. Seconds: `t0` when the call began; `t_load` what reading the files, the
    step's base and its warm-up took (the first call in a process also pays its imports there: 0 once
    warm); `t_mask` what the mask took. Callers warm the step's base up first (estimate_view would
    otherwise do it inside the registration's time)."""
    t1 = time.perf_counter()
    r = estimate_view(view, ctx, params, orientation_prior, trace_iterations)
    t2 = time.perf_counter()
    mask = view.mask
    if r.reading:  # the estimate came from another reading of the mask (registration/hypotheses.py)
        source = f"{source}, {r.reading}"
    if r.model_mask is not None:  # what the model shows at the pose: occluders and clutter cut, what the prompt missed added
        mask, source = r.model_mask, f"{source}, cut to the model's view"
    return pose_estimate(r, view.T_world_camera, ctx.view, mask, source,
                         {"load": t_load, "mask": t_mask, "registration": t2 - t1, "total": t2 - t0}, view.box)


def pose_estimate(r: RegistrationResult, T_world_camera, view, mask, source, timings,
                  prompt_box: tuple[int, int, int, int] | None = None) -> PoseEstimate:
    """A registration result as the robot-facing record (T_camera_part, the approach pose, the doubts); `prompt_box`:
    the box that prompted the mask, as given."""
    ok = bool(r.ok)
    approach = view.approach.start(r.T_world_part, r.T_world_base) if ok and view.approach is not None else None
    return PoseEstimate(ok, r.reason, T_world_camera, r.T_world_base if ok else None, r.T_world_part if ok else None,
                        se3.inv(T_world_camera) @ r.T_world_part if ok else None, bool(r.confident), float(r.coverage),
                        bool(r.ambiguous), [c.T_world_part for c in r.alternatives], mask, source, dict(timings), r,
                        "" if r.confident or not ok else doubts(r), r.equivalent if ok else [], approach,
                        base_alternatives=list(r.base_alternatives) if ok else [], depth_shift_px=r.depth_moved_px,
                        depth_scale_better=float(r.depth_scale_better), prompt_box=prompt_box)
