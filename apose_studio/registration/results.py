"""What an estimate returns: the result, its candidates and the stages of its replay."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_POINTS = 30  # fewer target points than this cannot constrain 6 DoF with any confidence
TIE_MARGIN = 0.03  # candidates scoring within this of the best explain the data equally well
CONFIDENT_COVERAGE = 0.85  # below this share of target points within 2 voxels of the model, flag a poor fit


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
    symmetry: int  # index into BaseObject.symmetries it came from (0 = as registered)
    coverage: float = float("nan")  # share of target points within 2 voxels of what the model shows (loose fitness)


@dataclass
class RegistrationResult:
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
    preset: str = ""
    voxel: float = 0.0
    coverage: float = float("nan")  # share of target points within 2 voxels of what the model shows (loose fitness)

    @property
    def seconds(self) -> float:
        return float(sum(self.timings.values()))

    @property
    def confident(self) -> bool:
        """The model explains most of the target; a poor fit is likely a wrong pose, whatever else it says."""
        return bool(self.ok and (np.isnan(self.coverage) or self.coverage >= CONFIDENT_COVERAGE))


def failed(reason: str, **kw) -> RegistrationResult:
    return RegistrationResult(ok=False, reason=reason, **kw)


class Degenerate(Exception):
    """Input the estimator cannot work with (raised inside, returned as ok=False with the reason)."""
