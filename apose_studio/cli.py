"""`apose` command line: a thin shell over the core. Errors become one line each, never a traceback."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from . import __version__, se3
from .errors import AposeError

REPO = Path(__file__).resolve().parent.parent
SAMPLES = REPO / "sample_assemblies"
DEFAULT_SAMPLE = SAMPLES / "helical_gearbox" / "assembly.yaml"


def _fmt_pose(T: np.ndarray, scale_to_mm: float = 1000.0) -> str:
    t = T[:3, 3] * scale_to_mm
    q = se3.matrix_to_quat_wxyz(T[:3, :3])
    ang = se3.rotation_angle_deg(T[:3, :3])
    return (f"t = ({t[0]:+.2f}, {t[1]:+.2f}, {t[2]:+.2f}) mm, "
            f"q_wxyz = ({q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f}), {ang:.1f}° rotation")


def show_json(asm, models) -> dict:
    """The `apose show --json` document (metres, 4x4 lists)."""
    return {
        "name": asm.name,
        "parts": {pid: {"mesh": str(p.mesh), "diameter": models[pid].diameter, "root": asm.root_of(pid),
                        "T_root_part": asm.T_root_part(pid).tolist()} for pid, p in asm.parts.items()},
        "steps": [{"step": i + 1, "part": s.part, "base": list(s.base), "T_base_part": s.T_base_part.tolist()}
                  for i, s in enumerate(asm.steps)],
    }


def show_text(asm, models) -> str:
    lines = [f"{asm.name}  ({asm.path})", f"units in file: {asm.units}", "", "parts:"]
    w = max(len(p) for p in asm.parts)
    for pid, p in asm.parts.items():
        m = models[pid]
        size = " x ".join(f"{v * 1000:.1f}" for v in m.size)
        root = "root" if pid in asm.roots else f"on {asm.root_of(pid)}"
        sym = ""
        if p.symmetry is not None:
            sym = f", {'continuous' if p.symmetry.order == 0 else str(p.symmetry.order) + '-fold'} symmetry"
        lines.append(f"  {pid:<{w}}  {p.mesh.name}  {size} mm, diameter {m.diameter * 1000:.1f} mm, {root}{sym}")
        if m.unit_warning:
            lines.append(f"  {'':<{w}}  warning: {m.unit_warning}")
    lines += ["", "steps:"]
    for i, s in enumerate(asm.steps):
        lines.append(f"  {i + 1}. place {s.part} on [{', '.join(s.base)}]")
        lines.append(f"     pose in {s.base[0]}: {_fmt_pose(s.T_base_part)}")
    lines += ["", "completed assembly (pose of each part in its root's frame):"]
    for root, members in asm.completed().items():
        for pid, T in members.items():
            lines.append(f"  {root} <- {pid:<{w}}  {_fmt_pose(T)}")
    return "\n".join(lines)


def cmd_show(args) -> int:
    from .assembly import load_assembly
    from .mesh import load_parts

    asm = load_assembly(args.assembly)
    models = load_parts(asm)
    if args.json:
        print(json.dumps(show_json(asm, models), indent=2))
    else:
        print(show_text(asm, models))
    return 0


def cmd_demo(args) -> int:
    path = Path(args.assembly) if args.assembly else DEFAULT_SAMPLE
    if not path.is_file():
        raise AposeError(f"{path}: sample assembly not found; run `python sample_assemblies/generate.py` "
                         "in the repository to create it")
    print(f"apose demo: the sample assembly {path.relative_to(REPO) if path.is_relative_to(REPO) else path}\n")
    args.assembly, args.json = path, False
    return cmd_show(args)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="apose", description="6D assembly pose estimation by point-cloud "
                                 "registration, with a browser studio.")
    ap.add_argument("--version", action="version", version=f"apose_studio {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="show debug logging and tracebacks")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("show", help="summarise an assembly file: parts, sizes, steps and poses")
    p.add_argument("assembly", help="assembly YAML file (format apose-assembly/1)")
    p.add_argument("--json", action="store_true", help="print JSON (metres, 4x4 row-major lists)")
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("demo", help="run the main job on the embedded sample assembly")
    p.add_argument("assembly", nargs="?", help="another assembly file instead of the sample")
    p.set_defaults(func=cmd_demo)
    return ap


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return args.func(args)
    except AposeError as e:
        for line in str(e).splitlines():
            print(f"error: {line}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a bug: one line, plus the traceback with --verbose
        if args.verbose:
            raise
        print(f"error: unexpected {type(e).__name__}: {e} (run with -v for the traceback, and please report it)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
