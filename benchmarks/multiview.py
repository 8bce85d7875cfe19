#!/usr/bin/env python3
"""Two views settle what one cannot: single-view against fused estimates, and next-view advice.

    .venv/bin/python benchmarks/multiview.py [--placements 6] [--noise none,realsense]
                                             [--assemblies fidget,helical_gearbox,planetary_reducer]

Renders `apose render --views-per-scene 2` datasets (the base at a random yaw, no prior; two cameras
at least 30 degrees apart per placement; kept in artifacts/multiview/), ground-truth masks. Per
placement:
- each view alone (`default`): right = MSSD below 10 % of the part's diameter modulo the base's exact
  symmetries; a silent miss = a wrong result that is confident (neither ambiguous nor unconfident);
- both views fused (registration.fusion): right, confident;
- wall seconds of each (median single view, median fused, and their ratio);
- next-view advice: on the first view's results that are ambiguous or not confident, the advised
  camera is rendered (the same scene, the same noise model) and fused with the first view; against
  the dataset's own second view (a random second look). Resolved = the fused result is right and
  confident.
"""

from __future__ import annotations

import apose_studio  # noqa: F401  (first: its thread settings apply only before numpy loads)

# isort: split

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from registration import ASSEMBLIES, loaded_assemblies  # noqa: E402

from apose_studio.data.dataset import Dataset  # noqa: E402
from apose_studio.estimation import StepContext, estimate_frames, estimate_view  # noqa: E402
from apose_studio.evaluate import score_frame
from apose_studio.registration import resolve_params  # noqa: E402
from apose_studio.registration.next_view import next_view  # noqa: E402
from apose_studio.registration.types import View  # noqa: E402
from apose_studio.synth.frame import RenderSettings, sample_scene, view_of  # noqa: E402
from apose_studio.synth.render import RayGrid, render_dataset


def right(frame, r, ctx) -> bool:
    if not r.ok:
        return False
    sc = score_frame(frame, r, ctx.part, None, ctx.base.symmetries)
    return bool(sc.mssd_mod_base_sym < 0.1 * ctx.part.diameter)


def advised_view(asm, models, ctx, settings: RenderSettings, step: int, placement: int, T_world_camera, grid) -> View:
    """The placement's scene (re-drawn from its seed, as render_placement drew it) seen from T_world_camera."""
    rng = np.random.default_rng([settings.seed, step, placement, settings.views_per_scene])
    scene = sample_scene(models, asm.step_view(step), settings, rng)
    fr = view_of(scene, T_world_camera, grid, np.random.default_rng([settings.seed, step, placement, 99]), settings)
    base_ids = [i for i, o in enumerate(scene.objects) if o.part in ctx.view.base]
    return View(fr.depth, np.isin(fr.labels, base_ids), settings.camera, T_world_camera, "advised")


def run(root: Path, asm, models, settings: RenderSettings, params) -> list[dict]:
    ds = Dataset(root)
    grid = RayGrid(settings.camera)
    rows = []
    for step in ds.steps:
        ctx = StepContext(asm, models, step)
        ctx.base.warm_up(params)
        for placement, ids in ds.placements(step).items():
            if len(ids) < 2:
                continue
            frames = [ds.frame(step, i) for i in ids[:2]]
            views = [View.of(f, f.base_mask()) for f in frames]
            row = {"step": step, "single": [], "t_single": []}
            for f, v in zip(frames, views):
                t = time.perf_counter()
                r = estimate_view(v, ctx, params)
                row["t_single"].append(time.perf_counter() - t)
                row["single"].append((right(f, r, ctx), bool(r.ok and r.confident), bool(r.ambiguous)))
                if f is frames[0]:
                    first = r
            t = time.perf_counter()
            fused = estimate_frames(views, ctx, params)
            row["t_fused"] = time.perf_counter() - t
            row["fused"] = (right(frames[0], fused, ctx), bool(fused.ok and fused.confident))
            if first.ok and not (first.confident and not first.ambiguous):
                advice = next_view(first, ctx.base, [views[0].T_world_camera], views[0].camera)
                row["doubt"] = True
                if advice is not None:
                    adv = advised_view(asm, models, ctx, settings, step, placement, advice.T_world_camera, grid)
                    a = estimate_frames([views[0], adv], ctx, params)
                    row["advised"] = right(frames[0], a, ctx) and a.confident
                row["random"] = row["fused"][0] and row["fused"][1]
            rows.append(row)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--placements", type=int, default=6, help="placements per step, two views each (default 6)")
    ap.add_argument("--noise", default="none,realsense")
    ap.add_argument("--assemblies", default=",".join(ASSEMBLIES))
    ap.add_argument("--data", default=str(REPO / "artifacts" / "multiview"), help="where the renders are kept")
    args = ap.parse_args()
    params = resolve_params("default")
    print("| assembly | noise | placements | single recall | single silent misses | fused recall | fused confident "
          "| s single (median) | s fused (median) | fused / single |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    every: list[dict] = []
    for name, asm, models in loaded_assemblies(args.assemblies.split(",")):
        for noise in args.noise.split(","):
            settings = RenderSettings(frames=2 * args.placements, views_per_scene=2, seed=7, noise=noise)
            if asm.camera is not None:
                from dataclasses import replace

                settings = replace(settings, camera=asm.camera)
            root = Path(args.data) / f"{name}-{noise}-{args.placements}"
            if not (root / "dataset_info.json").is_file():
                render_dataset(asm, root, settings, overwrite=True, progress=False)
            rows = run(root, asm, models, settings, params)
            every += rows
            single = [s for r in rows for s in r["single"]]
            ts, tf = np.median([t for r in rows for t in r["t_single"]]), np.median([r["t_fused"] for r in rows])
            print(f"| {name} | {noise} | {len(rows)} | {np.mean([s[0] for s in single]):.3f} | "
                  f"{sum(s[1] and not s[0] for s in single)} of {len(single)} | {np.mean([r['fused'][0] for r in rows]):.3f} | "
                  f"{np.mean([r['fused'][1] for r in rows]):.3f} | {ts:.3f} | {tf:.3f} | {tf / ts:.2f} |", flush=True)
    doubts = [r for r in every if r.get("doubt")]
    single = [s for r in every for s in r["single"]]
    print(f"\nall: single-view recall {np.mean([s[0] for s in single]):.3f}, silent misses "
          f"{sum(s[1] and not s[0] for s in single)} of {len(single)} views; fused recall "
          f"{np.mean([r['fused'][0] for r in every]):.3f} over {len(every)} placements (goal >= 0.99); "
          f"fused / single median time {np.median([r['t_fused'] for r in every]) / np.median([t for r in every for t in r['t_single']]):.2f} (goal <= 1.5)")
    print(f"next view: {len(doubts)} first views ambiguous or not confident; resolved (right and confident) with the "
          f"advised view: {sum(bool(r.get('advised')) for r in doubts)}, with the dataset's random second view: "
          f"{sum(bool(r.get('random')) for r in doubts)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
