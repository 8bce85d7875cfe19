"""The use cases: estimate step K of an assembly in one frame, or in several views of one placement,
with the base object's mask from a named source.

Every caller comes through here: the Python API (`api.estimate_pose`), `apose estimate` and `apose eval`,
BOP scoring and the studio. `registration/` is the method; this module turns "this frame, this step,
this mask source, these settings" into the method's inputs (a `View`, the prepared base, the part).

Mask sources (`MASK_SOURCES`, a name -> function of the frame): `gt` the renderer's or the scene's own
masks, `depth` depth alone (the object nearest the image centre), `box` a box prompt drawn around the
ground truth's visible mask (what a user or detector would give). Besides those, `find_mask` takes a
model from `apose train-seg` (a .pt path), a mask image file, or a box / point prompt.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from apose_studio.assembly.mesh import PartModel, base_body_mesh, base_mesh, load_parts
from apose_studio.assembly.model import Assembly, load_assembly
from apose_studio.assembly.roi import Roi
from apose_studio.data.dataset import Frame, read_image
from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics, mask_bounds
from apose_studio.geometry.raycast import own_edges, raycast_depth, silhouette_outline
from apose_studio.geometry.sensor import SHIFT_MIN_PX, depth_colour_shift, outline_shift_ratios, shift_image, shift_looks
from apose_studio.masks.prompt import PromptError, box_depth, prompted_mask
from apose_studio.masks.segment import depth_mask, load_model, table_objects
from apose_studio.registration import BaseObject, Params, RegistrationResult, doubts, estimate, failed, prepare_base
from apose_studio.registration.base import PLAIN_SHARE, Region, plainness, raycast_source
from apose_studio.registration.calibration import scale_checked
from apose_studio.registration.fusion import estimate_views
from apose_studio.registration.next_view import next_view
from apose_studio.registration.table import table_plane
from apose_studio.registration.track import (
    HIDDEN_TOLERANCES,
    TABLE_TOLERANCES,
    final_distance,
    hidden_points,
    predict,
    table_now,
    track,
)
from apose_studio.registration.types import CONFIDENT_PART_SPREAD, View

BOX_MARGIN = 0.04  # the `box` source: the ground truth's visible box, this much wider on each side


class StepContext:
    """What a step's frames share: its base object (prepared once) and the part to place."""

    def __init__(self, asm: Assembly, models: dict[str, PartModel], step: int):
        self.view = asm.step_view(step)
        self.base: BaseObject = prepare_base(base_mesh(models, self.view), region=base_region(models, self.view))
        self.part = models[self.view.part]


def base_region(models: dict[str, PartModel], view) -> Region | None:
    """The extent of a step's base where a member is a region of a larger part (`roi`): each member's roi, or a
    whole member's box; None when every member is whole."""
    members = view.T_base_members
    if all(models[pid].roi is None for pid in members):
        return None
    boxes = []
    for pid, T_base_member in members.items():
        m = models[pid]
        lo, hi = m.aabb
        roi = m.roi if m.roi is not None else Roi("box", tuple((lo + hi) / 2), size=tuple(hi - lo))
        boxes.append((roi, se3.inv(T_base_member)))
    regions = [models[pid].region for pid in members if models[pid].region is not None]
    return Region(tuple(boxes), body=base_body_mesh(models, view), twins=region_twins(models, view),
                  plain=len(members) == 1 and plainness(regions[0]) < PLAIN_SHARE)


def same_mesh(a, b) -> bool:
    """Whether two meshes are one shape (one object, or the same faces and vertices: a rendered dataset keeps a copy
    of the mesh file per part)."""
    return a is b or (a.vertices.shape == b.vertices.shape and np.array_equal(a.faces, b.faces)
                      and np.allclose(a.vertices, b.vertices, atol=1e-9))


TWIN_MATCH = 0.03  # region_twins: a region moved onto another place of its part is alike there when its surface lies
# within this share of its diameter of the part's (mean distance, after a shift-only fit)
TWIN_FIT_ROUNDS = 12
TWIN_SAMPLES = 200_000  # the part's surface sampled ~1 mm apart on an engine head: the mean distance of a region lying on it ~0.5 mm


