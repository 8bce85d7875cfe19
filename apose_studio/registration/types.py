"""The registration package's shared data: what a frame shows (Observation), the searches' starting poses
(Start, Found), and what an estimate returns (the result, its candidates and the stages of its replay)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from apose_studio.geometry.camera import CameraIntrinsics, box_region

MIN_POINTS = 30  # fewer target points than this cannot constrain 6 DoF with any confidence
BOX_SLACK, BOX_SLACK_PX = 0.05, 4  # a prompt box is drawn loosely: the model may show this much outside it
TIE_MARGIN = 0.03  # candidates scoring within this of the best explain the data equally well
TWIN_TIE_MARGIN = 0.045  # ... and a twin of the best (turned by a symmetry or close twin) within this: the evidence
# where the two differ decides (benchmarks/captures.py: a planetary motor's wrong twin scored 0.034 above the right
# one, its connector on clutter the mask took in; it was a confident miss)
# below this share of target points near the model (2 voxels, or 3 sigmas of the frame's depth noise), flag a poor
# fit. Calibrated on 160 cluttered renders under four noise models with box-prompted masks
# (benchmarks/captures.py): 0.80 with "not ambiguous" gave 1 confident-and-wrong frame; 0.85 gave the same
# and 13 more right poses called unconfident.
CONFIDENT_COVERAGE = 0.80
CONFIDENT_CONTRADICTION = 0.05  # above this share of the model's view that the depth sees past, flag a poor fit
CONFIDENT_CONTINUATION = 0.3  # above this share of the ring around the model's outline where the surface runs on at
# the edge's depth, the model may be laid onto a larger object; captures.py: right confident poses 0-0.16, a watering
# can fitted to the face of a box in front of it 0.42
CONFIDENT_SUNK = 0.25  # a region of a larger part (roi): above this share of what the model shows hidden behind a nearer
# surface, it may be sunk into that surface (a seat's pad laid on a table, its deck and sides below the table top: 0.47).
# benchmarks/seats.py: right poses 0.00-0.19 (88 seat views, RealSense- and Kinect-like), wrong ones 0.04-0.56
CONFIDENT_BODY_PAST = 0.10  # a region of a larger part: above this share of the rest of the part (at the region's pose)
# seen past, the region is laid onto something else (a seat's pad fitted to a sphere on the bench, the head beyond it
# where the camera sees the table)
CONFIDENT_SPREAD = 0.06  # the data must pin the pose to within this share of the base's diameter (3 sigma, at its rim);
# benchmarks/captures.py (stacked, hidden, real rows): right confident poses 0.003-0.054, a duck 7 mm off 0.071
CONFIDENT_PART_SPREAD = 0.05  # ... and within this share of the placed part's diameter (half the 10 % a right pose may
# be off; estimation.held_to_part). captures.py, all 528 frames: of 370 confident results, 2 wrong ones exceed it
# (duck labels 8.5 and 24.7 mm off against 7 mm) and 4 right ones (all in the stacked, hidden and real rows)


@dataclass
class Stage:
    """One step of the registration, for the studio's replay."""

    name: str  # "initial", "global" (or "prior", or "first look": where a second look began), "icp 1", ..., "final"
    # (then "settled" where pipeline.settled refitted it)
    T_world_base: np.ndarray
    fitness: float
    inlier_rmse: float


@dataclass
class Candidate:
    T_world_base: np.ndarray
    T_world_part: np.ndarray
    fitness: float  # share of target points explained by the model
    source_fitness: float  # share of what the model shows the camera that the target confirms
    inlier_rmse: float
    score: float
    symmetry: int  # the turn it came from: 0 as registered, k >= 1 the k-th of symmetries[1:] + close_twins
    coverage: float = float("nan")  # share of target points within 2 voxels of what the model shows (loose fitness)


