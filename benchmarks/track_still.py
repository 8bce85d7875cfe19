#!/usr/bin/env python3
"""A camera holding still over a cluttered desk: does the tracker keep the base it detected?

    .venv/bin/python benchmarks/track_still.py [--conditions real,stacked,hidden,kinect]
                                               [--assemblies desk_objects,helical_gearbox,planetary_reducer,fidget]
                                               [--repeats 3] [--frames 6] [--apart 1]

On benchmarks/captures.py's renders (kept in artifacts/captures/, rendered there when missing, the same settings):
each frame is detected as `apose track` detects its first frame (the box prompt round the renderer's visible mask,
10 px wider, the prompted mask, the estimate), and, where that is confident, the very same frame is given to the
tracker --repeats times more, numbered --apart frames apart (default 1: the frames that follow, as a live camera
numbers them, so the tracker carries the motion between its last two poses on as it would there): nothing moved, so
every one should be tracked (milliseconds), the pose where the detection put it. Prints per row: the frames detected
confident, those tracked on every repeat, the repeats re-detected or lost (and the first reason), the tracked frames'
median and 95th-percentile milliseconds, how far the part moved from the detection's pose (median and largest, mm),
the part's error against the renderer's truth (MSSD, exact twins of the base forgiven; the detections' median, the
confident tracked results' median and largest, mm), and the tracked results confident and wrong (that error over
10 % of the part's diameter).
"""

from __future__ import annotations

import apose_studio  # noqa: F401  (first: its thread settings apply only before numpy loads)

# isort: split

import argparse
import collections
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from captures import CONDITIONS, ONLY, prompt_box  # noqa: E402
from registration import loaded_assemblies  # noqa: E402

from apose_studio.data.dataset import Dataset  # noqa: E402
from apose_studio.estimation import StepContext, Tracker, estimate_frame  # noqa: E402
from apose_studio.evaluate import score_frame  # noqa: E402
from apose_studio.masks.prompt import prompted_mask  # noqa: E402
from apose_studio.registration import resolve_params  # noqa: E402
from apose_studio.synth.frame import RenderSettings  # noqa: E402
from apose_studio.synth.render import render_dataset  # noqa: E402


def still(ds: Dataset, asm, models, params, repeats: int, apart: int = 1) -> dict:
    row = collections.defaultdict(list)
    for step in ds.steps:
        ctx = StepContext(asm, models, step)
        ctx.base.warm_up(params)
        for im_id in ds.image_ids(step):
            frame = replace(ds.frame(step, im_id), depth_scale_known=False)  # as a capture: its scale is checked
            box = prompt_box(frame.base_mask(), 10)
            if box is None:
                continue

            def detect(f, _last_seen, box=box, ctx=ctx):  # the user's box, as `apose track --box` gives it
                return estimate_frame(f, ctx, params, mask=prompted_mask(f.rgb, f.depth, f.camera, box=box).mask, box=box)

            tracker = Tracker(ctx, params, detect)
            first = tracker.step(replace(frame, im_id=0))
            if not first.result.confident:
                continue
            row["detected"].append(1)
            row["err_detected"].append(score_frame(frame, first.result, ctx.part, None,
                                                   ctx.base.symmetries).mssd_mod_base_sym * 1000)
            kept = True
            for k in range(1, repeats + 1):
                s = tracker.step(replace(frame, im_id=apart * k))  # the same image again, `apart` frames on
                kept &= s.mode == "tracked"
                if s.mode == "tracked":
                    row["ms"].append(s.seconds * 1000)
                else:
                    row["other"].append(f"{s.mode}: {s.lost_because}")
                r = s.result
                if r.ok:
                    row["moved"].append(float(np.linalg.norm(r.T_world_part[:3, 3] - first.result.T_world_part[:3, 3])) * 1000)
                    mssd = score_frame(frame, r, ctx.part, None, ctx.base.symmetries).mssd_mod_base_sym
                    row["cw"].append(int(r.confident and not (mssd is not None and mssd < 0.1 * ctx.part.diameter)))
                    if r.confident and mssd is not None:
                        row["err_tracked"].append(mssd * 1000)
            row["kept"].append(int(kept))
    return row


def pct(v, q) -> float:
    return float(np.percentile(v, q)) if len(v) else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conditions", default="real,stacked,hidden,kinect")
    ap.add_argument("--assemblies", default="desk_objects,helical_gearbox,planetary_reducer,fidget")
    ap.add_argument("--repeats", type=int, default=3, help="the same frame given to the tracker this many times more")
    ap.add_argument("--frames", type=int, default=6, help="views per step of the renders (captures.py's --frames)")
    ap.add_argument("--apart", type=int, default=1, help="frame numbers between the repeats (1: the frames that follow, "
                    "as a live camera numbers them; the tracker carries the motion between its last two poses on "
                    "over gaps of up to estimation.MAX_GAP frames, so 1000 carries none)")
    ap.add_argument("--data", default=str(REPO / "artifacts" / "captures"))
    args = ap.parse_args()
    unknown = [c for c in args.conditions.split(",") if c not in CONDITIONS]
    if unknown:
        ap.error(f"--conditions: {unknown[0]!r} is not one of {', '.join(CONDITIONS)}")
    params = resolve_params("default")
    print("| assembly | condition | detected confident | tracked on every repeat | repeats re-detected or lost | "
          "tracked ms median / p95 | part moved mm median / max | part's error mm: detected median / tracked median / "
          "tracked max | tracked c&w |")
    print("|---|---|---|---|---|---|---|---|---|")
    total = collections.Counter()
    for name, asm, models in loaded_assemblies(args.assemblies.split(",")):
        for cond in args.conditions.split(","):
            if name not in ONLY.get(cond, (name,)):
                continue
            root = Path(args.data) / f"{name}-{cond}-{args.frames}"
            if not (root / "dataset_info.json").is_file():
                settings = RenderSettings(frames=args.frames, seed=5, **CONDITIONS[cond])
                render_dataset(asm, root, settings if asm.camera is None else replace(settings, camera=asm.camera),
                               overwrite=True, progress=False)
            r = still(Dataset(root), asm, models, params, args.repeats, args.apart)
            total.update(detected=len(r["detected"]), kept=sum(r["kept"]), other=len(r["other"]), cw=sum(r["cw"]))
            why = f" ({r['other'][0][:90]}...)" if r["other"] else ""
            print(f"| {name} | {cond} | {len(r['detected'])} | {sum(r['kept'])} | {len(r['other'])}{why} | "
                  f"{pct(r['ms'], 50):.1f} / {pct(r['ms'], 95):.1f} | {pct(r['moved'], 50):.2f} / "
                  f"{max(r['moved'], default=float('nan')):.2f} | {pct(r['err_detected'], 50):.2f} / "
                  f"{pct(r['err_tracked'], 50):.2f} / {max(r['err_tracked'], default=float('nan')):.2f} | "
                  f"{sum(r['cw'])} |", flush=True)
    print(f"\nall: {total['detected']} frames detected confident, {total['kept']} tracked on every repeat, "
          f"{total['other']} repeats re-detected or lost, {total['cw']} tracked results confident and wrong")
    return 0


if __name__ == "__main__":
    sys.exit(main())