def region_twins(models: dict[str, PartModel], view) -> tuple:
    """((name, S), ...) for a base that is one region (`roi`) of a part: the places of the same part where the region
    appears again (rocker-arm seats in a row on an engine head), each named by the other region (an roi of the same
    mesh, of any shape or size) that marks it, S the shift (T_base_base) that lays this region there. Each other
    roi's centre gives a first shift, which a shift-only fit of the region onto the part's surface settles; the place
    is a twin where the region then lies on the surface (TWIN_MATCH). Look-alikes that no roi marks, and turned ones,
    are not looked for."""
    if len(view.T_base_members) != 1:
        return ()
    (pid,) = view.T_base_members
    mine = models[pid]
    if mine.roi is None:
        return ()
    from apose_studio.assembly.mesh import sample_surface
    from apose_studio.geometry.nn import NearestTree

    region = np.asarray(mine.region.vertices)[:: max(1, len(mine.region.vertices) // 2000)]
    size = float(np.linalg.norm(mine.region.extents))
    surface, samples = None, None
    out = []
    for other, m in models.items():
        if other == pid or m.roi is None or not same_mesh(m.mesh, mine.mesh):
            continue
        if surface is None:
            samples = sample_surface(mine.mesh, TWIN_SAMPLES, 0)
            surface = NearestTree(samples)
        shift = np.subtract(m.roi.center, mine.roi.center)
        for _ in range(TWIN_FIT_ROUNDS):  # a shift-only ICP of the region onto the part's surface
            d, i = surface.query(region + shift)
            shift = shift + np.mean(samples[i] - (region + shift), axis=0)
        d, _ = surface.query(region + shift)
        if float(np.mean(d)) < TWIN_MATCH * size and np.linalg.norm(shift) > 0.25 * size:
            S = np.eye(4)
            S[:3, 3] = shift
            out.append((other, S))
    return tuple(out)


_CONTEXTS: dict = {}


def step_context(assembly: Assembly | str | Path, step: int) -> tuple[Assembly, StepContext]:
    """(Assembly, StepContext) for an assembly (path or Assembly) and a 1-based step, cached per file."""
    asm = assembly if isinstance(assembly, Assembly) else load_assembly(assembly)
    if not 1 <= step <= len(asm.steps):
        raise AposeError(f"{asm.path}: step {step} does not exist; the assembly has steps 1..{len(asm.steps)}"
                         if asm.steps else f"{asm.path}: the assembly has no steps")
    key = (str(asm.path), Path(asm.path).stat().st_mtime if Path(str(asm.path)).exists() else id(asm), step)
    if key not in _CONTEXTS:
        if len(_CONTEXTS) > 8:
            _CONTEXTS.clear()
        _CONTEXTS[key] = StepContext(asm, load_parts(asm), step)
    return asm, _CONTEXTS[key]


# ---- mask sources -------------------------------------------------------------------------------------

def truth_box(mask: np.ndarray, margin: float = BOX_MARGIN) -> tuple[int, int, int, int] | None:
    """The box a user or detector would draw: the visible mask's box, `margin` of its size wider per side."""
    bounds = mask_bounds(mask)
    if bounds is None:
        return None
    y0, y1, x0, x1 = bounds
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    h, w = mask.shape
    return max(int(x0 - mx), 0), max(int(y0 - my), 0), min(int(x1 + mx), w), min(int(y1 + my), h)


def _truth_box_prompt(frame: Frame) -> np.ndarray:
    """The `box` mask source: the prompted mask of the box round the truth's visible mask (truth_box). Where the prompt
    refuses that box (a base at the image's border showing a few pixels, or nothing in the box standing out of the
    table) the mask is empty: the frame's estimate then fails with its reason, and an `apose eval --mask box` run goes
    on to the next frame, as it does where the base is not in view at all."""
    truth = frame.base_mask()
    box = truth_box(truth)
    if box is None:
        return truth
    try:
        return prompted_mask(frame.rgb, frame.depth, frame.camera, box=box).mask
    except PromptError:
        return np.zeros_like(truth)


MASK_SOURCES: dict[str, Callable[[Frame], np.ndarray]] = {
    "gt": lambda frame: frame.base_mask(),
    "depth": lambda frame: depth_mask(frame.depth, frame.camera),
    "box": _truth_box_prompt,
}
TRUTH_MASK_SOURCES = ("gt", "box")  # the sources that read the frame's ground-truth masks (a capture has none)
IMAGE_SUFFIXES = (".png", ".jpg", ".bmp", ".tif", ".tiff")


def mask_sources_for(frame_masks: bool) -> tuple[str, ...]:
    """The MASK_SOURCES names that work on frames with (or without) ground-truth masks."""
    return tuple(s for s in MASK_SOURCES if frame_masks or s not in TRUTH_MASK_SOURCES)

_SEGMENTERS: dict = {}


def _is_model(source: str) -> bool:
    return source.endswith(".pt") or Path(source).exists()


def _segmenter(path: str, asm: Assembly | None = None):
    key = (path, Path(path).stat().st_mtime if Path(path).exists() else 0)
    if key not in _SEGMENTERS:
        _SEGMENTERS[key] = load_model(path, asm)
    elif asm is not None and list(asm.parts) != _SEGMENTERS[key].part_ids:
        load_model(path, asm)  # raises with the explanation
    return _SEGMENTERS[key]


def check_mask_source(source: str, asm: Assembly) -> str:
    """A name of MASK_SOURCES, or a model file trained for this assembly (loaded once here, so a wrong
    one is refused before any work; returned as its absolute path). Raises AposeError naming the fix."""
    if source in MASK_SOURCES:
        return source
    if _is_model(source):
        _segmenter(str(Path(source).resolve()), asm)
        return str(Path(source).resolve())
    raise AposeError(f"--mask {source}: expected {', '.join(MASK_SOURCES)}, or a model file (.pt) from `apose train-seg`")


def frame_mask(frame: Frame, source: str) -> np.ndarray:
    """The base object's mask in a frame from a source that check_mask_source accepted."""
    if source in MASK_SOURCES:
        return MASK_SOURCES[source](frame)
    if _is_model(source):
        return _segmenter(str(Path(source).resolve())).mask(frame.rgb, frame.depth, frame.base, frame.camera)
    raise ValueError(f"unknown mask source {source!r}; available: {', '.join(MASK_SOURCES)} or a .pt model")


def check_mask(mask: np.ndarray, shape: tuple[int, int], what: str = "mask") -> np.ndarray:
    """A caller's mask as (H, W) bool of the depth's size; AposeError naming both sizes otherwise."""
    mask = np.asarray(mask)
    if mask.ndim == 3:
        mask = mask[..., 0]
    if mask.shape != shape:
        raise AposeError(f"{what} is {mask.shape[1] if mask.ndim > 1 else '?'}x{mask.shape[0]} but the depth is "
                         f"{shape[1]}x{shape[0]}; give a mask of the same size as the image")
    return mask > 0


def check_colour(rgb, shape: tuple[int, int], what: str = "rgb") -> np.ndarray:
    """A caller's colour image as (H, W, 3) uint8 of the depth's size: RGBA loses its alpha, a grey (H, W) image is
    taken as each channel, whole numbers in 0-255 of any integer type (a nested list) as they are. AposeError naming
    what it got and the fix otherwise (a float image in 0-1, 16-bit colour, NaN, a mask: OpenCV failed deep inside
    the mask with a message about its own internals)."""
    got = rgb
    rgb = np.asarray(rgb)
    if rgb.ndim < 2 or rgb.ndim > 3:
        raise AposeError(f"{what} must be an (H, W, 3) colour image (uint8), got "
                         f"{'None' if got is None else f'an array of shape {rgb.shape}'}")
    if rgb.shape[:2] != tuple(shape):
        raise AposeError(f"{what} is {rgb.shape[1]}x{rgb.shape[0]} but the depth is {shape[1]}x{shape[0]}; align depth "
                         "to colour first")
    if rgb.dtype != np.uint8:
        if rgb.dtype.kind not in "iuf" or rgb.size == 0:
            raise AposeError(f"{what} must be 8-bit colour (uint8, 0-255), got {rgb.dtype}")
        if rgb.dtype.kind == "f" and not np.isfinite(rgb).all():
            raise AposeError(f"{what} holds NaN or inf; give 8-bit colour (uint8, 0-255)")
        lo, hi = float(rgb.min()), float(rgb.max())
        if rgb.dtype.kind in "iu" and lo >= 0 and hi <= 255:
            rgb = rgb.astype(np.uint8)  # the same numbers: nothing to guess
        else:
            fix = "rgb.astype(np.uint8)"
            if rgb.dtype.kind == "f" and hi <= 1.0:
                fix = "(rgb * 255).round().astype(np.uint8)"
            elif hi > 255:
                fix = "(rgb >> 8).astype(np.uint8)" if rgb.dtype.kind in "iu" and hi <= 65535 else "rgb scaled to 0-255"
            raise AposeError(f"{what} must be 8-bit colour (uint8, 0-255), got {rgb.dtype} with values {lo:.3g} to "
                             f"{hi:.3g}; give {fix}")
    if rgb.ndim == 2:
        return np.repeat(rgb[..., None], 3, axis=2)
    if rgb.shape[2] == 4:
        return np.ascontiguousarray(rgb[..., :3])
    if rgb.shape[2] != 3:
        raise AposeError(f"{what} must be an (H, W, 3) colour image, got shape {rgb.shape}")
    return rgb


POINT_WINDOW_PX = 80  # a point prompt's depth and colour are compared this far around it each way


def colour_registered(rgb, depth: np.ndarray, box=None, point=None) -> tuple[np.ndarray, tuple[int, int]]:
    """(depth, (du, dv)): the depth moved back onto the colour image when, around the prompt (its box, or
    POINT_WINDOW_PX round its point), it lies clearly shifted against it (geometry.sensor.depth_colour_shift:
    (du, dv) is how far it lay right and down); the depth as it is, and (0, 0), otherwise or without a prompt.

    A prompt is drawn on the colour image, and a Kinect's depth registered a few pixels off moves the cloud
    under the mask sideways with it (benchmarks/captures.py, `real`: depth 3 px off, every right pose 4-7 mm
    off). Asked for (`apose estimate --align-depth`, estimate_pose(align_depth=True)), not by default: on
    frames registered exactly, a Kinect's edge bleeding and projector shadows made it find a shift now and
    then (docs/CAPTURES_AND_BOP.md). Without a prompt nothing says where to compare: the whole image's edges
    found wrong shifts."""
    if rgb is None or (box is None and point is None):
        return depth, (0, 0)
    if box is None:
        u, v = point
        box = (u - POINT_WINDOW_PX, v - POINT_WINDOW_PX, u + POINT_WINDOW_PX + 1, v + POINT_WINDOW_PX + 1)
    du, dv = depth_colour_shift(np.asarray(rgb), depth, box)
    return (shift_image(depth, -du, -dv), (du, dv)) if (du, dv) != (0, 0) else (depth, (0, 0))


def array_mask(rgb, depth, cam: CameraIntrinsics, mask=None, box=None, point=None,
               region: bool = False) -> tuple[np.ndarray, str]:
    """The base's mask for frames held in arrays, and where it came from: the caller's `mask`, else a
    box / point prompt (`region`: the step's base is a region of a larger part, masks.prompt.prompted_mask),
    else depth alone."""
    if mask is not None:
        return check_mask(mask, depth.shape), "given"
    if box is not None or point is not None:
        return (prompted_mask(rgb, depth, cam, box=box, point=point, region=region).mask,
                "box" if box is not None else "point")
    return depth_mask(depth, cam), "depth"


@dataclass(frozen=True)
class MaskRequest:
    """How a command-line user asked for the mask: `source` (a MASK_SOURCES name, a .pt model or a mask
    image; None: the ground truth where the frame has one, else depth), or a box / point prompt."""

    source: str | None = None
    box: tuple[int, int, int, int] | None = None
    point: tuple[int, int] | None = None

    def __post_init__(self):
        if self.box is not None and self.point is not None:  # (the box alone was used, the point dropped unsaid)
            raise AposeError("--box and --point: give one prompt, a box round the base or a point on it")


def find_mask(frame: Frame, request: MaskRequest, asm: Assembly, name: str = "",
              region: bool = False) -> tuple[np.ndarray, str]:
    """The base's mask in `frame` as `request` asks, and its source's name. `name` says in errors which
    input the frame came from; `region`: the step's base is a region of a larger part (array_mask)."""
    if request.box is not None or request.point is not None:
        if request.source not in (None, "depth"):
            raise AposeError(f"--mask {request.source} and --box/--point: give one way to find the object")
        return array_mask(frame.rgb, frame.depth, frame.camera, box=request.box, point=request.point, region=region)
    source = request.source or ("gt" if frame.masks else "depth")
    if source.lower().endswith(IMAGE_SUFFIXES):
        return check_mask(read_image(Path(source), cv2.IMREAD_GRAYSCALE, "the mask image"), frame.depth.shape, source), source
    if source in TRUTH_MASK_SOURCES and not frame.masks:
        raise AposeError(f"{name or 'this frame'}: no ground-truth masks here (--mask {source} reads them); use "
                         "--box x0,y0,x1,y1, --point u,v, --mask depth or --mask MASK.png")
    return frame_mask(frame, check_mask_source(source, asm)), source


# ---- estimates ----------------------------------------------------------------------------------------

def estimate_view(view: View, ctx: StepContext, params: Params, orientation_prior: bool = False,
                  trace_iterations: bool = False) -> RegistrationResult:
    """Step `ctx`'s assembly pose in one view (`estimate_colour_checked`), a confident one checked for a depth
    whose scale is off (calibration.scale_checked, `params.scale_check`)."""
    result = estimate_colour_checked(view, ctx, params, orientation_prior, trace_iterations)
    if not result.confident:
        return result
    seen = region_target(view, ctx.base)
    if result.depth_moved_px != (0, 0):  # the result is the estimate on the depth moved back onto the colour image
        du, dv = result.depth_moved_px
        seen = replace(seen, depth=shift_image(seen.depth, -du, -dv))
    return scale_checked(result, seen, ctx.base, params)


def estimate_colour_checked(view: View, ctx: StepContext, params: Params, orientation_prior: bool = False,
                            trace_iterations: bool = False) -> RegistrationResult:
    """Step `ctx`'s assembly pose in one view. With orientation_prior the CAD's orientation is taken as
    the base's orientation in the world (what `--base-pose fixed` renders, and the paper assumes). With
    `params.colour_check`, a clear shift of the depth against the colour image costs confidence
    (colour_checked); with `params.move_depth_to_colour` too, the depth is then moved back by that shift and the
    estimate made again, and that estimate is the result (its `depth_moved_px` says how far) when the check finds
    no shift left after it; where the edges suggest a shift before any pose and a box prompted the mask (looks_ahead),
    the depth moved back by it is estimated first, and kept when the check at that pose confirms the shift. A base that is a region of a larger part, prompted by a box, is registered to the box's
    pixels with depth near its centre (region_target)."""
    ctx.base.warm_up(params)
    if ctx.base.region is not None and view.box is None:
        return failed(f"{ctx.view.base[0]} is a region of a larger part (its roi): its target is what a box drawn round "
                      "it holds; give one (--box, or a box prompt), not a mask of the whole part or a click",
                      preset=params.preset)
    view = region_target(view, ctx.base)
    looked = time.perf_counter()
    first_look = edges_suggest_shift(view) if params.colour_check else EdgeLook()
    suggested = first_look.confirmed  # ((du, dv), ratio) of a clear shift the edges suggest, or None
    looked = time.perf_counter() - looked

    def checked(v: View, p: Params = params, look=NOT_LOOKED) -> tuple[RegistrationResult, RegistrationResult]:
        """(the registration's result, that result held to the part and colour-checked)."""
        raw = estimate(v, ctx.base, ctx.view.T_base_part, p, prior_T_world_base=np.eye(4) if orientation_prior else None,
                       trace_iterations=trace_iterations, part_symmetries=ctx.part.symmetries)
        return raw, held_to_part(colour_checked(raw, v, p, ctx.base.mesh, look), ctx.part)

    on_moved: dict[tuple[int, int], RegistrationResult] = {}  # per shift

    def settled(du: int, dv: int) -> RegistrationResult | None:
        """The estimate (held to the part, colour-checked) on the depth moved back by (du, dv), made once per shift,
        when its own check finds no shift left; None otherwise."""
        key = (int(du), int(dv))
        if key not in on_moved:
            on_moved[key] = checked(replace(view, depth=shift_image(view.depth, -du, -dv)))[1]
        again = on_moved[key]
        return again if again.ok and not shifted(again) else None

    def moved_back(first: RegistrationResult, before: float) -> RegistrationResult | None:
        """settled on the shift `first`'s check found. `before`: the seconds spent before it (the first estimate's)."""
        du, dv = first.colour_offset_px
        again = settled(du, dv)
        return None if again is None else replace(again, depth_moved_px=(int(du), int(dv)),
                                                  timings={**again.timings, "estimate on the depth as it lay": before})

    def moved_ahead(shift: tuple[int, int], before: float) -> RegistrationResult | None:
        """settled on the shift the edges suggest before any pose (`first_look`), when the check at its pose on the
        depth as it lay finds that shift, to within a pixel (the base's own edges left out where it is: the colour
        image's); None otherwise. What the estimate on the depth as it lay would have told (moved_back), without
        making it: a Kinect-like frame's depth lies a few pixels off on every frame. `before`: the seconds spent
        before it (the first look's)."""
        du, dv = shift
        again = settled(du, dv)
        if again is None:
            return None
        t = time.perf_counter()
        told = colour_checked(again, view, params, ctx.base.mesh, first_look)
        if not (shifted(told) and max(abs(told.colour_offset_px[0] - du), abs(told.colour_offset_px[1] - dv)) <= 1):
            return None  # the check's own resolution is a pixel (at the pose on the depth as it lay it finds the same)
        return replace(again, depth_moved_px=(int(du), int(dv)),
                       timings={**again.timings, "colour check": again.timings.get("colour check", 0.0) + before
                                + time.perf_counter() - t})

    def with_look(r: RegistrationResult, spent: float = 0.0) -> RegistrationResult:  # the first look's time counted
        if not params.colour_check:
            return r
        extra = {"colour check": r.timings.get("colour check", 0.0) + looked, **({"quick estimate": spent} if spent else {})}
        return replace(r, timings={**r.timings, **extra})

    def counted(r: RegistrationResult) -> RegistrationResult:
        """`r` with the look-ahead's estimate (moved_ahead) counted where it was made and `r` is not it: time spent on
        a shift that `r` did not keep. (`r` on that same shift is that very estimate, its time in its own timings.)"""
        if not ahead_spent or r.depth_moved_px == ahead_shift:
            return r
        return replace(r, timings={**r.timings, "estimate on the depth moved back": ahead_spent})

    moving = params.colour_check and params.move_depth_to_colour
    tried, spent, ahead_spent, ahead_shift = None, 0.0, 0.0, None
    if moving and suggested is not None and looks_ahead(view):  # the edges suggest a shift: estimate on the depth
        # moved back by it first
        t_ahead = time.perf_counter()
        ahead = moved_ahead(suggested[0], looked)
        if ahead is not None:
            return ahead
        ahead_spent, ahead_shift = time.perf_counter() - t_ahead, (int(suggested[0][0]), int(suggested[0][1]))
    if moving and suggested is not None and params.mask_hypotheses:  # the edges suggest a shift: the estimate on
        # the mask as given tells whether the shift holds at the pose. Not its other readings, second look or free
        # search, the costly parts: none runs on a result that fits, and one that does not is estimated again
        # (benchmarks/captures.py, 528 frames: every outcome the same, the `real` row's first estimates 12.4 -> 6.4 s)
        quick_params = replace(params, mask_hypotheses=False, second_look=False, free_after_upright=False)
        raw, quick = checked(view, quick_params, first_look)
        if quick.ok and shifted(quick):
            moved = moved_back(quick, quick.seconds + looked)
            if moved is not None:
                return counted(moved)
            tried = quick.colour_offset_px
        elif raw.fits:  # the other readings run only on a result that does not fit: this is the whole estimate
            return counted(with_look(quick))
        spent = quick.seconds
    result = with_look(checked(view, params, first_look)[1], spent)
    if moving and result.ok and shifted(result) and result.colour_offset_px != tried:
        return counted(moved_back(result, result.seconds) or result)
    return counted(result)


def region_target(view: View, base: BaseObject) -> View:
    """The view whose mask is the prompt box's pixels with depth (masks.prompt.box_depth), where the base is a
    region of a larger part (`roi`) and a box prompted it, whatever mask the caller made; `view` as it is
    otherwise. What of the box lies outside the region does not count for or against the pose
    (BaseObject.belongs). Measured on engine-head renders: the prompted mask's colour cut had kept a few stray
    pixels of a seat (1 of 7 frames), and its table fit took the head's deck for the table (refused boxes)."""
    if base.region is None or view.box is None:
        return view
    try:
        mask = box_depth(view.depth, view.box)
    except AposeError:  # a box off the image: the mask as given is judged (and refused) as usual
        return view
    return replace(view, mask=near_box_centre(mask, view.depth, view.camera, view.box, REGION_REACH * base.diameter))


REGION_REACH = 0.75  # region_target: the box's pixels whose points lie farther than this share of the region's diameter
# from the point seen at the box's centre are the larger part's (an engine head's side walls, the table beyond it)


def near_box_centre(mask: np.ndarray, depth: np.ndarray, cam, box, reach: float) -> np.ndarray:
    """`mask` without the pixels whose points lie farther than `reach` (metres) from the point seen at the box's
    centre (of the middle third's pixels in the mask, the one at their median depth): a box drawn round a region is
    centred on it, while the larger part runs on to its corners. `mask` as it is when its middle has no depth."""
    x0, y0, x1, y1 = (int(v) for v in box)
    cx0, cx1, cy0, cy1 = x0 + (x1 - x0) // 3, x1 - (x1 - x0) // 3, y0 + (y1 - y0) // 3, y1 - (y1 - y0) // 3
    vs, us = np.nonzero(mask[cy0:cy1, cx0:cx1])
    if not len(vs):
        return mask
    z = depth[vs + cy0, us + cx0]
    k = int(np.argmin(np.abs(z - np.median(z))))  # a pixel seen there: the centre is a point of the target
    centre = cam.backproject(us[k] + cx0, vs[k] + cy0, float(z[k]))
    vs, us = np.nonzero(mask)
    far = np.linalg.norm(cam.backproject(us, vs, depth[vs, us]) - centre, axis=1) > reach
    out = mask.copy()
    out[vs[far], us[far]] = False
    return out


def looks_ahead(view: View) -> bool:
    """Whether estimate_colour_checked, where the edges suggest a shift before any pose, estimates first on the depth
    moved back by it (and not first on the depth as it lay): where a box prompted the mask. On benchmarks/captures.py's
    `real` row (its depth 3 px off) that is one estimate a frame instead of two, the median frame 0.906 -> 0.533 s,
    every frame as right and as confident as before. The edges suggest a shift falsely (the base's own creases: the check at the pose does
    not confirm it, and the estimate is wasted) on 6 of the 504 box-prompted renders registered exactly there, but on
    30 of the 280 frames of benchmarks/tune.py, whose ground-truth masks' own box is the window (its fixed protocol's
    p95 went 64 -> 214 ms): a mask without a box goes as before."""
    return view.box is not None


CLEAR_SHIFT_MAX_PX = 4  # colour_checked: a shift of the depth against the colour held against the confidence is at
# most this long (a Kinect's registration is a few pixels off; the 5-6 px the search also tries were found only on
# frames registered exactly, where shading along an outline fooled the edges) ...
CLEAR_SHIFT_GAIN = 0.75  # ... and lays the depth's edges at most this share of their unshifted distance from the
# colour's (the base's own creases and inner outlines left out). With the renderer's poses (a scratch script over
# benchmarks/captures.py's and tune.py's renders): the `real` row's shifts (3 px) 0.35-0.80, 22 of its 24 frames
# below; none of the 720 frames registered exactly below at <= 4 px (with the own edges in: 36)


OUTLINE_BLEED = 0.95  # colour_checked: where the edges read as a shift alone but not beside a bleed, the model's
# outline at the pose moved back by that shift (to within a pixel) lying no nearer the colour's edges than this share of
# its distance as it is says the pose lies on the colour's outline: the depth bleeds, and no shift is held against it


def shifted(result: RegistrationResult) -> bool:
    """colour_checked found the depth's edges clearly off the colour's by a shift, a bleed of the outlines beside it
    (colour_offset_bleed: a bleed explains them as well, so the depth is not moved by it, only held against the
    confidence)."""
    return result.colour_offset > 0 and not result.colour_offset_bleed


def clear_shift(du: int, dv: int, ratio: float) -> bool:
    """A shift of the depth against the colour image clear enough to count (CLEAR_SHIFT_MAX_PX, CLEAR_SHIFT_GAIN)."""
    return SHIFT_MIN_PX <= max(abs(du), abs(dv)) <= CLEAR_SHIFT_MAX_PX and ratio < CLEAR_SHIFT_GAIN


def check_window(view: View) -> tuple[int, int, int, int] | None:
    """Where the depth's edges are compared with the colour's: the prompt's box, or the mask's."""
    return view.box if view.box is not None else truth_box(view.mask, 0.0)


def edges_suggest_shift(view: View) -> EdgeLook:
    """The depth's edges against all the colour image's in the prompt's box (or the mask's), before any pose
    (edge_look; its `confirmed` is the clear shift they suggest). Leaving an object's own edges out
    (colour_checked) only takes evidence away: over the 744 renders of benchmarks/captures.py and tune.py (a
    scratch script, the renderer's poses), no clear shift was found with them left out where none was found with
    them in; so a frame where this finds none is done (1.9 ms, against 3.5 ms more for the object's own edges, on a
    gearbox frame of tune.py)."""
    window = check_window(view)
    if view.rgb is None or window is None:
        return EdgeLook()
    return edge_look(np.asarray(view.rgb), view.depth, window, None)


@dataclass(frozen=True)
class EdgeLook:
    """What the edges say of a shift of the depth against the colour image, each ((du, dv), ratio) or None: `alone`,
    the clear shift they show compared as a shift alone; `confirmed`, that shift as the comparison allowing a bleed
    confirms it (edge_look)."""

    alone: tuple[tuple[int, int], float] | None = None
    confirmed: tuple[tuple[int, int], float] | None = None


def edge_look(rgb: np.ndarray, depth: np.ndarray, window, explained) -> EdgeLook:
    """The edges of `depth` against `rgb`'s in `window`, `explained` colour edges left out (geometry.sensor.
    shift_looks, gated by clear_shift: CLEAR_SHIFT_MAX_PX, CLEAR_SHIFT_GAIN). The edges compared as a shift alone must
    find a shift; the comparison that allows the depth's outlines to bleed past the colour's
    (geometry.sensor.shift_and_bleed) must find it too, to within a pixel each way, to confirm it, and its shift is
    the one confirmed (it is exact where the alone's is a pixel off toward the bleed). A bleed never suggests a shift
    the edges alone do not: joined with a shift it can explain edges that neither explains alone (on a
    RealSense-like gearbox frame registered exactly, a "shift" of (3, -4) that moved the depth and the pose 3.0 mm)."""
    return EdgeLook(*shift_looks(rgb, depth, window, explained, clear_shift))


NOT_LOOKED = object()  # colour_checked's `look` when edges_suggest_shift has not looked at the view yet


def colour_checked(result: RegistrationResult, view: View, params: Params, mesh,
                   look=NOT_LOOKED) -> RegistrationResult:
    """`result` with what a depth lying off the colour image may cost it. The intrinsics are the colour
    camera's and the prompt is drawn on the colour image; where the depth lies a few pixels off it (a
    Kinect's registration), the pose fitted to the depth lies off the base by as much (a pixel at depth z is
    z / f metres), and nothing in the depth shows it. So the depth's edges are compared with the colour's in
    the prompt's box (or the mask's; geometry.sensor.shift_evidence), and a clear shift found there
    (CLEAR_SHIFT_MAX_PX, CLEAR_SHIFT_GAIN: stricter than --align-depth's gate) is held against the confidence
    as `colour_offset`: with the spread it must stay within the placement's allowance (half the line a right
    pose keeps to; the other half is left for what no frame shows, such as a constant depth bias).

    The colour edges the base shows at its pose by its own shape (`mesh`, the base's: its creases and inner
    outlines, geometry.raycast.own_edges) are left out of the comparison. Shading runs along them in any image:
    a casing's top face ends a wall's thickness inside its outline, a box's top face a side's height above its
    lower outline, and with them in, the edges found a clear shift on 36 of 720 renders registered exactly (the
    gearbox casing's rims most of all); without them, none (see CLEAR_SHIFT_GAIN; docs/BENCHMARKS.md).

    The pose is not moved here (estimate_view moves the depth and estimates again, `move_depth_to_colour`).
    On by default (`params.colour_check`); only with a colour image and an ok result. `look`: what
    edges_suggest_shift found on this view (an EdgeLook), when already looked (NOT_LOOKED: looked here)."""
    if not (params.colour_check and result.ok and view.rgb is not None):
        return result
    t0 = time.perf_counter()
    if look is NOT_LOOKED:
        look = edges_suggest_shift(view)
    if look.alone is None:  # nothing suggests a shift, read with a bleed or without (the bleed's is looked for only
        # where the alone's is found); leaving edges out only takes evidence away
        return replace(result, timings={**result.timings, "colour check": time.perf_counter() - t0})
    explained = own_edges(mesh, result.T_world_base, view.T_world_camera, view.camera)
    rgb = np.asarray(view.rgb)
    seen = edge_look(rgb, view.depth, check_window(view), explained)
    alone, both = seen.alone, seen.confirmed
    ambiguous = False
    if alone is not None and both is None:  # a shift alone explains the edges, a bleed beside one does not need
        # it: the outlines lie off the colour's as a bleed or as that shift puts them. The model's own outline at
        # the pose tells which: a pose fitted to depth lying off lies as far off the colour's edges; one fitted to
        # depth that only bleeds lies on them
        du, dv = alone[0]
        outline = silhouette_outline(mesh, result.T_world_base, view.T_world_camera, view.camera)
        near = [(du + a, dv + b) for a in (-1, 0, 1) for b in (-1, 0, 1) if (du + a, dv + b) != (0, 0)]
        told = min(outline_shift_ratios(rgb, outline, near, explained))  # to within a pixel, as the edges find a shift
        if told >= OUTLINE_BLEED:  # the pose's outline lies on the colour's as it is: a bleed, no shift
            alone = None
        ambiguous = not told < CLEAR_SHIFT_GAIN  # moved back it lies clearly nearer: the shift is real
    found = both or alone
    if found is not None:
        (du, dv), ratio = found
        region = result.model_mask if result.model_mask is not None and result.model_mask.shape == view.depth.shape \
            else view.mask
        z = view.depth[region & np.isfinite(view.depth) & (view.depth > 0)]
        zc = float(np.median(z)) if len(z) else float(se3.transform_points(se3.inv(view.T_world_camera),
                                                                            result.T_world_base[None, :3, 3])[0, 2])
        result = replace(result, colour_offset=float(np.hypot(du * zc / view.camera.fx, dv * zc / view.camera.fy)),
                         colour_offset_px=(int(du), int(dv)), colour_offset_bleed=ambiguous)
    return replace(result, timings={**result.timings, "colour check": time.perf_counter() - t0})


def held_to_part(result: RegistrationResult, part: PartModel) -> RegistrationResult:
    """`result` judged also against the part it places: the pose answers where the part goes, and a part
    is placed right within 10 % of its own diameter, which for a label on a duck is less than the base's
    own allowance (6 % of the base's diameter). A result stays confident only when the data pins the pose
    to within CONFIDENT_PART_SPREAD of the part's diameter too (its `spread_allowed` is the smaller of
    the two)."""
    if not result.ok:
        return result
    return replace(result, spread_allowed=min(result.spread_allowed, CONFIDENT_PART_SPREAD * part.diameter))


def estimate_frame(frame: Frame, ctx: StepContext, params: Params, mask_source: str = "gt",
                   orientation_prior: bool = False, trace_iterations: bool = False,
                   mask: np.ndarray | None = None, box: tuple[int, int, int, int] | None = None) -> RegistrationResult:
    """Step `ctx`'s assembly pose in one frame, its mask from `mask_source` unless `mask` is given (`box`: the
    prompt's box that gave it, View.box). A region's ground-truth sources (`gt`, `box`) give the box round what the
    camera sees of the region (region_truth_box): the frame's truth masks its whole part."""
    if mask is None:
        mask, box = region_truth_prompt(frame, ctx, mask_source) or (frame_mask(frame, mask_source), box)
    return estimate_view(replace(View.of(frame, mask), box=box), ctx, params, orientation_prior, trace_iterations)


def region_truth_prompt(frame: Frame, ctx: StepContext, mask_source: str) -> tuple[np.ndarray, tuple] | None:
    """(mask, box) for a base that is a region, asked for by a ground-truth source (`gt`, `box`) on a frame with
    truth: the box round what the camera sees of the region (region_truth_box) and its pixels with depth, as a box
    prompt gives them. None otherwise (or when the camera sees none of the region, or too little to prompt)."""
    if ctx.base.region is None or mask_source not in TRUTH_MASK_SOURCES or not frame.masks or frame.T_world_base is None:
        return None
    box = region_truth_box(frame, ctx.base)
    mask = box_pixels(frame.depth, box)
    return (mask, box) if mask is not None else None


def box_pixels(depth: np.ndarray, box: tuple[int, int, int, int] | None) -> np.ndarray | None:
    """The pixels with depth in a box the code drew round what the camera sees of a place (masks.prompt.box_depth); None
    where there is no box, or where it is too small or too far off the image to prompt: a place at the image's border
    that shows a few pixels (an engine head's corner seat, 2 x 2 pixels, stopped `--instances all` with a traceback)."""
    if box is None:
        return None
    try:
        return box_depth(depth, box)
    except PromptError:
        return None


def region_truth_box(frame: Frame, base: BaseObject, margin: float = BOX_MARGIN) -> tuple[int, int, int, int] | None:
    """The box a user or detector would draw round a region (the base's roi) in a rendered frame: where the region,
    ray-cast at the true pose, is its part's first surface and the truth's mask of the part holds it, `margin` of its
    size wider per side (truth_box); None when the camera sees none of it."""
    z_body = raycast_depth(base.region.body, frame.T_world_base, frame.T_world_camera, frame.camera)
    return truth_box(region_in_front(base, frame.T_world_base, z_body, frame) & frame.base_mask(), margin)


def region_in_front(base: BaseObject, T_world_base: np.ndarray, z_body: np.ndarray, frame: Frame) -> np.ndarray:
    """(H, W) bool: where the base's region, ray-cast at T_world_base, is the first surface of its part (whose depth,
    ray-cast where the part stands, is `z_body`)."""
    z_region = raycast_depth(base.mesh, T_world_base, frame.T_world_camera, frame.camera)
    return np.isfinite(z_region) & (z_region <= z_body + 1e-4)


_PICK_BASES: dict = {}


def pick_base(part: PartModel) -> BaseObject:
    """The part's own CAD prepared as a base object, to find where the part lies before it is picked (cached)."""
    key = id(part.mesh)
    if key not in _PICK_BASES or _PICK_BASES[key][0] is not part.mesh:
        if len(_PICK_BASES) > 8:
            _PICK_BASES.clear()
        _PICK_BASES[key] = (part.mesh, prepare_base(part.mesh))
    return _PICK_BASES[key][1]


def estimate_pick(view: View, part: PartModel, params: Params) -> RegistrationResult:
    """Where a loose part lies, before it is picked: the same registration with the part's CAD as the base
    (its T_world_base is T_world_part), no orientation prior (a loose part may lie on any side)."""
    base = pick_base(part)
    base.warm_up(params)
    return held_to_part(estimate(view, base, np.eye(4), params, part_symmetries=part.symmetries), part)


def estimate_frames(views: list[View], ctx: StepContext, params: Params,
                    orientation_prior: bool = False) -> RegistrationResult:
    """One fused estimate from several views of one placement (registration.fusion); not of a region of a larger
    part (fusion scores all of each target)."""
    ctx.base.warm_up(params)
    if ctx.base.region is not None:
        return failed(f"{ctx.view.base[0]} is a region of a larger part (its roi): fused views do not take regions yet; "
                      "estimate one view with a box round the region", preset=params.preset)
    return held_to_part(estimate_views(views, ctx.base, ctx.view.T_base_part, params,
                                       np.eye(4) if orientation_prior else None, ctx.part.symmetries), ctx.part)


# ---- instances ------------------------------------------------------------------------------------------

INSTANCE_MIN_SIZE = 0.6  # a group of depth points on the table smaller across (5th to 95th percentile) than this share
# of the base's diameter is not one of its instances (clutter, a fragment); an instance seen whole measures ~1.0-1.4
INSTANCE_SPLIT_SIZE = 1.5  # a group larger than this many diameters may hold more than one instance: after one is
# found in it, what the model does not explain is searched again
INSTANCE_SAME = 0.3  # two poses whose base centres lie closer than this share of the diameter are one instance
MAX_INSTANCES = 32


@dataclass(frozen=True)
class Instance:
    """One instance of a step's base found in a frame: the prompt box it was found from and its estimate."""

    box: tuple[int, int, int, int]
    mask: np.ndarray
    result: RegistrationResult


REGION_PLACE_SLACK = 0.25  # estimate_region_instances: a region found farther than this share of its diameter from
# the place its part's pose puts it is not at that place


class _RegionAt:
    """A step's context for estimating its region at one known place of its part (S: T_base_base from the region's own
    place to that one): the same base, its look-alike places left out (the part's pose, not the region, says which
    place this is), and its part moved by S's inverse, so that the region there has the part where it stands."""

    def __init__(self, ctx: StepContext, name: str, S: np.ndarray):
        self.view, self.part = ctx.view, ctx.part
        cache = ctx.base._features.setdefault("bodies_at", {})
        if name not in cache:  # one mesh per place (its ray-casting structure is kept per mesh)
            cache[name] = ctx.base.region.body.copy().apply_transform(se3.inv(S))
        self.base = replace(ctx.base, region=replace(ctx.base.region, twins=(), body=cache[name]))


def refined_at(frame: Frame, place: "_RegionAt", params: Params, head: RegistrationResult,
               T_world_base: np.ndarray) -> RegistrationResult:
    """The region refined from where its part's pose puts it (T_world_base), as a tracker follows a base from the
    frame before (registration.track: a short ICP on the depth near it, judged like any estimate)."""
    base = place.base
    seen, _ = raycast_source(base, T_world_base, frame.T_world_camera, frame.camera)
    if len(seen) < 50:
        return failed("the region is (almost) out of view at its place")
    start = replace(head, T_world_base=T_world_base, T_world_part=T_world_base @ place.view.T_base_part,
                    source_cloud=se3.transform_points(se3.inv(T_world_base), seen))
    r = track(frame.depth, frame.camera, frame.T_world_camera, base, place.view.T_base_part, params, start)
    return held_to_part(replace(r, tracked=False), place.part)


def body_base(ctx: StepContext) -> BaseObject:
    """The whole part a region belongs to, prepared as a base (kept on the step's base)."""
    cache = ctx.base._features
    if "body_base" not in cache:
        cache["body_base"] = prepare_base(ctx.base.region.body)
    return cache["body_base"]


def estimate_region_instances(frame: Frame, ctx: StepContext, params: Params,
                              orientation_prior: bool = False) -> list[Instance]:
    """Every place of a region on its part in `frame` without a prompt (the eight seats of an engine head for step 1's
    seat): the part found whole first (estimate_instances with its whole mesh as the base, the largest depth groups
    first; the first confident instance, else the best fitting), then the region at its own place and at each
    look-alike (Region.twins), each refined from where the part's pose puts it (refined_at), or searched for in the
    box round what of it is the part's first surface there where that fails. Each keeps its own confidence, but none
    is confident where the part's pose is not, or where the region slid off its place (REGION_PLACE_SLACK); places
    out of view, or showing too few pixels to prompt (box_pixels), are left out. Left to right in the image by the
    region's centre."""
    body = body_base(ctx)
    whole = SimpleNamespace(view=replace(ctx.view, T_base_part=np.eye(4)), base=body, part=ctx.part)
    # the part's pose only starts each region's own refinement (refined_at): no polish of it (a quarter of the time).
    # Its second look is the full one, which compares the pose's twins on the cut: refitting the pose alone there
    # (second_look_from_pose) confirmed a head turned half round onto its near-symmetric twin, confident and 220 mm
    # off by ADD, its seat_8 placed 102 mm from every seat (benchmarks/seats.py --instances, step 8, frame 4)
    head_params = replace(params, polish_voxel_factor=0.0)
    parts = [i.result for i in estimate_instances(frame, whole, head_params, orientation_prior, first_confident=True)
             if i.result.ok]
    if not parts:
        return []
    head = max(parts, key=lambda r: (r.confident, r.fitness))
    region = ctx.base
    z_body = raycast_depth(region.region.body, head.T_world_base, frame.T_world_camera, frame.camera)
    out = []
    for name, S in ((ctx.view.base[0], np.eye(4)), *region.region.twins):
        T = head.T_world_base @ S
        box = truth_box(region_in_front(region, T, z_body, frame), BOX_MARGIN)
        pixels = box_pixels(frame.depth, box)
        if pixels is None:  # out of view, or too little of it to prompt
            continue
        view = replace(View.of(frame, pixels), box=box)
        place = _RegionAt(ctx, name, S)
        r = refined_at(frame, place, params, head, T)  # from where the part's pose puts it: a short ICP
        if not r.ok:  # else searched for in the box
            r = estimate_view(view, place, params, orientation_prior)
        if r.ok and not head.confident:
            r = replace(r, part_doubt=f"the part {name} is a region of is not found with confidence ({doubts(head)})")
        elif r.ok and np.linalg.norm(r.T_world_base[:3, 3] - T[:3, 3]) > REGION_PLACE_SLACK * region.diameter:
            r = replace(r, part_doubt=f"the region slid off {name}'s place on its part")
        out.append((float(np.mean(box[0::2])), Instance(box, view.mask, replace(r, reading=f"at {name}"))))
    return [i for _, i in sorted(out, key=lambda x: x[0])]


def instance_boxes(frame: Frame, diameter: float) -> list[tuple[tuple[int, int, int, int], np.ndarray]]:
    """Prompt boxes (and the depth groups they hold) around what stands on the table and could be one
    instance of a base of `diameter` metres: groups of depth points above the table plane (masks.segment
    .table_objects) at least INSTANCE_MIN_SIZE of the diameter across (`_extent`), largest first."""
    objs = table_objects(frame.depth, frame.camera)
    if objs is None:
        return []
    out = []
    for sel in objs.groups(min_points=60):
        mask = objs.mask(sel)
        if _extent(frame, mask) < INSTANCE_MIN_SIZE * diameter:
            continue
        out.append((truth_box(mask), mask))
    out.sort(key=lambda b: -int(b[1].sum()))
    return out[:MAX_INSTANCES]


def estimate_instances(frame: Frame, ctx: StepContext, params: Params, orientation_prior: bool = False,
                       estimate: Callable | None = None, first_confident: bool = False) -> list[Instance]:
    """Every instance of step `ctx`'s base in `frame` without a prompt per instance: each candidate group of
    depth on the table (`instance_boxes`) estimated with a box prompt around it (a group that may hold
    several, what the found model does not explain searched again), poses of one instance merged (the
    confident one, else the better fitting), the rest in a stable order: left to right in the image by the
    base's centre. Each keeps its own confidence. `estimate(view)`: the estimator per candidate (default
    estimate_view with these params). `first_confident`: stop at the first confident instance (the largest
    groups are tried first). A base that is a region of a larger part (roi): estimate_region_instances."""
    if ctx.base.region is not None:
        return estimate_region_instances(frame, ctx, params, orientation_prior)
    diameter = ctx.base.diameter
    run = estimate or (lambda view: estimate_view(view, ctx, params, orientation_prior))
    todo = [(box, group, True) for box, group in instance_boxes(frame, diameter)]
    found = []
    while todo:
        box, group, split = todo.pop(0)
        try:
            mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box).mask
        except AposeError:  # nothing in the box stands out of the table after all
            continue
        r = run(replace(View.of(frame, mask), box=box))
        found.append(Instance(box, mask, r))
        if first_confident and r.confident:
            break
        if split and r.ok and r.model_mask is not None and _extent(frame, group) > INSTANCE_SPLIT_SIZE * diameter:
            rest = group & ~cv2.dilate(r.model_mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
            if rest.sum() >= 60 and _extent(frame, rest) >= INSTANCE_MIN_SIZE * diameter:  # searched once more
                todo.insert(0, (truth_box(rest), rest, False))
    return distinct_instances(found, ctx.base, frame)


def _extent(frame: Frame, mask: np.ndarray) -> float:
    """How far the mask's depth points reach across (metres): the diagonal of their 5th to 95th percentiles per
    axis (a few flying pixels at a depth edge would stretch the whole range)."""
    vs, us = np.nonzero(mask & (frame.depth > 0))
    if len(vs) < 2:
        return 0.0
    pts = frame.camera.backproject(us.astype(float), vs.astype(float), frame.depth[vs, us].astype(float))
    return float(np.linalg.norm(np.percentile(pts, 95, axis=0) - np.percentile(pts, 5, axis=0)))


def distinct_instances(found: list[Instance], base, frame: Frame) -> list[Instance]:
    """The instances with a pose, one per place (base centres closer than INSTANCE_SAME of the diameter are one:
    the confident one kept, else the higher fitness x coverage), left to right in `frame` by the base's
    centre (then top to bottom)."""
    centre = base.centre

    def where(inst):
        return se3.transform_points(inst.result.T_world_base, centre[None])[0]

    def rank(inst):
        r = inst.result
        return (bool(r.confident), float(r.fitness) * float(np.nan_to_num(r.coverage)))

    kept: list[Instance] = []
    for inst in sorted((i for i in found if i.result.ok), key=rank, reverse=True):
        if all(np.linalg.norm(where(inst) - where(k)) >= INSTANCE_SAME * base.diameter for k in kept):
            kept.append(inst)

    def pixel(inst):
        pc = se3.transform_points(se3.inv(frame.T_world_camera), where(inst)[None])
        u, v = frame.camera.project(pc)
        return float(u[0]), float(v[0])

    return sorted(kept, key=pixel)


# ---- tracking ------------------------------------------------------------------------------------------

TRACK_MODES = ("detected", "tracked", "re-detected", "fused", "lost", "not found")
FUSE_NEAR_DEG = 20.0  # a frame whose camera looks within this angle of the advised camera's direction ...
FUSE_NEAR_SHARE = 0.25  # ... from within this share of its distance to the base is "from there": fused
MAX_GAP = 10  # frames over which the tracker carries the base's motion on (Tracker.expected)


@dataclass(frozen=True)
class TrackStep:
    """One frame of a tracked sequence: its result and how it was found. `mode`: detected (estimated with no
    pose to start from), tracked (from the frame before's pose), re-detected (tracking lost it on this frame,
    a new estimate found it: lost and recovered), fused (an ambiguous frame before and this one, seen from
    near where it advised to look, estimated together: confident), lost (tracking lost it and no confident
    estimate found it), not found (no pose to track and no confident estimate)."""

    im_id: int
    result: RegistrationResult
    mode: str
    seconds: float  # this frame's wall time, everything included
    lost_because: str = ""  # why tracking let go (modes re-detected and lost)
    advice: object = None  # with no confident pose: where to look from to settle an ambiguous one (NextView)


@dataclass
class Tracker:
    """Step `ctx`'s pose through a sequence of frames of one placement (a trajectory, a recording), in order.

    A frame is tracked from the last confident pose (registration.track); with none, or when tracking loses
    the base, it is estimated anew by `detect(frame, box)` (`box`: where the base was last seen, as a prompt
    box, or None). Only a confident result is tracked from: an ambiguous one could be either twin, and
    tracking one would hide the doubt. A tracked result is judged every frame by the estimator's rules, so
    a pose that drifts off the depth is lost, not reported."""

    ctx: StepContext
    params: Params
    detect: Callable[[Frame, tuple[int, int, int, int] | None], RegistrationResult]
    last: RegistrationResult | None = None  # the last confident result
    plane: tuple | None = None  # the table under the base (world), from the detection tracking started from
    steps: list[TrackStep] = field(default_factory=list)
    pending: tuple | None = None  # (view, advice, the base's centre) of an ambiguous frame, waiting for a frame from
    # where its advice (registration.next_view) said to look: the two are then estimated together
    seen: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (im_id, T_world_base) of the last two
    # confident results: the base's motion per frame in the world (none when the camera's pose is known and the
    # base stands still; the camera's own motion when every frame's world is the camera's frame)
    depth_shift: tuple[int, int] = (0, 0)  # how far (right, down) the camera's depth lies off its colour image, as the
    # detection tracking started from found it (RegistrationResult.depth_moved_px): a sensor's registration does
    # not change between frames, so the tracked frames' depth is moved back by as much
    hidden: np.ndarray | None = None  # the last confident result's source points (base frame) that something stood over
    # in its frame (registration.track.hidden_points): the next frame registers none of the depth where they fall

    def step(self, frame: Frame) -> TrackStep:
        t0 = time.perf_counter()
        why, tried = "", self.last is not None
        start = self.expected(frame.im_id) if tried else None
        if tried:
            pred = predict(start, frame.T_world_camera, frame.camera, self.hidden)
            depth = self._depth(frame)
            self.plane = table_now(self.plane, depth, frame.camera, frame.T_world_camera, pred, self.ctx.base,
                                   TABLE_TOLERANCES * final_distance(self.params, self.ctx.base, start))
            r = held_to_part(track(depth, frame.camera, frame.T_world_camera, self.ctx.base,
                                   self.ctx.view.T_base_part, self.params, start, self.plane, pred), self.ctx.part)
            r = replace(r, depth_moved_px=self.depth_shift)
            if r.confident:
                return self._done(TrackStep(frame.im_id, r, "tracked", time.perf_counter() - t0), r, frame)
            why = r.reason if not r.ok else doubts(r)
        box = last_seen_box(start, frame) if tried else None
        r = self.detect(frame, box)
        if r.confident:
            self.plane, self.pending = getattr(r.problem, "table", None), None
            return self._done(TrackStep(frame.im_id, r, "re-detected" if tried else "detected",
                                        time.perf_counter() - t0, why), r, frame)
        self.last, self.hidden = None, None
        self.seen.clear()
        if self.pending is not None and r.ok and r.model_mask is not None and near_view(frame.T_world_camera,
                                                                                        *self.pending[1:]):
            fused = estimate_frames([self.pending[0], View.of(frame, r.model_mask)], self.ctx, self.params)
            if fused.confident:
                self.pending, self.plane = None, getattr(r.problem, "table", None)
                return self._done(TrackStep(frame.im_id, fused, "fused", time.perf_counter() - t0, why), fused, frame)
        if self.pending is None and r.ok and r.ambiguous and r.model_mask is not None:
            advice = next_view(r, self.ctx.base, [frame.T_world_camera], frame.camera)
            if advice is not None:
                centre = se3.transform_points(r.T_world_base, self.ctx.base.centre[None])[0]
                self.pending = (View.of(frame, r.model_mask), advice, centre)
        return self._done(TrackStep(frame.im_id, r, "lost" if tried else "not found", time.perf_counter() - t0, why,
                                    self.pending[1] if self.pending is not None else None))

    def resume(self, result: RegistrationResult, frame: Frame) -> None:
        """Go on from `result`, a confident pose of `frame` (the one on show when a paused player plays again):
        the next frames are tracked from it; the table under the base fitted on `frame`."""
        mask = result.model_mask if result.model_mask is not None else np.zeros(frame.depth.shape, bool)
        self.last, self.pending, self.depth_shift = result, None, result.depth_moved_px
        self.seen = [(frame.im_id, result.T_world_base)]
        self.hidden = self._hidden(result, frame)
        self.plane = table_plane(self._depth(frame), mask, frame.camera, frame.T_world_camera, base_size=self.ctx.base.diameter)

    def _depth(self, frame: Frame) -> np.ndarray:
        """The frame's depth moved back by the shift the detection found (depth_shift)."""
        du, dv = self.depth_shift
        return shift_image(frame.depth, -du, -dv) if (du, dv) != (0, 0) else frame.depth

    def expected(self, im_id: int) -> RegistrationResult:
        """The last confident result, moved on to frame `im_id` at the base's motion per frame between the last
        two (a constant velocity, over gaps of at most MAX_GAP frames; the last pose as it was otherwise)."""
        if len(self.seen) < 2:
            return self.last
        (i0, T0), (i1, T1) = self.seen
        if not (0 < i1 - i0 <= MAX_GAP and 0 < im_id - i1 <= MAX_GAP):
            return self.last
        step = se3.scale_motion(se3.inv(T0) @ T1, (im_id - i1) / (i1 - i0))
        return replace(self.last, T_world_base=T1 @ step)

    def _hidden(self, result: RegistrationResult, frame: Frame) -> np.ndarray:
        """hidden_points of `result` in `frame` (its depth moved back by depth_shift), at the tracker's final
        distance (HIDDEN_TOLERANCES)."""
        tol = HIDDEN_TOLERANCES * final_distance(self.params, self.ctx.base, result)
        return hidden_points(result, self._depth(frame), frame.camera, frame.T_world_camera, tol)

    def _done(self, s: TrackStep, confident: RegistrationResult | None = None, frame: Frame | None = None) -> TrackStep:
        if confident is not None:
            if not confident.tracked:  # an estimate: the depth's shift it found (or none) holds from here on
                self.depth_shift = confident.depth_moved_px
            self.last = confident
            self.seen = [*self.seen[-1:], (s.im_id, confident.T_world_base)]
            t = time.perf_counter()
            self.hidden = None if frame is None else self._hidden(confident, frame)
            s = replace(s, seconds=s.seconds + time.perf_counter() - t)  # the next frame's start is this frame's work
        self.steps.append(s)
        return s


def near_view(T_world_camera: np.ndarray, advice, centre: np.ndarray) -> bool:
    """Whether a camera is where `advice` (a NextView) said to look from: its optical axis within FUSE_NEAR_DEG of
    the advised one's, its position within FUSE_NEAR_SHARE of the advised camera's distance to the base's centre
    (`centre`, world)."""
    A = advice.T_world_camera
    cos = float(np.clip(T_world_camera[:3, 2] @ A[:3, 2], -1.0, 1.0))
    reach = FUSE_NEAR_SHARE * float(np.linalg.norm(A[:3, 3] - centre))
    return bool(np.degrees(np.arccos(cos)) <= FUSE_NEAR_DEG and np.linalg.norm(A[:3, 3] - T_world_camera[:3, 3]) <= reach)


def last_seen_box(last: RegistrationResult, frame: Frame, margin: float = 0.15) -> tuple[int, int, int, int] | None:
    """A prompt box around where `last` puts the base in `frame` (what the camera saw of it, moved into this
    camera), `margin` of its size wider per side; None when that is out of the image."""
    pc = se3.transform_points(se3.inv(frame.T_world_camera) @ last.T_world_base, last.source_cloud)
    pc = pc[pc[:, 2] > 1e-6]
    if len(pc) == 0:
        return None
    u, v = frame.camera.project(pc)
    w, h = frame.camera.width, frame.camera.height
    mx, my = margin * (u.max() - u.min()), margin * (v.max() - v.min())
    box = (max(int(u.min() - mx), 0), max(int(v.min() - my), 0), min(int(u.max() + mx) + 1, w),
           min(int(v.max() + my) + 1, h))
    return box if box[2] - box[0] >= 4 and box[3] - box[1] >= 4 else None
