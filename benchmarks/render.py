#!/usr/bin/env python3
"""Rendering speed: frames/s of `apose render` (640x480 RGB-D + masks + BOP files) per assembly and noise model.

    .venv/bin/python benchmarks/render.py [--frames 40]

Renders every step of each sample assembly (and ../shared/data/fidget_helical when present) into a
temporary folder and prints a table. Frames/s counts the frame loop (ray casting, shading, noise,
PNG and JSON writing); loading the parts is reported apart. Goal: >= 20 frames/s on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from apose_studio.assembly.mesh import load_parts  # noqa: E402
from apose_studio.assembly.model import load_assembly  # noqa: E402
from apose_studio.synth.frame import RenderSettings  # noqa: E402
from apose_studio.synth.render import render_dataset


def assemblies() -> list[Path]:
    out = [REPO / "sample_assemblies" / n / "assembly.yaml" for n in ("helical_gearbox", "planetary_reducer")]
    fidget = REPO.parent / "shared" / "data" / "fidget_helical" / "assembly.yaml"
    return out + ([fidget] if fidget.is_file() else [])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="views per step (default 40)")
    args = ap.parse_args()
    print(f"machine: {os.cpu_count()} cores; 640x480; {args.frames} frames per step\n")
    print(f"{'assembly':<20} {'noise':<10} {'frames':>6} {'seconds':>8} {'frames/s':>9} {'setup s':>8}")
    for path in assemblies():
        asm = load_assembly(path)
        models = load_parts(asm)
        for noise in ("none", "realsense"):
            with tempfile.TemporaryDirectory() as tmp:
                s = render_dataset(asm, Path(tmp) / "ds", RenderSettings(frames=args.frames, noise=noise),
                                   progress=False, models=models)
            print(f"{asm.name:<20} {noise:<10} {s['frames']:>6} {s['seconds']:>8.2f} {s['fps']:>9.1f} {s['setup_seconds']:>8.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
