#!/usr/bin/env python3
"""Tuning: two or more settings of the `default` preset, run frame by frame in turn on the same frames.

    .venv/bin/python benchmarks/tune.py '{}' '{"max_starts": 4}' [--frames 10] [--base-pose yaw] [--data DIR]
                                        [--poses OUT.json] [--compare BEFORE.json]

Each argument is a JSON object of registration parameters (the names of an assembly file's
`registration` section; `{}` is the preset as shipped). The frames (every assembly of
benchmarks/registration.py, with and without RealSense-like noise) are rendered once into --data
(kept there for the next run) and every frame is estimated with each setting in turn, the order
alternating from frame to frame, so that this machine's drift in speed falls on all settings
alike: on a 2-core machine run-to-run timings drift by 10-15 %, which a back-to-back comparison of
two whole benchmark runs cannot tell from a real change. Prints, per step, recall (MSSD below 10 %
of the part's diameter) and median seconds per frame of each setting, then a summary line each, and
a table per setting of where the time went (the results' timings by stage), and the estimate's own
median and 95th percentile per frame (no scoring) against issue #27's goal for the protocol.

--poses writes every frame's estimated T_world_part of the first setting; --compare reads such a
file from another run (e.g. before a refactoring) and prints how far each pose moved (mm, degrees).
"""

from __future__ import annotations

import apose_studio  # noqa: F401  (first: its thread settings apply only before numpy loads)

# isort: split

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from registration import ASSEMBLIES, loaded_assemblies, stage_table  # noqa: E402

from apose_studio.data.dataset import Dataset  # noqa: E402
from apose_studio.estimation import StepContext, estimate_frame, frame_mask  # noqa: E402
from apose_studio.evaluate import estimate_and_score, score_frame  # noqa: E402
from apose_studio.registration import resolve_params  # noqa: E402
from apose_studio.synth.frame import RenderSettings  # noqa: E402
from apose_studio.synth.render import render_dataset  # noqa: E402

GOAL_P95_MS = {"fixed": 33, "yaw": 50}  # issue #27: per frame, rendered frames, ground-truth masks, this machine


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("settings", nargs="*", default=["{}"], help="JSON objects of registration parameters")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--base-pose", default="yaw", choices=["yaw", "fixed"])
    ap.add_argument("--noise", default="none,realsense")
    ap.add_argument("--data", default=str(REPO / "artifacts" / "tune"), help="where the rendered frames are kept")
    ap.add_argument("--poses", default=None, help="write the first setting's pose of every frame here (JSON)")
    ap.add_argument("--compare", default=None, help="a --poses file of another run: print how far the poses moved")
    args = ap.parse_args()
    poses: dict[str, list | None] = {}
    settings = [json.loads(s) for s in args.settings]
    params = [resolve_params("default", **s) for s in settings]
    times: list[list[float]] = [[] for _ in params]
    recalls: list[list[float]] = [[] for _ in params]
    adis: list[list[float]] = [[] for _ in params]
    stages: list[list[dict[str, float]]] = [[] for _ in params]  # per frame: seconds by stage (a result's timings)
    estimated: list[list[float]] = [[] for _ in params]  # per frame: seconds of the estimate alone (no scoring)
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
                        result = estimate_frame(fr, ctx, params[i], orientation_prior=args.base_pose == "fixed",
                                                mask=frame_mask(fr, "gt"))
                        estimated[i].append(time.perf_counter() - t)
                        score = score_frame(fr, result, ctx.part, None, ctx.base.symmetries)
                        t_step[i].append(time.perf_counter() - t)
                        stages[i].append({**result.timings,
                                          "rest": max(estimated[i][-1] - sum(result.timings.values()), 0.0)})
                        if i == 0:
                            poses[f"{root.name}/{step}/{fr.im_id}"] = result.T_world_part.tolist() if result.ok else None
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
    goal = GOAL_P95_MS[args.base_pose]
    for i, s in enumerate(settings):
        e = np.asarray(estimated[i]) * 1000
        print(f"#{i} estimate alone (ground-truth mask, no scoring), {len(e)} frames: median {np.median(e):.0f} ms, "
              f"p95 {np.percentile(e, 95):.0f} ms; goal (#27, {args.base_pose} protocol) p95 <= {goal} ms: "
              f"{'met' if np.percentile(e, 95) <= goal else 'NOT met'}")
    for i, s in enumerate(settings):
        print(f"\nwhere the time went, #{i} {json.dumps(s)} ('rest': judging and what no stage names):\n")
        print(stage_table(stages[i]))
    if args.poses:
        Path(args.poses).write_text(json.dumps(poses))
        print(f"wrote {len(poses)} poses to {args.poses}")
    if args.compare:
        compare_poses(json.loads(Path(args.compare).read_text()), poses)
    return 0


def compare_poses(before: dict, after: dict) -> None:
    """How far each frame's pose moved between two runs: identical, within thread noise, or apart."""
    from apose_studio.geometry import se3

    common = sorted(set(before) & set(after))
    moves, rots, flips = [], [], []
    for k in common:
        a, b = before[k], after[k]
        if (a is None) != (b is None):
            flips.append(k)
            continue
        if a is None:
            continue
        A, B = np.asarray(a), np.asarray(b)
        moves.append(float(np.linalg.norm(A[:3, 3] - B[:3, 3])) * 1000)
        rots.append(se3.rotation_angle_deg(A[:3, :3].T @ B[:3, :3]))
    moves_a = np.asarray(moves)
    print(f"\ncompared {len(common)} frames with {len(before)} before: identical {int(np.sum(moves_a == 0))}, "
          f"within 0.1 mm {int(np.sum(moves_a < 0.1))}, over 1 mm {int(np.sum(moves_a > 1))} "
          f"(max {moves_a.max() if len(moves) else 0:.3f} mm, {max(rots or [0]):.3f}°); ok/failed changed: {len(flips)}")
    for k in [k for k, m in zip([k for k in common if before[k] is not None and after[k] is not None], moves) if m > 1][:10]:
        print(f"  moved: {k}")


if __name__ == "__main__":
    sys.exit(main())
