"""Several views of one placement of the base (`apose render --views-per-scene K`): one scene, K
cameras whose viewing directions are at least MIN_VIEW_SEPARATION_DEG apart, as an eye-in-hand camera
takes its looks. The placement's id is recorded per image (docs/DATASET.md)."""

from __future__ import annotations

import numpy as np
import trimesh

from apose_studio.assembly.mesh import PartModel
from apose_studio.assembly.model import StepView
from apose_studio.geometry import se3
from apose_studio.geometry.raycast import RayGrid
from apose_studio.synth.frame import RenderedFrame, RenderSettings, sample_camera, sample_scene, view_of

MIN_VIEW_SEPARATION_DEG = 30.0


def sample_cameras(rng: np.random.Generator, target: np.ndarray, settings: RenderSettings, base_diameter: float,
                   k: int) -> list[np.ndarray]:
    """k camera poses of one placement, their viewing directions at least MIN_VIEW_SEPARATION_DEG apart
    (drawn like `sample_camera`, a draw too close to an earlier one drawn again; after 500 tries the
    best-separated draw is taken)."""
    poses: list[np.ndarray] = []
    for _ in range(k):
        best, best_sep = None, -1.0
        for _ in range(500):
            T = sample_camera(rng, target, settings, base_diameter)
            sep = min((se3.rotation_angle_deg(T[:3, :3].T @ P[:3, :3]) for P in poses), default=180.0)
            if sep > best_sep:
                best, best_sep = T, sep
            if sep >= MIN_VIEW_SEPARATION_DEG:
                break
        poses.append(best)
    return poses


def render_placement(models: dict[str, PartModel], view: StepView, settings: RenderSettings, grid: RayGrid,
                     seed: list[int], base: trimesh.Trimesh | None = None, noise: bool = True) -> list[RenderedFrame]:
    """`settings.views_per_scene` views of one placement of the base (one scene, cameras >= 30 deg apart).
    The scene and cameras come from default_rng(seed), each view's shading from seed + [its index]."""
    rng = np.random.default_rng(seed)
    scene = sample_scene(models, view, settings, rng, base)
    cams = sample_cameras(rng, scene.base_centre, settings, scene.base_diameter, settings.views_per_scene)
    return [view_of(scene, T, grid, np.random.default_rng(seed + [j]), settings if noise else None)
            for j, T in enumerate(cams)]
