#!/usr/bin/env python3
"""Registration: the `default` preset against the authors' `paper` preset, on the same frames.

    .venv/bin/python benchmarks/registration.py [--frames 10] [--assemblies fidget,helical_gearbox,planetary_reducer]
                                                [--noise none,realsense] [--base-pose fixed,yaw] [--json OUT]

For every assembly (the two samples, and ../shared/data/fidget_helical when present), noise model
and base-pose protocol, renders the frames once, then runs both presets on them in this process and
prints per step: median time of each and their ratio, mean ADI and MSSD (mm), and recall (MSSD below
10 % of the part's diameter), strict and modulo the base object's exact symmetries. `fixed` renders give
both presets the CAD's orientation as a prior (the paper's protocol); `yaw` renders give none.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from apose_studio.assembly.mesh import load_parts  # noqa: E402
from apose_studio.assembly.model import load_assembly  # noqa: E402
from apose_studio.data.dataset import Dataset  # noqa: E402
from apose_studio.evaluate import evaluate  # noqa: E402
from apose_studio.registration import resolve_params  # noqa: E402
from apose_studio.synth.frame import RenderSettings  # noqa: E402
from apose_studio.synth.render import render_dataset

ASSEMBLIES = {
    "fidget": REPO.parent / "shared" / "data" / "fidget_helical" / "assembly.yaml",
    "helical_gearbox": REPO / "sample_assemblies" / "helical_gearbox" / "assembly.yaml",
    "planetary_reducer": REPO / "sample_assemblies" / "planetary_reducer" / "assembly.yaml",
}
DESK = {"desk_objects": REPO / "sample_assemblies" / "desk_objects" / "assembly.yaml"}  # household objects at their
# real size (benchmarks/captures.py's real-like rows); not in the registration/tune tables


def stage_table(timings: list[dict[str, float]], title: str = "stage") -> str:
    """A markdown table of where the time went, from each frame's `timings` (seconds by stage, as a
    result's `timings_s` reports them, plus any the caller adds such as the prompted mask): per stage, the
    frames it ran in, its median and 90th-percentile milliseconds there, and its share of all the time.
    Stages in the order they first appear."""
    import numpy as np

    stages: list[str] = []
    for t in timings:
        stages += [k for k in t if k not in stages]
    total = sum(sum(t.values()) for t in timings) or 1.0
    lines = [f"| {title} | frames | median ms | p90 ms | share of the time |", "|---|---|---|---|---|"]
    for k in stages:
        v = np.array([t[k] for t in timings if k in t]) * 1000
        lines.append(f"| {k} | {len(v)} | {np.median(v):.1f} | {np.percentile(v, 90):.1f} | {v.sum() / 1000 / total:.1%} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10, help="views per step (default 10)")
    ap.add_argument("--assemblies", default=",".join(ASSEMBLIES))
    ap.add_argument("--noise", default="none,realsense")
    ap.add_argument("--base-pose", default="fixed,yaw")
    ap.add_argument("--presets", default="paper,default")
    ap.add_argument("--no-free", dest="free", action="store_false",
                    help="skip the extra rows of ours searching freely (--no-upright) on the yaw frames")
    ap.add_argument("--json", help="write every evaluation document here")
    args = ap.parse_args()
    print(f"machine: {os.cpu_count()} cores; {args.frames} frames per step; times are per frame, one process\n")
    hdr = (f"{'assembly':<18} {'noise':<9} {'base':<5} {'step':>4} | {'t paper':>8} {'t ours':>7} {'ratio':>6} | "
           f"{'ADI p':>6} {'ADI o':>6} {'MSSD p':>7} {'MSSD o':>7} | {'rec p':>5} {'rec o':>5} {'~sym p':>6} {'~sym o':>6}")
    print(hdr)
    print("-" * len(hdr))
    docs, summary = [], []
    for name, asm, models in loaded_assemblies(args.assemblies.split(",")):
        for noise in args.noise.split(","):
            for base_pose in args.base_pose.split(","):
                with tempfile.TemporaryDirectory() as tmp:
                    render_dataset(asm, Path(tmp) / "ds", RenderSettings(frames=args.frames, noise=noise, base_pose=base_pose,
                                                                         seed=11), progress=False, models=models)
                    ds = Dataset(Path(tmp) / "ds")
                    res = {}
                    for preset in args.presets.split(","):
                        res[preset] = evaluate(ds, resolve_params(preset), orientation_prior=(base_pose == "fixed"),
                                               progress=False, models=models)
                        res[preset].update(assembly=name, noise=noise, base_pose=base_pose)
                        docs.append(res[preset])
                    if base_pose == "yaw" and args.free and "default" in res:  # ours without the table's cue
                        free = evaluate(ds, resolve_params("default", upright=False), progress=False, models=models)
                        free.update(assembly=name, noise=noise, base_pose="yaw", upright=False)
                        docs.append(free)
                rows = [(base_pose, res.get("default"))]
                if "paper" in res:
                    summary += [(base_pose, noise, res["paper"], o) for _, o in rows if o] + \
                        ([("yaw-", noise, res["paper"], free)] if base_pose == "yaw" and args.free and "default" in res else [])
                if base_pose == "yaw" and args.free and "default" in res:
                    rows.append(("yaw-", free))
                for label, o in rows:
                    print_rows(name, noise, label, res.get("paper"), o)
    if args.json:
        Path(args.json).write_text(json.dumps(docs))
    print("\ncolumns: median seconds per frame (paper, ours) and paper/ours; mean ADI and MSSD in mm over frames "
          "that returned a pose; recall = share of frames with MSSD < 0.1 x part diameter, failures count as misses; "
          "~sym = recall modulo the base object's exact symmetries. base: fixed = CAD orientation given to both; yaw = no "
          "prior (ours as shipped: where it sees a table, it searches first the yaw of the base standing on it); "
          "yaw- = the same yaw frames, ours searching freely (--no-upright), the paper's columns repeated")
    print_goals(summary)
    return 0


def loaded_assemblies(names):
    """(name, assembly, part models) of each named benchmark assembly whose file is here; says which are not."""
    for name in names:
        path = {**ASSEMBLIES, **DESK}[name]
        if not path.is_file():
            print(f"{name}: skipped, {path} not found")
            continue
        asm = load_assembly(path)
        yield name, asm, load_parts(asm)


def print_goals(summary) -> None:
    """The estimation goals, per protocol: >= 20x faster (median per step), mean ADI and MSSD no worse
    than the paper's settings, recall >= 0.99 without noise and >= 0.95 with it."""
    import numpy as np

    if not summary:
        return
    print("\ngoals per protocol (rows = assembly x noise x step):")
    for label in dict.fromkeys(lbl for lbl, *_ in summary):
        ratios, fast, adi_ok, mssd_ok, rec_ok, rec_sym_ok, recall, n = [], 0, 0, 0, 0, 0, [], 0
        for lbl, noise, p, o in summary:
            if lbl != label:
                continue
            goal = 0.99 if noise == "none" else 0.95
            for sp, so in zip(p["steps"], o["steps"]):
                n += 1
                r = sp["time_s"]["median"] / so["time_s"]["median"]
                ratios.append(r)
                fast += r >= 20
                adi_ok += _mean(so, "adi") <= _mean(sp, "adi")
                mssd_ok += _mean(so, "mssd") <= _mean(sp, "mssd")
                rec_ok += so["recall_mssd"] >= goal
                rec_sym_ok += so["recall_mssd_mod_base_sym"] >= goal
                recall.append(so["recall_mssd"])
        print(f"  {label:<5}: {n} rows; speed-up {min(ratios):.1f}-{max(ratios):.1f}x, median {np.median(ratios):.1f}x, "
              f"{fast}/{n} rows >= 20x; ADI no worse in {adi_ok}/{n}, MSSD no worse in {mssd_ok}/{n}; "
              f"recall mean {np.mean(recall):.2f}, goal met in {rec_ok}/{n} rows ({rec_sym_ok}/{n} modulo the base's symmetries)")


