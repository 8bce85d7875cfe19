#!/usr/bin/env python3
"""Segmentation: train on renders of each sample assembly (CPU), then on held-out noisy frames report
mask IoU and pose recall with predicted masks beside ground-truth and depth-only masks.

    .venv/bin/python benchmarks/segmentation.py [--train-frames 50] [--epochs 25] [--max-minutes 9.5]
                                                [--test-frames 10] [--assemblies helical_gearbox,planetary_reducer]

Training set: `--train-frames` RealSense-like views per step, base at a random yaw (seed 10). Test set:
`--test-frames` other views per step (seed 99), base at the CAD orientation so pose recall measures
the masks, not RANSAC luck (the estimator gets the orientation prior, preset default).
Goals: training <= 10 min on this CPU, base-object IoU >= 0.90, recall within 2 points of gt masks.
"""

from __future__ import annotations

import argparse
import atexit
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from apose_studio.assembly.mesh import load_parts  # noqa: E402
from apose_studio.assembly.model import load_assembly  # noqa: E402
from apose_studio.data.dataset import Dataset  # noqa: E402
from apose_studio.evaluate import evaluate  # noqa: E402
from apose_studio.masks.segment import evaluate_masks, save_model, train  # noqa: E402
from apose_studio.registration import resolve_params  # noqa: E402
from apose_studio.synth.frame import RenderSettings  # noqa: E402
from apose_studio.synth.render import render_dataset


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train-frames", type=int, default=50)
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--max-minutes", type=float, default=9.5)
    ap.add_argument("--test-frames", type=int, default=10)
    ap.add_argument("--assemblies", default="helical_gearbox,planetary_reducer")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="apose-bench-seg-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # renders and copies: gone when the run ends
    rows = []
    for name in args.assemblies.split(","):
        asm = load_assembly(REPO / "sample_assemblies" / name / "assembly.yaml")
        models = load_parts(asm)
        train_dir, test_dir = tmp / name / "train", tmp / name / "test"
        render_dataset(asm, train_dir, RenderSettings(frames=args.train_frames, noise="realsense", seed=10),
                       progress=False, models=models)
        render_dataset(asm, test_dir, RenderSettings(frames=args.test_frames, noise="realsense", base_pose="fixed", seed=99),
                       progress=False, models=models)
        t0 = time.perf_counter()
        seg, rep = train(Dataset(train_dir), epochs=args.epochs, device="cpu", max_minutes=args.max_minutes,
                         progress=sys.stderr.isatty())
        train_s = time.perf_counter() - t0
        save_model(seg, tmp / name / "seg.pt")
        test = Dataset(test_dir)
        ious = evaluate_masks(seg, test, [(s, i) for s in test.steps for i in test.image_ids(s)])
        docs = {src: evaluate(test, resolve_params("default"), mask_source=src, orientation_prior=True, progress=False,
                              models=models)
                for src in ("gt", str(tmp / name / "seg.pt"), "depth")}
        for k, st in enumerate(docs["gt"]["steps"]):
            rows.append((name, st["step"], rep["epochs"], train_s, ious["base_iou"].get(st["step"], float("nan")),
                         ious["base_iou_raw"].get(st["step"], float("nan")),
                         docs["depth"]["steps"][k]["mask_iou"], st["recall_mssd"],
                         docs[str(tmp / name / "seg.pt")]["steps"][k]["recall_mssd"], docs["depth"]["steps"][k]["recall_mssd"]))
        print(f"{name}: part IoU " + ", ".join(f"{p} {v:.3f}" for p, v in ious["part_iou"].items()), flush=True)
    print(f"\nmachine: {os.cpu_count()} cores, CPU training; {args.train_frames} training views per step, "
          f"{args.test_frames} held-out test views per step (RealSense-like noise)\n")
    print(f"{'assembly':<18} {'step':>4} {'epochs':>6} {'train s':>7} | {'IoU net':>7} {'(raw)':>6} {'IoU depth':>9} | "
          f"{'rec gt':>6} {'rec net':>7} {'rec depth':>9}")
    for r in rows:
        print(f"{r[0]:<18} {r[1]:>4} {r[2]:>6} {r[3]:>7.0f} | {r[4]:>7.3f} {r[5]:>6.3f} {r[6]:>9.3f} | "
              f"{r[7]:>6.2f} {r[8]:>7.2f} {r[9]:>9.2f}")
    print("\nIoU: base object (union of the step's base parts) against ground truth at full resolution; net = the "
          "network's mask sharpened with depth (what the estimator uses), raw = the network alone; "
          "rec: pose recall (MSSD < 0.1 d) with each mask source")
    return 0


if __name__ == "__main__":
    sys.exit(main())
