"""Assembly pose estimation by point-cloud registration: the paper's Alg. 1, with every step kept.

Read it from the top in `pipeline.py`, where `estimate` runs one frame:

    PROJ3D    masked depth -> world target cloud                     stages.project_to_cloud
    TFORM     the base object's CAD moved onto the target            stages.place_source
    RCAST     what the real camera would see of it                   stages.raycast_source
    search    prior fast path | upright yaw search | free RANSAC     searches.py
    refine    fine ICP of the best few coarse poses, symmetric twins refine.py
    score     fitness, depth agreement, coverage; near-ties split    scoring.py
    compose   T_world_part = T_world_base @ T_base_part              pipeline.compose

Beside it: `presets.py` (Params, `paper` and `default`), `base.py` (the prepared base object and its
per-step caches), `problem.py` (one frame's prepared target), `results.py` (what comes back), and
`paper.py` (the authors' pipeline as published). Symmetry detection is geometry: ../symmetry.py.
"""

from apose_studio.geometry.symmetry import detect_symmetries
from apose_studio.params import PRESET_PARAMS, Params, resolve_params
from apose_studio.registration.base import BaseObject, NearGrid, place_source, prepare_base, raycast_source
from apose_studio.registration.pipeline import estimate
from apose_studio.registration.scoring import MASK_MARGIN_PX, mask_edge
from apose_studio.registration.searches import upright_starts
from apose_studio.registration.stages import global_registration, icp, project_to_cloud
from apose_studio.registration.table import table_normal
from apose_studio.registration.task import scale_problem
from apose_studio.registration.types import (
           CONFIDENT_COVERAGE,
           MIN_POINTS,
           TIE_MARGIN,
           Candidate,
           Observation,
           RegistrationResult,
           Stage,
           doubts,
           failed,
)

__all__ = ["BaseObject", "CONFIDENT_COVERAGE", "Candidate", "MASK_MARGIN_PX", "MIN_POINTS", "NearGrid", "Observation",
           "PRESET_PARAMS", "Params", "RegistrationResult", "Stage", "TIE_MARGIN", "detect_symmetries", "doubts", "estimate",
           "failed", "global_registration", "icp", "mask_edge", "place_source", "prepare_base", "project_to_cloud",
           "raycast_source", "resolve_params", "scale_problem", "table_normal", "upright_starts"]