@dataclass(frozen=True, eq=False, kw_only=True)
class RegistrationResult:
    """What `estimate` returns. Frozen: a stage that changes a result (judge, the second look, fusion)
    returns a new one (`dataclasses.replace`)."""

    ok: bool
    reason: str = ""
    T_world_base: np.ndarray | None = None
    T_world_part: np.ndarray | None = None
    T_world_source: np.ndarray | None = None  # the source's initial pose (TFORM)
    target_cloud: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # world
    source_cloud: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # base frame
    stages: list[Stage] = field(default_factory=list)
    fitness: float = 0.0
    inlier_rmse: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    candidates: list[Candidate] = field(default_factory=list)
    ambiguous: bool = False
    alternatives: list[Candidate] = field(default_factory=list)  # other placements of the part that fit as well
    equivalent: list[np.ndarray] = field(default_factory=list)  # T_world_part of the placements an exact symmetry of
    # the base makes physically the same assembly (the part may equally go there; not an ambiguity)
    preset: str = ""
    voxel: float = 0.0
    coverage: float = float("nan")  # share of target points within 2 voxels of what the model shows (loose fitness)
    contradiction: float = float("nan")  # share of what the model shows (confirmed or contradicted) that the camera
    # sees past: the depth is farther than the model's surface there, so the model cannot be there
    second_look: np.ndarray | None = None  # the model-cut mask, when the second look gave this result
    model_mask: np.ndarray | None = None  # the base's visible silhouette at the final pose: the mask the result came
    # from cut to it (an object in front of the base and clutter beside it removed), and the pixels the mask missed
    # within its reach (the prompt's box) where the depth lies on the model (pipeline.model_cut_mask)
    depth_noise: float = 0.0  # the frame's depth noise around the object (metres, one sigma), which widens tolerances
    out_of_time: str = ""  # what the time budget cut short (empty: nothing); such a result is never confident
    views: int = 1  # how many views the estimate fused (registration.fusion)
    spread: float = float("nan")  # how far the data lets the pose move (metres, 3 sigma at the base's rim, along the
    # least constrained motion; scoring.pose_spread): a target that is only a plane or a cylinder's side pins nothing
    spread_allowed: float = float("inf")  # the most `spread` a confident result may have (CONFIDENT_SPREAD x diameter)
    continuation: float = float("nan")  # share of the ring around the model's outline where the surface runs on at
    # the edge's depth (pipeline.outline_continuation): a model laid onto part of a larger surface
    off_table: float = float("nan")  # how far the base's lowest point lies above (+) or in (-) the table it stands on,
    # beyond the slack (0: on it; NaN: no table seen): a pose that floats or sinks cannot be
    sunk: float = float("nan")  # a region of a larger part (roi): the share of what the model shows that a nearer
    # surface hides (scoring.hidden_share); NaN for a whole base, whose occluders are judged by the mask's readings
    body_past: float = float("nan")  # a region of a larger part: the share of the rest of that part, at the region's
    # pose, where the camera sees past it (pipeline.body_evidence); NaN for a whole base
    part_doubt: str = ""  # a region found at a place on its part (estimation.estimate_region_instances): a doubt about
    # that place (the part's own pose not confident, the region off its place); never confident then
    region_twin: str = ""  # a region of the same part alike to the base's (another seat of the head) that the rest of
    # the part fits as well there, or better (pipeline.region_twin): the box may hold that one; never confident then
    tracked: bool = False  # the pose was tracked from the frame before's (registration.track), not searched for
    colour_offset: float = 0.0  # how far (metres) the pose may lie off the base because the depth lies
    # `colour_offset_px` (right, down) off the colour image by its edges (estimation.colour_checked): it counts
    # against the confidence with the spread; 0: no shift found
    colour_offset_px: tuple[int, int] = (0, 0)
    colour_offset_bleed: bool = False  # the edges lie off by colour_offset_px as a shift alone puts them, but a bleed
    # of the depth's outlines past the colour's explains them as well (geometry.sensor.shift_and_bleed): the depth is
    # not moved by it, and it counts against the confidence all the same
    depth_moved_px: tuple[int, int] = (0, 0)  # the depth lay this far (right, down) off the colour image, by its edges,
    # and the result is the estimate on the depth moved back (estimation.estimate_view, `move_depth_to_colour`)
    reading: str = ""  # the reading of the mask the result came from ("": the mask as given; hypotheses.readings)
    problem: object = field(default=None, repr=False)  # the prepared registration problem (ours), for fusion
    base_alternatives: list[np.ndarray] = field(default_factory=list)  # T_world_base of the base turned by a near-
    # symmetry that places the part alike and explains the data as well (refine.base_twins_alike): the part's place is
    # sure, the base's own turn is not (`confident` is about the part's placement; see `base_confident`)
    input_error: bool = False  # a failure that is the input's, not the scene's: depth or CAD units 10x or more off, or
    # a mask of the whole scene (task.scale_problem); `apose estimate` exits 2 (bad input) on it
    depth_scale_better: float = 1.0  # a factor on the depth that the model explains clearly better than the depth as
    # given (calibration.scale_checked): the depth_scale or the intrinsics are off, and the pose with them; never
    # confident then. 1.0: none, or not checked
    depth_scale_gain: float = float("nan")  # how much more the best explained scaled depth is explained than the depth
    # as given (a share; below 0: less; NaN: not checked)
    target_span: float = float("nan")  # the whole mask's depth: its extent over the base's diameter (task.target_span),
    # set where the result is not confident (pipeline.spanned; NaN elsewhere); above SPAN_HINT the doubts say so

    @property
    def base_confident(self) -> bool:
        """`confident`, and the base's own pose too: no turn of it that places the part alike fits as well."""
        return self.confident and not self.base_alternatives

    @property
    def seconds(self) -> float:
        return float(sum(self.timings.values()))

    @property
    def fits(self) -> bool:
        """The fit part of `confident`: enough coverage, little contradiction, no search cut short, a pose the
        data pins down (spread, with what a depth lying off the colour image may add: colour_offset), resting
        on the table where one is seen, an outline that is an outline (not a larger surface running on past
        it); an ambiguous result may fit: each of its placements explains the data."""
        return bool(self.ok and np.isfinite(self.coverage) and self.coverage >= CONFIDENT_COVERAGE
                    and not self.contradiction > CONFIDENT_CONTRADICTION and not self.out_of_time
                    and not self.spread + self.colour_offset > self.spread_allowed and not abs(self.off_table) > 0
                    and not self.continuation > CONFIDENT_CONTINUATION and not self.sunk > CONFIDENT_SUNK
                    and not self.body_past > CONFIDENT_BODY_PAST)

    @property
    def confident(self) -> bool:
        """One placement that the data supports: the model explains most of the target (a poor fit is likely
        a wrong pose, whatever else it says), the depth contradicts almost nothing the model shows, no
        search was cut short, and no other placement fits as well (ambiguous). An unknown coverage (NaN)
        is never confident."""
        return (self.fits and not self.ambiguous and not self.region_twin and not self.part_doubt
                and self.depth_scale_better == 1.0)


