"""Synthetic RGB-D datasets of assembly steps (`apose render`): every chosen step's frames (synth/frame.py)
written in the BOP-compatible layout of docs/DATASET.md, into a locked, journalled output folder."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from apose_studio.assembly.mesh import PartModel, base_body_mesh, load_parts
from apose_studio.assembly.model import Assembly
from apose_studio.data.dataset import FORMAT, SceneWriter, write_json, write_models
from apose_studio.data.outdir import OutputLock, check_output_dir, make_output_dir, remove_previous_dataset, write_manifest
from apose_studio.errors import RenderError
from apose_studio.geometry.raycast import RayGrid
from apose_studio.synth.frame import RenderSettings, render_frame
from apose_studio.synth.frame_queue import FrameQueue
from apose_studio.synth.placement import render_placement, render_trajectory


def step_numbers(asm: Assembly, steps: list[int] | None) -> list[int]:
    """Validate a user's step list (1-based) against the assembly."""
    if not asm.steps:
        raise RenderError(f"{asm.path}: the assembly has no steps to render")
    if not steps:
        return list(range(1, len(asm.steps) + 1))
    bad = [s for s in steps if not 1 <= s <= len(asm.steps)]
    if bad:
        raise RenderError(f"--steps: step {bad[0]} does not exist; {asm.name} has steps 1..{len(asm.steps)}")
    return sorted(set(steps))


# --------------------------------------------------------------------------------- whole datasets


def render_dataset(asm: Assembly, out, settings: RenderSettings, steps: list[int] | None = None,
                   overwrite: bool = False, progress: bool = True, models: dict[str, PartModel] | None = None) -> dict:
    """Render `settings.frames` views of every chosen step into a BOP-layout dataset at `out`.

    Returns a summary {"frames": n, "seconds": s, "fps": f, "setup_seconds": s0}: frames/s over the
    frame loop; loading parts and writing models/ is setup. An interrupt (Ctrl-C) stops after the
    frame in hand; every frame already listed in the JSON files is complete on disk.
    """
    settings.validate()
    numbers = step_numbers(asm, steps)
    out = make_output_dir(Path(out))
    with OutputLock(out):  # first the lock, then the look inside: no other render writes there meanwhile
        check_output_dir(out, overwrite)
        return _render_into(asm, out, settings, numbers, progress, models)


def _render_into(asm: Assembly, out, settings: RenderSettings, numbers: list[int], progress: bool,
                 models: dict[str, PartModel] | None) -> dict:
    t_setup = time.perf_counter()
    models = models or load_parts(asm)
    obj_ids, info = _start_dataset(asm, out, settings, numbers, models)
    grid = RayGrid(settings.camera)
    bar = tqdm(total=len(numbers) * settings.frames, unit="frame", desc=f"render {asm.name}", disable=not progress,
               leave=False)
    t0, done = time.perf_counter(), 0

    queue = FrameQueue(out, info, settings)
    try:
        for number in numbers:
            view = asm.step_view(number)
            base = base_body_mesh(models, view)
            writer = SceneWriter(out, number, {
                "step": number, "part": view.part, "base": list(view.base),
                "part_obj_id": obj_ids[view.part], "base_obj_ids": [obj_ids[p] for p in view.base],
                "T_base_part": view.T_base_part.tolist(),
                "instance_obj_ids": [obj_ids[p] for p in (view.base[0], *view.twins)] if len(view.base) == 1 else []})
            k, group = settings.views_per_scene, []
            path = render_trajectory(models, view, settings, grid, [settings.seed, number, 0], base, noise=False) \
                if settings.trajectory else None
            for im_id in range(settings.frames):
                placement, j = divmod(im_id, k)
                if path is not None:  # one placement, the camera moving along its path
                    placement, fr = 0, next(path)
                elif k == 1:  # one view per placement: seeded per frame, so a dataset re-renders bit for bit
                    rng = np.random.default_rng([settings.seed, number, im_id])
                    fr = render_frame(models, view, settings, grid, rng, base, noise=False)
                else:
                    if j == 0:
                        group = render_placement(models, view, settings, grid, [settings.seed, number, placement, k], base,
                                                 noise=False)
                    fr = group[j]
                queue.submit(writer, im_id, fr, view, obj_ids, placement)
                if im_id % 25 == 24:
                    queue.checkpoint(writer)
                done += 1
                bar.update(1)
            queue.checkpoint(writer)
    finally:
        try:
            queue.close()
        finally:
            bar.close()
    seconds = time.perf_counter() - t0
    return {"frames": done, "seconds": seconds, "fps": done / seconds if seconds > 0 else float("inf"),
            "setup_seconds": t0 - t_setup}


def _start_dataset(asm: Assembly, out, settings: RenderSettings, numbers: list[int],
                   models: dict[str, PartModel]) -> tuple[dict[str, int], dict]:
    """Remove an earlier render's files, write models/, camera.json and the manifest: (obj_ids, info)."""
    remove_previous_dataset(out)
    obj_ids, _ = write_models(asm, models, out)
    cam = settings.camera
    write_json(out / "camera.json", {"cx": cam.cx, "cy": cam.cy, "depth_scale": 0.1, "fx": cam.fx, "fy": cam.fy,
                                     "height": cam.height, "width": cam.width})
    info = {"format": FORMAT, "assembly": asm.name, "source_assembly": str(asm.path) if asm.path else None,
            "obj_ids": obj_ids, "steps_rendered": numbers, "units_of_apose_files": "m",
            "settings": {"frames": settings.frames, "seed": settings.seed, "noise": settings.noise,
                         "noise_sigma_at_05m": settings.noise_sigma_at_05m, "base_pose": settings.base_pose,
                         "yaw_range_deg": list(settings.yaw_range_deg),
                         "pitch_range_deg": list(settings.pitch_range_deg),
                         "distance_range_m": list(settings.distance_range_m) if settings.distance_range_m else "auto",
                         "distractors": settings.distractors, "views_per_scene": settings.views_per_scene,
                         "trajectory": settings.trajectory,
                         "clutter": list(settings.clutter), "depth_bias_m": settings.depth_bias_m,
                         "misregistration_px": settings.misregistration_px, "bleed_px": settings.bleed_px,
                         "base_fill": list(settings.base_fill)}}
    write_manifest(out, info)
    return obj_ids, info
