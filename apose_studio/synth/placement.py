"""Several views of one placement of the base: `apose render --views-per-scene K` (one scene, K cameras
whose viewing directions are at least MIN_VIEW_SEPARATION_DEG apart, as an eye-in-hand camera takes its
looks) and `apose render --trajectory` (one scene per step, a camera moving smoothly over it, a frame per
point of its path: what a tracker sees). The placement's id is recorded per image (docs/DATASET.md)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import trimesh

from apose_studio.assembly.mesh import PartModel
from apose_studio.assembly.model import StepView
from apose_studio.geometry import se3
from apose_studio.geometry.raycast import RayGrid
from apose_studio.synth.frame import (
    RenderedFrame,
    RenderSettings,
    auto_distance_range,
    eye_at,
    sample_camera,
    sample_scene,
    view_of,
)

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


APPROACH_SWEEP_DEG = 40.0  # an approach turns this far round the base while it closes in
ORBIT_SWEEP_DEG = 90.0  # an orbit goes this far round at one distance and height
WOBBLE = 0.02  # the point looked at wanders by this share of the base's diameter (an arm's path is not a rail)


def trajectory_cameras(rng: np.random.Generator, target: np.ndarray, settings: RenderSettings, base_diameter: float,
                       n: int) -> list[np.ndarray]:
    """n T_world_camera along a smooth path over `target`, eased at both ends (a robot's motion starts and
    stops gently). `approach` (an eye-in-hand camera closing in): from the far end of the distance range
    and the top of the pitch range to the near end and the middle, turning APPROACH_SWEEP_DEG round the
    base; `orbit`: ORBIT_SWEEP_DEG round it at the middle distance and pitch. The start's yaw is drawn
    from the yaw range; the point looked at wanders by WOBBLE of the base's diameter."""
    lo, hi = settings.distance_range_m or auto_distance_range(base_diameter, settings.camera, settings.base_fill)
    p_lo, p_hi = settings.pitch_range_deg
    yaw0 = rng.uniform(*settings.yaw_range_deg)
    phase = rng.uniform(0, 2 * np.pi, size=2)
    if settings.trajectory == "approach":
        yaws, pitches, dists = (yaw0, yaw0 + APPROACH_SWEEP_DEG), (p_hi, 0.5 * (p_lo + p_hi)), (hi, lo)
    else:  # orbit
        mid_p, mid_d = 0.5 * (p_lo + p_hi), 0.5 * (lo + hi)
        yaws, pitches, dists = (yaw0, yaw0 + ORBIT_SWEEP_DEG), (mid_p, mid_p), (mid_d, mid_d)
    out = []
    for k in range(n):
        s = 0.5 - 0.5 * math.cos(math.pi * k / (n - 1)) if n > 1 else 0.0
        yaw = math.radians(yaws[0] + s * (yaws[1] - yaws[0]))
        pitch = math.radians(pitches[0] + s * (pitches[1] - pitches[0]))
        dist = dists[0] + s * (dists[1] - dists[0])
        look = target + WOBBLE * base_diameter * np.array([math.sin(2 * math.pi * s + phase[0]),
                                                           math.sin(4 * math.pi * s + phase[1]), 0.0])
        out.append(se3.look_at(eye_at(target, dist, yaw, pitch), look))
    return out


def render_trajectory(models: dict[str, PartModel], view: StepView, settings: RenderSettings, grid: RayGrid,
                      seed: list[int], base: trimesh.Trimesh | None = None, noise: bool = True) -> Iterator[RenderedFrame]:
    """`settings.frames` views of one placement along `settings.trajectory` (trajectory_cameras), one at a time.
    The scene and path come from default_rng(seed), the light (one for every view) from seed + [2**32], each
    view's sensor noise from seed + [its index]."""
    rng = np.random.default_rng(seed)
    scene = sample_scene(models, view, settings, rng, base)
    cams = trajectory_cameras(rng, scene.base_centre, settings, scene.base_diameter, settings.frames)
    for j, T in enumerate(cams):
        yield view_of(scene, T, grid, np.random.default_rng(seed + [j]), settings if noise else None,
                      lighting=np.random.default_rng(seed + [2 ** 32]))