def doubts(result: RegistrationResult) -> str:
    """Why a result is not confident, in words ("" when it is, or when it failed)."""
    if not result.ok or result.confident:
        return ""
    why = []
    if not np.isfinite(result.coverage) or result.coverage < CONFIDENT_COVERAGE:
        why.append(f"only {result.coverage:.0%} of the target lies near the model" if np.isfinite(result.coverage)
                   else "how much of the target the model explains is unknown")
    if result.contradiction > CONFIDENT_CONTRADICTION:
        why.append(f"the depth contradicts {result.contradiction:.0%} of what the model shows")
    if result.spread == float("inf"):
        why.append("nothing the camera sees pins the pose down (too few points near the model, or a plain region: a flat "
                   "patch or a cylinder's side slides along itself; give the roi a distinctive feature)")
    elif result.spread > result.spread_allowed:
        why.append(f"the view leaves the pose free to move by {result.spread * 1000:.1f} mm, more than the "
                   f"{result.spread_allowed * 1000:.1f} mm the placement allows (what is seen, such as a flat face or "
                   "a cylinder's side, pins it down poorly)")
    elif result.colour_offset and result.spread + result.colour_offset > result.spread_allowed:
        du, dv = result.colour_offset_px
        bled = " (or its outlines bleed past the colour's by as much: the edges cannot tell which)" \
            if result.colour_offset_bleed else ""
        why.append(f"the depth's edges lie {du:+d}, {dv:+d} px (right, down) off the colour image's here{bled}: if the "
                   "depth is "
                   f"registered that far off, the pose is {result.colour_offset * 1000:.1f} mm off, more than the "
                   f"{result.spread_allowed * 1000:.1f} mm the placement allows with what the view leaves free; if it is "
                   "(a Kinect's often is), align depth to colour (--align-depth) to move it back first")
    if result.continuation > CONFIDENT_CONTINUATION:
        why.append(f"the surface runs on past {result.continuation:.0%} of the model's outline (it may be laid onto "
                   "part of a larger object)")
    if result.sunk > CONFIDENT_SUNK:
        why.append(f"a nearer surface hides {result.sunk:.0%} of what the region shows (it may be sunk into that surface, "
                   "or hidden: draw the box round the region where the camera sees it)")
    if result.body_past > CONFIDENT_BODY_PAST:
        why.append(f"the camera sees past {result.body_past:.0%} of the rest of the part at this pose (the region may be "
                   "laid onto something else)")
    if abs(result.off_table) > 0:
        why.append(f"the pose {'floats' if result.off_table > 0 else 'sinks'} {abs(result.off_table) * 1000:.0f} mm "
                   f"{'above' if result.off_table > 0 else 'into'} the table it stands on")
    if result.out_of_time:
        why.append(f"the time budget cut short {result.out_of_time}")
    if result.part_doubt:
        why.append(result.part_doubt)
    if result.region_twin:
        why.append(f"the box may hold {result.region_twin} (a region alike on the same part): the rest of the part fits "
                   "as well or better were it that one (draw the box round the step's own region, or show more of the part)")
    if result.depth_scale_better != 1.0:
        f = result.depth_scale_better
        why.append(f"the model explains the view {result.depth_scale_gain:.0%} better with every depth "
                   f"{abs(f - 1):.0%} {'nearer' if f < 1 else 'farther'} (x {f:.2f}): the depth's scale looks off (check "
                   f"{DEPTH_SCALE_WHERE}, and that cam_K is for this image's resolution); the pose is off along the "
                   "camera's rays by as much")
    if result.ambiguous:
        why.append(f"{len(result.alternatives) + 1} placements fit the data equally (ambiguous)")
    hint = span_hint(result.target_span)
    if why and hint:
        why.append(hint)
    return "; ".join(why)