def _mean(step: dict, key: str) -> float:
    """The step's mean of a metric; infinite when no frame returned a pose."""
    v = step[key]["mean"]
    return float("inf") if v is None else v


def _get(st, *keys, scale=1.0, fmt="{:.3f}") -> str:
    if st is None:
        return "-"
    v = st
    for key in keys:
        v = v[key]
    return "-" if v is None else fmt.format(v * scale)


def print_rows(name, noise, base_pose, p, o) -> None:
    """One table row per step: the paper's evaluation `p` beside ours `o`."""
    g = _get
    for i, st in enumerate((o or p)["steps"]):
        sp = p["steps"][i] if p else None
        so = o["steps"][i] if o else None
        ratio = (sp["time_s"]["median"] / so["time_s"]["median"]) if (sp and so) else float("nan")
        print(f"{name:<18} {noise:<9} {base_pose:<5} {st['step']:>4} | {g(sp, 'time_s', 'median'):>8} "
              f"{g(so, 'time_s', 'median'):>7} {ratio:>6.1f} | {g(sp, 'adi', 'mean', scale=1000, fmt='{:.2f}'):>6} "
              f"{g(so, 'adi', 'mean', scale=1000, fmt='{:.2f}'):>6} {g(sp, 'mssd', 'mean', scale=1000, fmt='{:.2f}'):>7} "
              f"{g(so, 'mssd', 'mean', scale=1000, fmt='{:.2f}'):>7} | {g(sp, 'recall_mssd', fmt='{:.2f}'):>5} "
              f"{g(so, 'recall_mssd', fmt='{:.2f}'):>5} {g(sp, 'recall_mssd_mod_base_sym', fmt='{:.2f}'):>6} "
              f"{g(so, 'recall_mssd_mod_base_sym', fmt='{:.2f}'):>6}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
