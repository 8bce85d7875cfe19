"""Grasps and the gripper in an assembly file (`ASSEMBLY_FORMAT.md`, "Optional part keys: grasps, and the
gripper"): how the robot's gripper holds a part, parsed with key paths and written back.

A grasp is `T_part_gripper`: the gripper's TCP frame in the part's frame (z out of the gripper towards the
part, y the jaws' closing direction, the origin between the finger tips). Metres inside; the file's
units at load and save.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apose_studio.assembly.fileio import describe_path
from apose_studio.assembly.fileio import yaml_number as _num
from apose_studio.assembly.yamlcheck import Checker, kind, rotation
from apose_studio.geometry import se3
from apose_studio.geometry.units import MAX_COORDINATE_M, unit_name

GRASP_KEYS = ("name", "pose_in_part", "width")
GRIPPER_KEYS = ("type", "max_width", "finger_length", "mesh")
GRIPPER_TYPES = ("parallel", "mesh")
MAX_GRASPS = 64  # per part
MAX_GRIPPER_M = 2.0  # no parallel-jaw gripper opens (or has fingers) wider than this


@dataclass(frozen=True, eq=False)
class Grasp:
    """A named way to hold a part: the gripper's TCP frame in the part's frame, and the finger opening (m)."""

    name: str
    T_part_gripper: np.ndarray
    width: float | None = None

    def __eq__(self, other) -> bool:
        return (isinstance(other, Grasp) and self.name == other.name and self.width == other.width
                and np.allclose(self.T_part_gripper, other.T_part_gripper, rtol=0, atol=1e-12))


@dataclass(frozen=True)
class Gripper:
    """The end effector, for drawing and checks: a parallel-jaw gripper (metres) or a mesh in the TCP frame."""

    type: str = "parallel"
    max_width: float | None = None
    finger_length: float | None = None
    mesh: Path | None = None


def parse_grasps(c: Checker, raw, key: str, scale: float) -> tuple[Grasp, ...]:
    """A part's `grasps` list; problems are added to `c` with their key paths."""
    if not isinstance(raw, list) or not raw:
        c.add(key, f"expected a list of grasps ({{name, pose_in_part, width}}), got {kind(raw)}")
        return ()
    if len(raw) > MAX_GRASPS:
        c.add(key, f"{len(raw)} grasps; at most {MAX_GRASPS} per part")
        return ()
    out: list[Grasp] = []
    seen: dict[str, int] = {}
    for i, g in enumerate(raw):
        k = f"{key}[{i}]"
        g = c.mapping(g, k, GRASP_KEYS, "a grasp {name, pose_in_part, width}")
        if g is None:
            continue
        name = g.get("name")
        if not (isinstance(name, str) and name.strip() and len(name) <= 64 and name.isprintable()):
            c.add(f"{k}.name", f"expected a name (1 to 64 printable characters), got {kind(name)}")
            continue
        if name in seen:
            c.add(f"{k}.name", f"{name!r} is also the name of {key}[{seen[name]}]; grasp names are unique within a part")
            continue
        seen[name] = i
        pose = c.mapping(g.get("pose_in_part"), f"{k}.pose_in_part", ("translation", "rotation"),
                         "a mapping with translation (and optional rotation): T_part_gripper")
        if pose is None:
            continue
        t = c.numbers(pose.get("translation"), f"{k}.pose_in_part.translation", 3, limit=MAX_COORDINATE_M / scale,
                      unit=f" {unit_name(scale)}")
        R = rotation(c, pose.get("rotation"), f"{k}.pose_in_part.rotation")
        width = None
        if g.get("width") is not None:
            w = c.numbers([g["width"]], f"{k}.width", 1, "number")
            if w is not None and not 0 < w[0] * scale <= MAX_GRIPPER_M:
                c.add(f"{k}.width", f"expected a finger opening above 0 and at most {MAX_GRIPPER_M / scale:g} "
                      f"{unit_name(scale)}, got {w[0]:g}")
            elif w is not None:
                width = w[0] * scale
        if t is not None and R is not None:
            out.append(Grasp(name, se3.make_T(R, np.asarray(t) * scale), width))
    return tuple(out)


def parse_gripper(c: Checker, raw, folder: Path, scale: float) -> Gripper | None:
    """The top-level `gripper`; problems are added to `c` with their key paths."""
    g = c.mapping(raw, "gripper", GRIPPER_KEYS, "a mapping {type, max_width, finger_length, mesh}")
    if g is None:
        return None
    typ = g.get("type", "parallel")
    if typ not in GRIPPER_TYPES:
        c.add("gripper.type", f"expected one of {', '.join(GRIPPER_TYPES)}, got {kind(typ)}")
        return None
    lengths = {}
    for name in ("max_width", "finger_length"):
        if g.get(name) is None:
            continue
        v = c.numbers([g[name]], f"gripper.{name}", 1, "number")
        if v is not None and not 0 < v[0] * scale <= MAX_GRIPPER_M:
            c.add(f"gripper.{name}", f"expected a length above 0 and at most {MAX_GRIPPER_M / scale:g} {unit_name(scale)}, "
                  f"got {v[0]:g}")
        elif v is not None:
            lengths[name] = v[0] * scale
    mesh = None
    if typ == "mesh":
        m = g.get("mesh")
        if not isinstance(m, str) or not m:
            c.add("gripper.mesh", f"type: mesh needs the path of the gripper's mesh (in the TCP frame), got {kind(m)}")
            return None
        mesh = (folder / m).resolve()
        if not mesh.is_file():
            c.add("gripper.mesh", f"{mesh}: {describe_path(mesh, 'a mesh file')}")
    elif g.get("mesh") is not None:
        c.add("gripper.mesh", "only type: mesh takes a mesh; write type: mesh, or delete mesh")
    return Gripper(typ, lengths.get("max_width"), lengths.get("finger_length"), mesh)


def check_widths(c: Checker, parts: dict, gripper: Gripper | None) -> None:
    """Every grasp's width within the gripper's max_width (when both are given)."""
    if gripper is None or gripper.max_width is None:
        return
    for pid, part in parts.items():
        for i, g in enumerate(part.grasps):
            if g.width is not None and g.width > gripper.max_width + 1e-12:
                c.add(f"parts.{pid}.grasps[{i}].width", f"{g.width * 1000:g} mm is more than the gripper opens "
                      f"(gripper.max_width {gripper.max_width * 1000:g} mm)")


def grasp_to_dict(g: Grasp, scale: float) -> dict:
    q = se3.matrix_to_quat_wxyz(g.T_part_gripper[:3, :3])
    out: dict = {"name": g.name, "pose_in_part": {"translation": [_num(v / scale) for v in g.T_part_gripper[:3, 3]],
                                                  "rotation": {"quat_wxyz": [float(v) for v in q]}}}
    if g.width is not None:
        out["width"] = _num(g.width / scale)
    return out


def gripper_to_dict(g: Gripper, scale: float, folder: Path) -> dict:
    out: dict = {"type": g.type}
    if g.max_width is not None:
        out["max_width"] = _num(g.max_width / scale)
    if g.finger_length is not None:
        out["finger_length"] = _num(g.finger_length / scale)
    if g.mesh is not None:
        out["mesh"] = Path(os.path.relpath(g.mesh, folder) if g.mesh.is_relative_to(folder) else str(g.mesh)).as_posix()
    return out