DEPTH_SCALE_WHERE = ("the depth_scale in camera.json (scene_camera.json in a BOP scene), or the depth's unit (metres in "
                     "the API)")  # where a depth's scale is set, for every message that doubts it
SPAN_HINT = 1.9  # a target this many times wider than the base's diameter is more than a view of the base: its mask
# holds other things, or the depth's scale is off. benchmarks/captures.py's prompted masks (all their depth): 1.03
# median, 1.60 at the 99th percentile, at most 1.89 (a motor's mask with a neighbour in it); a fidget casing's capture
# with depth_scale 2x and 3x too large: 1.92, 2.80 (a span over 4 is refused outright: task.scale_problem)
SPAN_LOW = 0.5  # ... and this many times narrower, too little of it, or a depth scaled too small: the same masks span
# 0.30 at the least (a base mostly hidden), 0.62 at the 1st percentile; the fidget casing with depth_scale 0.5x: 0.43


def span_hint(span: float) -> str:
    """The words for a target `span` times the base's diameter (a doubt's or a failure's last clause), or "" where
    the span is one a view of the base can have."""
    if span > SPAN_HINT:
        return (f"the masked depth spans {span:.1f}x the base object's diameter, more than any view of it: the mask takes "
                f"in other things (draw the box tighter), or the depth's scale is off (check {DEPTH_SCALE_WHERE})")
    if span < SPAN_LOW:
        return (f"the masked depth spans only {span:.2f}x the base object's diameter: too little of the base is in view, "
                f"or the depth's scale is too small (check {DEPTH_SCALE_WHERE})")
    return ""


def failed(reason: str, **kw) -> RegistrationResult:
    return RegistrationResult(ok=False, reason=reason, **kw)


class Degenerate(Exception):
    """Input the estimator cannot work with (raised inside, returned as ok=False with the reason)."""


class Observation(NamedTuple):
    """What a frame shows of the base: its mask, the depth (metres) and the mask's outline (`mask_edge`)."""

    mask: np.ndarray
    depth: np.ndarray
    edge: np.ndarray
    noise: float = 0.0  # the frame's own axial depth noise (metres, one sigma; noise.estimate_depth_noise)


@dataclass
class Start:
    """A starting pose after the coarse ICP: the share of what it shows that the target explains,
    the symmetry it came from (-1: the caller's prior), the pose ICP began from, the coarse pose."""

    explained: float
    symmetry: int
    T_start: np.ndarray
    T_coarse: np.ndarray


@dataclass
class Found:
    """What the searches found: coarse poses (best first), the best upright pose's near-symmetric
    twins, whether the base was taken to stand upright on a table, and whether it was also slid over the
    table (searches.resting_starts: no start centred on what is seen fitted)."""

    coarse: list[Start]
    twins: list[Start] = field(default_factory=list)
    upright: bool = False
    slid: bool = False


@dataclass(frozen=True, eq=False)
class View:
    """One look at the base: depth (metres), the base's mask, the intrinsics and the camera's pose; what
    `estimate` takes, and `estimate_views` takes several of."""

    depth: np.ndarray
    mask: np.ndarray
    camera: CameraIntrinsics
    T_world_camera: np.ndarray
    name: str = ""  # how errors name it (a file, "frame 3")
    rgb: np.ndarray | None = None  # (H, W, 3) uint8, registered to the depth, when known: colours split the mask's
    # readings (hypotheses.readings)
    box: tuple[int, int, int, int] | None = None  # the prompt's box (x0, y0, x1, y1), when a box gave the mask: what
    # the model shows of the base far outside it contradicts the pose (the user drew it around all they see)
    depth_scale_known: bool = False  # the depth's scale is the renderer's own (Frame.depth_scale_known): not checked

    def outside_box(self) -> np.ndarray | None:
        """(H, W) bool: pixels farther outside the prompt's box than its margin (BOX_SLACK of its size, at least
        BOX_SLACK_PX): where the user says no part of the base is seen. None without a box."""
        if self.box is None:
            return None
        x0, y0, x1, y1 = (int(v) for v in self.box)
        return ~box_region(self.depth.shape, self.box, max(BOX_SLACK_PX, int(BOX_SLACK * max(x1 - x0, y1 - y0))))

    @classmethod
    def of(cls, frame, mask: np.ndarray) -> "View":
        """A dataset.Frame (a render, a capture) with the base's mask."""
        return cls(frame.depth, mask, frame.camera, frame.T_world_camera, frame.source or f"frame {frame.im_id}",
                   getattr(frame, "rgb", None), depth_scale_known=getattr(frame, "depth_scale_known", False))
