"""The estimator's parameters: one typed `Params`, the two presets, and how an assembly file's
`registration` section and a caller override them."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from apose_studio.geometry.camera import CameraIntrinsics, RegistrationConfig
from apose_studio.errors import AposeError


@dataclass(frozen=True)
class Params:
    preset: str
    voxel_size_m: float | None  # None: base diameter / voxels_per_diameter
    voxels_per_diameter: float
    normal_radius_factor: float
    feature_radius_factor: float
    downsample: bool  # FPFH on voxel-down-sampled clouds (ours) or on the full clouds (paper)
    ransac_max_iterations: int
    ransac_confidence: float
    ransac_edge_length: float
    ransac_distance_factor: float
    mutual_filter: bool
    icp_threshold_factor: float
    icp_max_iterations: int
    global_source: str  # "raycast": the paper's partial view; "model": the whole model (orientation-free)
    source_camera: CameraIntrinsics | None  # None: the real camera
    use_symmetries: bool
    use_orientation_prior: bool  # with no prior from the caller, take the CAD's orientation as one (the paper does)
    seed: int = 0
    global_voxel_factor: float = 1.0  # the global step works at voxel x this (ours: coarser, faster)
    feature_matches: int = 1  # >1 (ours): RANSAC draws from the k nearest model features of each target point
    ransac_retry_iterations: int = 0  # ours: when the fast RANSAC explains < 60 % of the target, retry this long
    use_flips: bool = False  # ours: also start ICP from the global pose turned half round about each principal axis
    max_starts: int = 6  # ours: ICP from this many of the screened starting poses
    retry_below: float = 0.95  # retry RANSAC when the best start explains less than this share of what it shows
    prior_fast_path: bool = False  # ours: with an orientation prior, try ICP from it first and stop if it fits
    polish_voxel_factor: float = 0.0  # ours: > 0, a last ICP of the target (down-sampled at voxel x this) onto the
    # model seen at the chosen pose, with the model's exact normals (the noisy target's normals bias point-to-plane)
    polish_threshold_factor: float = 1.0  # its correspondence distance, x voxel
    deterministic: bool = True  # numpy's seeded ICP and RANSAC: the same input gives the same pose in any process
    max_seconds: float = 0.0  # ours: > 0, a time budget for the searches; a search that runs out stops and says so
    second_look: bool = False  # ours: a result that is not confident is estimated again on its mask cut to the model's
    # view at that pose (no clutter beside it, no occluder in front of it); kept only if that one is confident
    upright: bool = False  # ours: where a table is seen, first search the yaw of the base standing on it as modelled
    # (CAD +z along the table's normal); no table, or no confident upright fit: the free search

    def voxel(self, diameter: float) -> float:
        return self.voxel_size_m if self.voxel_size_m else diameter / self.voxels_per_diameter


def fov_camera(width: int, height: int, hfov_deg: float) -> CameraIntrinsics:
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return CameraIntrinsics(width, height, f, f, width / 2, height / 2)


PRESET_PARAMS = {
    # the authors' settings: voxel 8 mm, FPFH on the full clouds, RANSAC 100000 / 0.899, ICP at 0.4 voxel, the
    # source ray-cast at 1280x720 with a 60 degree field of view; the CAD's orientation is trusted; Open3D's
    # RANSAC and ICP (as they used; `deterministic: true` makes it repeatable)
    "paper": Params(
        preset="paper", voxel_size_m=0.008, voxels_per_diameter=40.0, normal_radius_factor=2.0,
        feature_radius_factor=3.0, downsample=False, ransac_max_iterations=100000, ransac_confidence=0.899,
        ransac_edge_length=0.09, ransac_distance_factor=1.2, mutual_filter=False, icp_threshold_factor=0.4,
        icp_max_iterations=30, global_source="raycast", source_camera=fov_camera(1280, 720, 60.0),
        use_symmetries=False, use_orientation_prior=True, deterministic=False),  # Open3D's solvers, as the authors
    # ours: scale-aware voxel, the whole model (no orientation prior needed), upright yaw search, polish
    "default": Params(
        preset="default", voxel_size_m=None, voxels_per_diameter=50.0, normal_radius_factor=2.5,
        feature_radius_factor=5.0, downsample=True, ransac_max_iterations=3000, ransac_confidence=0.999,
        ransac_edge_length=0.9, ransac_distance_factor=1.5, mutual_filter=False, icp_threshold_factor=0.6,
        icp_max_iterations=15, global_source="model", source_camera=None, use_symmetries=True,
        use_orientation_prior=False, global_voxel_factor=2.0, ransac_retry_iterations=30000, use_flips=True,
        prior_fast_path=True, upright=True, polish_voxel_factor=0.5, max_seconds=1.0, second_look=True),
}


def resolve_params(preset: str = "default", config: RegistrationConfig | None = None, **overrides) -> Params:
    """The preset's parameters, overridden by the assembly file's `registration` section and the caller."""
    cfg = config.overrides() if config else {}
    preset = overrides.pop("preset", None) or cfg.pop("preset", None) or preset
    cfg.pop("preset", None)
    if preset not in PRESET_PARAMS:
        raise AposeError(f"unknown preset {preset!r}; choose one of {', '.join(PRESET_PARAMS)}")
    return replace(PRESET_PARAMS[preset], **{**cfg, **overrides})
