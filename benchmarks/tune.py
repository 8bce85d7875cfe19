#!/usr/bin/env python3
"""Tuning: two or more settings of the `default` preset, run frame by frame in turn on the same frames.

    .venv/bin/python benchmarks/tune.py '{}' '{"max_starts": 4}' [--frames 10] [--base-pose yaw] [--data DIR]

Each argument is a JSON object of registration parameters (the names of an assembly file's
`registration` section; `{}` is the preset as shipped). The frames (every assembly of
benchmarks/registration.py, with and without RealSense-like noise) are rendered once into --data
(kept there for the next run) and every frame is estimated with each setting in turn, the order
alternating from frame to frame, so that this machine's drift in speed falls on all settings
alike: on a 2-core machine run-to-run timings drift by 10-15 %, which a back-to-back comparison of
two whole benchmark runs cannot tell from a real change. Prints, per step, recall (MSSD below 10 %
of the part's diameter) and median seconds per frame of each setting, then a summary line each.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from registration import ASSEMBLIES, loaded_assemblies  # noqa: E402

from apose_studio.dataset import Dataset  # noqa: E402
from apose_studio.evaluate import StepContext, estimate_and_score  # noqa: E402
from apose_studio.register import resolve_params  # noqa: E402
from apose_studio.render import RenderSettings, render_dataset  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("settings", nargs="*", default=["{}"], help="JSON objects of registration parameters")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--base-pose", default="yaw", choices=["yaw", "fixed"])
    ap.add_argument("--noise", default="none,realsense")
    ap.add_argument("--data", default=str(REPO / "artifacts" / "tune"), help="where the rendered frames are kept")
    args = ap.parse_args()
    settings = [json.loads(s) for s in args.settings]
    params = [resolve_params("default", **s) for s in settings]
    times: list[list[float]] = [[] for _ in params]
    recalls: list[list[float]] = [[] for _ in params]
    adis: list[list[float]] = [[] for _ in params]
    for name, asm, models in loaded_assemblies(ASSEMBLIES):
        for noise in args.noise.split(","):
            root = Path(args.data) / f"{name}-{noise}-{args.base_pose}-{args.frames}"
            if not (root / "dataset_info.json").is_file():
                render_dataset(asm, root, RenderSettings(frames=args.frames, noise=noise, base_pose=args.base_pose,
                                                         seed=11), progress=False, models=models)
            ds = Dataset(root)
            cells: list[list[str]] = [[] for _ in params]
            for step in range(1, len(ds.assembly.steps) + 1):
                ctx = StepContext(ds.assembly, models, step)
                frames = [ds.frame(step, im) for im in ds.image_ids(step)]
                for p in params:  # per-step caches (model features, grids) warmed for every setting
                    estimate_and_score(frames[0], ctx, p, orientation_prior=args.base_pose == "fixed")
                t_step: list[list[float]] = [[] for _ in params]
                ok_step: list[list[bool]] = [[] for _ in params]
                for j, fr in enumerate(frames):
                    order = range(len(params)) if j % 2 == 0 else reversed(range(len(params)))
                    for i in order:
                        t = time.perf_counter()
                        _, score = estimate_and_score(fr, ctx, params[i], orientation_prior=args.base_pose == "fixed")
                        t_step[i].append(time.perf_counter() - t)
                        ok = score.mssd is not None and score.mssd < 0.1 * ctx.part.diameter
                        ok_step[i].append(ok)
                        if ok:
                            adis[i].append(score.adi)
                for i in range(len(params)):
                    cells[i].append(f"{np.mean(ok_step[i]):.1f} {np.median(t_step[i]) * 1000:4.0f} ms")
                    times[i].append(float(np.median(t_step[i])))
                    recalls[i].append(float(np.mean(ok_step[i])))
            for i in range(len(params)):
                print(f"{name:<18} {noise:<9} #{i}  " + " | ".join(cells[i]), flush=True)
    print("\ncells: recall and median time per frame of each step (estimate and scoring)")
    for i, s in enumerate(settings):
        print(f"#{i} {json.dumps(s)}: mean recall {np.mean(recalls[i]):.3f}; median of the steps' median times "
              f"{np.median(times[i]) * 1000:.0f} ms, mean {np.mean(times[i]) * 1000:.0f} ms; mean ADI of the right "
              f"frames {np.mean(adis[i]) * 1000:.3f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
