"""The registration package's shared data: what a frame shows (Observation), the searches' starting poses
(Start, Found), and what an estimate returns (the result, its candidates and the stages of its replay)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from apose_studio.geometry.camera import CameraIntrinsics

MIN_POINTS = 30  # fewer target points than this cannot constrain 6 DoF with any confidence
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


@dataclass
class Stage:
    """One step of the registration, for the studio's replay."""

    name: str  # "initial", "global", "icp 1", ..., "final"
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
    model_mask: np.ndarray | None = None  # the mask the result came from, cut to what the model shows at the final
    # pose (an object in front of the base and clutter beside it removed): the base's mask as the estimate sees it
    depth_noise: float = 0.0  # the frame's depth noise around the object (metres, one sigma), which widens tolerances
    out_of_time: str = ""  # what the time budget cut short (empty: nothing); such a result is never confident
    views: int = 1  # how many views the estimate fused (registration.fusion)
    problem: object = field(default=None, repr=False)  # the prepared registration problem (ours), for fusion

    @property
    def seconds(self) -> float:
        return float(sum(self.timings.values()))

    @property
    def fits(self) -> bool:
        """The fit part of `confident`: enough coverage, little contradiction, no search cut short (an
        ambiguous result may fit: each of its placements explains the data)."""
        return bool(self.ok and np.isfinite(self.coverage) and self.coverage >= CONFIDENT_COVERAGE
                    and not self.contradiction > CONFIDENT_CONTRADICTION and not self.out_of_time)

    @property
    def confident(self) -> bool:
        """One placement that the data supports: the model explains most of the target (a poor fit is likely
        a wrong pose, whatever else it says), the depth contradicts almost nothing the model shows, no
        search was cut short, and no other placement fits as well (ambiguous). An unknown coverage (NaN)
        is never confident."""
        return self.fits and not self.ambiguous


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
    if result.out_of_time:
        why.append(f"the time budget cut short {result.out_of_time}")
    if result.ambiguous:
        why.append(f"{len(result.alternatives) + 1} placements fit the data equally (ambiguous)")
    return "; ".join(why)


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
    twins, and whether the base was taken to stand upright on a table."""

    coarse: list[Start]
    twins: list[Start] = field(default_factory=list)
    upright: bool = False


@dataclass(frozen=True, eq=False)
class View:
    """One look at the base: depth (metres), the base's mask, the intrinsics and the camera's pose; what
    `estimate` takes, and `estimate_views` takes several of."""

    depth: np.ndarray
    mask: np.ndarray
    camera: CameraIntrinsics
    T_world_camera: np.ndarray
    name: str = ""  # how errors name it (a file, "frame 3")

    @classmethod
    def of(cls, frame, mask: np.ndarray) -> "View":
        """A dataset.Frame (a render, a capture) with the base's mask."""
        return cls(frame.depth, mask, frame.camera, frame.T_world_camera, frame.source or f"frame {frame.im_id}")
