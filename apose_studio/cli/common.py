"""What the command line's commands share: the estimator's flags and the Params they ask for, output
path checks, printing poses, and what may reach the terminal (control characters escaped, long values
shortened)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.masks.prompt import parse_box, parse_point
from apose_studio.params import FIELDS, PRESETS, Params, parse_param, resolve_params
from apose_studio.safeio import escaped


def estimator_args(p: argparse.ArgumentParser, mask_default: str | None = "gt", per_frame: bool = True) -> None:
    """--preset, --mask, --orientation-prior, --upright and --param: every estimating command's flags
    (`per_frame` False: no --mask and --orientation-prior, for `apose serve`, whose requests carry their own)."""
    p.add_argument("--preset", default="default", choices=list(PRESETS), help="estimator settings (default: ours)")
    if per_frame:
        p.add_argument("--mask", default=mask_default, metavar="gt|depth|box|MODEL.pt|MASK.png",
                       help="the base object's mask: gt (the data's ground truth; the default where there is one), depth "
                       "(table-plane removal and 3D clustering, no training; the default for captures), box (eval: the "
                       "prompted mask from the ground truth's visible box, as a detector would give), a model from "
                       "`apose train-seg`, or a mask image")
        p.add_argument("--orientation-prior", action="store_true",
                       help="take the CAD's orientation as the base's orientation in the world (true for --base-pose fixed "
                       "renders)")
    p.add_argument("--upright", action=argparse.BooleanOptionalAction, default=None,
                   help="where a table is seen, first search the yaw of the base standing on it as modelled (its CAD "
                   "z axis along the table's normal), then freely if that fits poorly: on by default in the default "
                   "preset; --no-upright searches freely from the start")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="set one estimator parameter over the preset and the assembly file (repeatable), e.g. "
                   f"--param max_seconds=0; the names are those of a `registration:` section ({len(FIELDS) - 1} in "
                   "all, listed in docs/ASSEMBLY_FILES.md)")


def params_of(args, registration) -> Params:
    """The Params a command runs with: --preset, then the assembly file's `registration` section, then
    --upright and each --param (the later flag wins)."""
    return resolve_params(args.preset, registration, **param_overrides(args))


def param_overrides(args) -> dict:
    """--upright and each --param as overrides of the preset (checked: a bad name or value raises)."""
    over: dict = {}
    if args.upright is not None:
        if args.preset == "paper" and args.upright:
            raise AposeError("--upright is a search of ours; the paper preset has no such mode (use --preset default)")
        over["upright"] = args.upright
    for text in getattr(args, "param", None) or []:
        name, value = parse_param(text)
        if name == "preset":
            raise AposeError("--param preset=...: use --preset")
        over[name] = value
    return over


def failed_exit(result) -> int:
    """`apose estimate`'s exit code for a result that is not ok: 2 where the input is wrong (units 10x off, a mask of
    the whole scene: RegistrationResult.input_error), as for any bad input; 1 where the estimate failed."""
    return 2 if result.input_error else 1


def failed_words(result) -> str:
    """What a result that is not ok is called before its reason: bad input refused (exit 2), or a failed estimate."""
    return "refused, bad input" if result.input_error else "estimation failed"


def finite(x: float) -> float | None:
    """JSON has no NaN: an unknown number is null."""
    return float(x) if np.isfinite(x) else None


def check_output_file(path: Path, flag: str, inputs=()) -> None:
    """Refuse an output path that cannot take a file, or that would replace a file of an input folder
    (`apose eval --json DS/dataset_info.json` would leave the dataset unreadable), before any long work.
    `inputs`: the input paths (one path alone is taken as one, not as its characters)."""
    for folder in [inputs] if isinstance(inputs, (str, Path)) else inputs:
        folder = Path(folder).resolve()
        target = path.resolve()
        if target.exists() and (target == folder or target.is_relative_to(folder)):
            raise AposeError(f"{flag} {path}: a file of the input {folder}, which this would replace; write the "
                             "output elsewhere (or under a new name)")
    if path.is_dir():
        raise AposeError(f"{flag} {path}: a folder; give a file name (e.g. {path / 'out.json'})")
    if not path.parent.is_dir():
        raise AposeError(f"{flag} {path}: folder {path.parent} does not exist")


def pose_lines(T: np.ndarray) -> list[str]:
    """A 4x4 pose as people read it: the matrix with its translation in mm, xyz and the quaternion."""
    q = se3.matrix_to_quat_wxyz(T[:3, :3])
    M = T.copy()
    M[:3, 3] *= 1000.0  # people read millimetres; --json keeps metres
    rows = [" ".join(f"{v:+10.4f}" for v in row) for row in M]
    return [f"  [{r}]   (translation in mm)" if i == 0 else f"  [{r}]" for i, r in enumerate(rows)] + [
        f"  xyz (mm)    = ({M[0, 3]:+.2f}, {M[1, 3]:+.2f}, {M[2, 3]:+.2f})",
        f"  q (w,x,y,z) = ({q[0]:+.5f}, {q[1]:+.5f}, {q[2]:+.5f}, {q[3]:+.5f})"]


def parse_prompt(args, flag: str, k: int | None = None, views: int = 1):
    """--box / --point as pixels: given at most once for one view, or once per view (the k-th of `views`)."""
    given = getattr(args, flag) or []
    if k is None and len(given) > 1:
        raise AposeError(f"--{flag} given {len(given)} times for one view; give it once")
    if k is not None and given and len(given) != views:
        raise AposeError(f"--{flag} given {len(given)} time(s) for {views} views: give it once per view, "
                         "in the order of the views")
    text = given[k or 0] if given else None
    return None if text is None else (parse_box(text) if flag == "box" else parse_point(text))


# --------------------------------------------------------------------------------------- the terminal

# Every control and invisible character (text.unsafe_char's set: ESC sequences, bidi overrides, line
# separators, zero-width and tag characters) is printed as an escape; newlines, tabs and the progress
# bars' \r pass, because the CLI writes them itself (names and paths that hold them are refused where
# they are read).


def printable(text: str) -> str:
    """`text` with every control or invisible character shown as an escape (\\x1b, \\u202e)."""
    return escaped(text, allow="\t\n\r")


class Printable:
    """A text stream (stdout, stderr) that escapes control characters in everything written through it
    (`printable`): a part or file name holding ESC sequences or a bidi override cannot retitle or clear
    the user's terminal, nor reorder what it shows."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        return self._stream.write(printable(text))

    def __getattr__(self, name):
        return getattr(self._stream, name)
