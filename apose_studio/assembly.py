"""Assembly files, format 1 (`docs/ASSEMBLY_FORMAT.md` in shared): load with validation, save, chain poses.

Everything here is in metres; the file's `units` is applied at load and undone at save.
Steps are numbered from 1 for people (CLI, JSON) and indexed from 0 in key paths, as the format says.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from . import se3
from .config import (CameraIntrinsics, RegistrationConfig, camera_from_dict, camera_to_dict, is_number,
                     registration_from_dict, registration_to_dict)
from .errors import AssemblyError, Problem
from .fileio import atomic_write_text, parse_yaml, roundtrip_yaml
from .units import UNIT_TO_M

FORMAT = "apose-assembly/1"
_TOP_KEYS = ("format", "name", "units", "parts", "steps", "camera", "registration")
_PART_KEYS = ("mesh", "color", "symmetry")
_SYM_KEYS = ("axis", "origin", "order")
_STEP_KEYS = ("part", "base", "pose_in_base")
_POSE_KEYS = ("translation", "rotation")
PART_ID = re.compile(r"[A-Za-z0-9_.\-]{1,64}")  # shown in pages and file names: nothing that could be markup
PART_ID_RULE = "1 to 64 letters, digits, '_', '-' or '.'"
MAX_PARTS = 2000  # far beyond any real assembly; bounds what a hostile file can cost
MAX_STEPS = 2000
MAX_SYMMETRY_ORDER = 360
MAX_FILE_BYTES = 5 * 2**20


@dataclass(frozen=True)
class Symmetry:
    """Rotational symmetry about `axis` through `origin` (metres) in the part frame; order 0 = continuous."""

    axis: tuple[float, float, float]
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    order: int = 0


@dataclass(frozen=True)
class Part:
    id: str
    mesh: Path  # absolute, resolved against the assembly file's folder
    color: tuple[float, float, float] | None = None
    symmetry: Symmetry | None = None


@dataclass(frozen=True, eq=False)
class Step:
    """Place `part` on `base`; `T_base_part` (4x4, metres) is its pose in the frame of base[0]."""

    part: str
    base: tuple[str, ...]
    T_base_part: np.ndarray

    def __eq__(self, other) -> bool:
        return (isinstance(other, Step) and self.part == other.part and self.base == other.base
                and np.allclose(self.T_base_part, other.T_base_part, rtol=0, atol=1e-12))


@dataclass(frozen=True)
class StepView:
    """What the estimator needs for one step: the base object, the part to place and where it goes."""

    number: int  # 1-based
    part: str
    base: tuple[str, ...]
    root: str  # the root part the base hangs off
    T_base_part: np.ndarray
    T_base_members: dict[str, np.ndarray]  # pose of each base part in the frame of base[0]


@dataclass(frozen=True)
class Assembly:
    name: str
    units: str
    parts: dict[str, Part]
    steps: tuple[Step, ...]
    camera: CameraIntrinsics | None = None
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    path: Path | None = field(default=None, compare=False)  # the file it was loaded from

    @property
    def unit_scale(self) -> float:
        """Metres per file unit."""
        return UNIT_TO_M[self.units]

    @property
    def roots(self) -> tuple[str, ...]:
        placed = {s.part for s in self.steps}
        return tuple(p for p in self.parts if p not in placed)

    @cached_property
    def _chain(self) -> dict[str, tuple[str, np.ndarray]]:
        """(root, T_root_part) of every part, each chain walked once (linear in the number of steps).
        A draft whose steps form a cycle (which validation reports) treats the part closing it as a root."""
        placing = {s.part: s for s in self.steps}
        out: dict[str, tuple[str, np.ndarray]] = {}
        for start in list(self.parts) + list(placing):
            path, p = [], start
            while p in placing and p not in out and p not in path:
                path.append(p)
                p = placing[p].base[0]
            if p not in out:
                out[p] = (p, np.eye(4))  # a root (or the part closing a cycle)
            root, T = out[p]
            for q in reversed(path):
                if q not in out:
                    T = T @ placing[q].T_base_part
                    out[q] = (root, T)
        return out

    def root_of(self, part_id: str) -> str:
        return self._chain[part_id][0] if part_id in self._chain else part_id

    def T_root_part(self, part_id: str) -> np.ndarray:
        """Pose of a part in the frame of its root, by chaining the steps that place it."""
        return self._chain[part_id][1].copy() if part_id in self._chain else np.eye(4)

    def step_view(self, number: int) -> StepView:
        """Derived view of step `number` (1-based)."""
        if not 1 <= number <= len(self.steps):
            raise IndexError(f"step {number} does not exist; {self.name} has steps 1..{len(self.steps)}")
        step = self.steps[number - 1]
        T_root_base = self.T_root_part(step.base[0])
        T_base_root = se3.inv(T_root_base)
        members = {p: T_base_root @ self.T_root_part(p) for p in step.base}
        return StepView(number, step.part, step.base, self.root_of(step.base[0]), step.T_base_part, members)

    def completed(self) -> dict[str, dict[str, np.ndarray]]:
        """The finished assembly: for each root, every part hanging off it with its T_root_part."""
        out: dict[str, dict[str, np.ndarray]] = {r: {} for r in self.roots}
        for p in self.parts:
            out[self.root_of(p)][p] = self.T_root_part(p)
        return out

    def with_steps(self, steps) -> "Assembly":
        return replace(self, steps=tuple(steps))


# --------------------------------------------------------------------------------------------- load


class _Checker:
    """Collects problems while walking the YAML tree."""

    def __init__(self, file: str):
        self.file = file
        self.problems: list[Problem] = []

    def add(self, key: str, what: str) -> None:
        self.problems.append(Problem(self.file, key, what))

    def mapping(self, value, key: str, allowed: tuple[str, ...], what: str) -> dict | None:
        if not isinstance(value, dict):
            self.add(key, f"expected {what}, got {_kind(value)}")
            return None
        for k in value:
            if k not in allowed:
                self.add(f"{key}.{k}" if key else str(k), f"unknown key; expected one of {', '.join(allowed)}")
        return value

    def numbers(self, value, key: str, n: int, what: str = "numbers") -> list[float] | None:
        if not isinstance(value, list):
            self.add(key, f"expected a list of {n} {what}, got {_kind(value)}")
            return None
        if len(value) != n:
            self.add(key, f"expected {n} {what}, got {len(value)}")
            return None
        bad = [i for i, v in enumerate(value) if not is_number(v)]
        if bad:
            self.add(f"{key}[{bad[0]}]", f"expected a finite number, got {value[bad[0]]!r}")
            return None
        return [float(v) for v in value]


def _kind(value) -> str:
    """What a value is, for a message; text is quoted only when short (an error never echoes a file)."""
    if value is None:
        return "nothing"
    if isinstance(value, str):
        return f"the text {value!r}" if len(value) <= 40 and "\n" not in value else f"a text of {len(value)} characters"
    if isinstance(value, (dict, list)):
        return {dict: "a mapping", list: "a list"}[type(value)]
    if isinstance(value, bool) or isinstance(value, (int, float)):
        return f"{value}"
    return type(value).__name__


def _rotation(c: _Checker, value, key: str) -> np.ndarray | None:
    forms = "one of {quat_wxyz: [w, x, y, z]}, {euler_deg: [a, b, c], order: xyz}, {matrix: 3x3}"
    if value is None:
        return np.eye(3)
    if not isinstance(value, dict):
        c.add(key, f"expected {forms}, got {_kind(value)}")
        return None
    kinds = [k for k in ("quat_wxyz", "euler_deg", "matrix") if k in value]
    extra = [k for k in value if k not in ("quat_wxyz", "euler_deg", "matrix", "order")]
    if extra or len(kinds) != 1:
        c.add(f"{key}.{extra[0]}" if extra else key, f"expected {forms}")
        return None
    kind = kinds[0]
    if "order" in value and kind != "euler_deg":
        c.add(f"{key}.order", "only euler_deg takes an order")
        return None
    if kind == "quat_wxyz":
        q = c.numbers(value["quat_wxyz"], f"{key}.quat_wxyz", 4)
        if q is None:
            return None
        n = float(np.linalg.norm(q))
        if n < 1e-9:
            c.add(f"{key}.quat_wxyz", "expected a non-zero quaternion [w, x, y, z], got all zeros")
            return None
        return se3.quat_wxyz_to_matrix(q)
    if kind == "euler_deg":
        a = c.numbers(value["euler_deg"], f"{key}.euler_deg", 3)
        order = value.get("order", "xyz")
        if not (isinstance(order, str) and len(order) == 3 and (set(order) <= set("xyz") or set(order) <= set("XYZ"))
                and order[0] != order[1] and order[1] != order[2]):
            c.add(f"{key}.order", f"expected a scipy axis order such as xyz (extrinsic) or XYZ (intrinsic), got {order!r}")
            return None
        return None if a is None else se3.euler_deg_to_matrix(a, order)
    m = value["matrix"]
    if not (isinstance(m, list) and len(m) == 3 and all(isinstance(r, list) and len(r) == 3 for r in m)):
        c.add(f"{key}.matrix", "expected a 3x3 list of rows")
        return None
    rows = [c.numbers(r, f"{key}.matrix[{i}]", 3) for i, r in enumerate(m)]
    if any(r is None for r in rows):
        return None
    R = np.array(rows)
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
        c.add(f"{key}.matrix", "expected a rotation matrix (orthonormal, determinant +1)")
        return None
    return R


def _parse_parts(c: _Checker, parts_raw, folder: Path, scale: float) -> dict[str, Part]:
    parts: dict[str, Part] = {}
    if not isinstance(parts_raw, dict) or not parts_raw:
        got = "an empty mapping (no parts yet)" if isinstance(parts_raw, dict) else _kind(parts_raw)
        c.add("parts", f"expected a mapping of part ids to {{mesh: path}}, got {got}")
        return parts
    if len(parts_raw) > MAX_PARTS:
        c.add("parts", f"{len(parts_raw)} parts; at most {MAX_PARTS} are supported")
        return parts
    for pid, spec in parts_raw.items():
        key = f"parts.{pid}"
        if not isinstance(pid, str) or not PART_ID.fullmatch(pid):
            c.add(f"parts.{_kind(pid)}" if not isinstance(pid, str) or len(pid) > 40 else key,
                  f"a part id is {PART_ID_RULE}; rename it (and where steps use it)")
            continue
        spec = c.mapping(spec, key, _PART_KEYS, "a mapping with mesh (and optional color, symmetry)")
        if spec is None:
            continue
        mesh = spec.get("mesh")
        if not isinstance(mesh, str) or not mesh:
            c.add(f"{key}.mesh", f"expected a path to a mesh file, got {_kind(mesh)}")
            continue
        mesh_path = (folder / mesh).resolve()
        if not mesh_path.is_file():
            from .fileio import describe_path

            c.add(f"{key}.mesh", f"{mesh_path}: {describe_path(mesh_path, 'a mesh file')}")
        color = None
        if spec.get("color") is not None:
            rgb = c.numbers(spec["color"], f"{key}.color", 3, "numbers in 0..1")
            if rgb is not None and not all(0 <= v <= 1 for v in rgb):
                c.add(f"{key}.color", f"expected 3 numbers in 0..1, got {spec['color']}")
            elif rgb is not None:
                color = tuple(rgb)
        symmetry = None
        if spec.get("symmetry") is not None:
            symmetry = _parse_symmetry(c, spec["symmetry"], f"{key}.symmetry", scale)
        parts[pid] = Part(pid, mesh_path, color, symmetry)
    return parts


def _parse_symmetry(c: _Checker, raw, key: str, scale: float) -> Symmetry | None:
    sym = c.mapping(raw, key, _SYM_KEYS, "{axis: [x, y, z], order: n, origin: [x, y, z]}")
    if sym is None:
        return None
    axis = c.numbers(sym.get("axis"), f"{key}.axis", 3)
    origin = c.numbers(sym.get("origin", [0, 0, 0]), f"{key}.origin", 3)
    order = sym.get("order")
    if not (isinstance(order, int) and not isinstance(order, bool) and 0 <= order <= MAX_SYMMETRY_ORDER
            and order != 1):
        c.add(f"{key}.order", f"expected 0 (continuous) or a whole number n from 2 to {MAX_SYMMETRY_ORDER} (n-fold), "
              f"got {_kind(order)}")
        return None
    if axis is None or origin is None:
        return None
    if np.linalg.norm(axis) < 1e-9:
        c.add(f"{key}.axis", "expected a non-zero direction")
        return None
    a = np.asarray(axis) / np.linalg.norm(axis)
    return Symmetry(tuple(float(x) for x in a), tuple(float(x) * scale for x in origin), order)


def _parse_steps(c: _Checker, steps_raw, parts: dict[str, Part], scale: float) -> list[Step]:
    steps: list[Step] = []
    if not isinstance(steps_raw, list):
        c.add("steps", f"expected a list of steps, got {_kind(steps_raw)}")
        return steps
    if len(steps_raw) > MAX_STEPS:
        c.add("steps", f"{len(steps_raw)} steps; at most {MAX_STEPS} are supported")
        return steps
    placed_by: dict[str, int] = {}
    for i, raw in enumerate(steps_raw):
        key = f"steps[{i}]"
        raw = c.mapping(raw, key, _STEP_KEYS, "a mapping with part, base, pose_in_base")
        if raw is None:
            continue
        n_before = len(c.problems)
        part = raw.get("part")
        if not isinstance(part, str):
            c.add(f"{key}.part", f"expected a part id, got {_kind(part)}")
        elif part not in parts:
            c.add(f"{key}.part", f"unknown part {part!r}; parts are {', '.join(parts)}")
        elif part in placed_by:
            c.add(f"{key}.part", f"{part!r} is already placed by steps[{placed_by[part]}]; a part is placed at most once")
        base = raw.get("base")
        if not (isinstance(base, list) and base and all(isinstance(b, str) for b in base)):
            c.add(f"{key}.base", f"expected a non-empty list of part ids, got {_kind(base)}")
            base = None
        else:
            for j, b in enumerate(base):
                if b not in parts:
                    c.add(f"{key}.base[{j}]", f"unknown part {b!r}; parts are {', '.join(parts)}")
                elif b == part:
                    c.add(f"{key}.base[{j}]", f"{b!r} cannot be part of its own base")
                elif base.index(b) != j:
                    c.add(f"{key}.base[{j}]", f"{b!r} is listed twice")
        pose = raw.get("pose_in_base")
        T = None
        if c.mapping(pose, f"{key}.pose_in_base", _POSE_KEYS, "a mapping with translation (and optional rotation)") is not None:
            t = c.numbers(pose.get("translation"), f"{key}.pose_in_base.translation", 3)
            R = _rotation(c, pose.get("rotation"), f"{key}.pose_in_base.rotation")
            if t is not None and R is not None:
                T = se3.make_T(R, np.asarray(t) * scale)
        if len(c.problems) == n_before and T is not None:
            steps.append(Step(part, tuple(base), T))
            placed_by[part] = i
        elif isinstance(part, str):
            placed_by.setdefault(part, i)
    return steps


def _check_order(c: _Checker, steps: list[Step], parts: dict[str, Part]) -> None:
    """Base parts must be roots or placed earlier, and all of one step's base must share a root."""
    placed_later = {s.part: i for i, s in enumerate(steps)}
    placed_so_far: dict[str, str] = {}  # part -> base[0] it was placed on
    for i, s in enumerate(steps):
        for j, b in enumerate(s.base):
            if b in placed_later and b not in placed_so_far:
                c.add(f"steps[{i}].base[{j}]", f"{b!r} is placed only by a later step (steps[{placed_later[b]}]); "
                      "move that step before this one")
        roots = set()
        for b in s.base:
            r = b
            while r in placed_so_far:
                r = placed_so_far[r]
            roots.add(r)
        if len(roots) > 1:
            c.add(f"steps[{i}].base", f"base parts hang off different roots ({', '.join(sorted(roots))}); "
                  "a base object must be one connected sub-assembly")
        placed_so_far[s.part] = s.base[0]


def assembly_from_dict(data, file: str | Path, folder: Path | None = None) -> Assembly:
    """Validate a parsed YAML mapping; raises AssemblyError with every problem found."""
    file = str(file)
    folder = Path(folder) if folder is not None else Path(file).resolve().parent
    c = _Checker(file)
    data = c.mapping(data, "", _TOP_KEYS, "a mapping with format, name, units, parts, steps")
    if data is None:
        raise AssemblyError(c.problems)
    if data.get("format") != FORMAT:
        c.add("format", f"expected {FORMAT!r}, got {_kind(data.get('format'))}")
    name = data.get("name")
    if not isinstance(name, str) or not name.strip():
        c.add("name", f"expected a name, got {_kind(name)}")
    units = data.get("units")
    if units not in UNIT_TO_M:
        c.add("units", f"expected one of {', '.join(UNIT_TO_M)}, got {_kind(units)}")
        units = "m"
    scale = UNIT_TO_M[units]
    parts = _parse_parts(c, data.get("parts"), folder, scale)
    steps = _parse_steps(c, data.get("steps"), parts, scale)
    if not c.problems:
        _check_order(c, steps, parts)
    camera, cam_problems = camera_from_dict(data.get("camera"), file)
    registration, reg_problems = registration_from_dict(data.get("registration"), file)
    c.problems += cam_problems + reg_problems
    if c.problems:
        raise AssemblyError(c.problems)
    return Assembly(name, units, parts, tuple(steps), camera, registration, Path(file).resolve())


def load_assembly(path: str | Path) -> Assembly:
    """Read and validate an assembly file; raises AssemblyError naming file, key path and expectation."""
    from .fileio import describe_path

    path = Path(path)
    if not path.is_file():
        raise AssemblyError([Problem(str(path), "", describe_path(path, "an assembly file (.yaml)"))])
    if path.stat().st_size > MAX_FILE_BYTES:
        raise AssemblyError([Problem(str(path), "", f"{path.stat().st_size / 2**20:.0f} MB is far too large for an "
                                     f"assembly file (at most {MAX_FILE_BYTES // 2**20} MB); is this the right file?")])
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise AssemblyError([Problem(str(path), "", "not a text file (an assembly file is YAML text)")]) from None
    except OSError as e:
        raise AssemblyError([Problem(str(path), "", f"cannot be read ({e.strerror})")]) from None
    return assembly_from_dict(parse_yaml(text, str(path)), path)


# --------------------------------------------------------------------------------------------- save


def _num(x: float) -> float | int:
    """Round-off noise away (1e-12 of a unit) so saved files stay readable; ints stay ints."""
    r = round(float(x), 12)
    return int(r) if r == int(r) and abs(r) < 1e15 else r


def assembly_to_dict(asm: Assembly, folder: Path) -> dict:
    """The YAML mapping of an assembly, with mesh paths relative to `folder` where possible."""
    s = asm.unit_scale
    parts = {}
    for pid, p in asm.parts.items():
        # relative when the mesh sits under the file's folder (the pair can move together), else absolute
        mesh = os.path.relpath(p.mesh, folder) if p.mesh.is_relative_to(folder) else str(p.mesh)
        spec: dict = {"mesh": Path(mesh).as_posix()}
        if p.color is not None:
            spec["color"] = [_num(v) for v in p.color]
        if p.symmetry is not None:
            sym = {"axis": [_num(v) for v in p.symmetry.axis], "order": p.symmetry.order}
            if any(p.symmetry.origin):
                sym["origin"] = [_num(v / s) for v in p.symmetry.origin]
            spec["symmetry"] = sym
        parts[pid] = spec
    steps = []
    for st in asm.steps:
        q = se3.matrix_to_quat_wxyz(st.T_base_part[:3, :3])
        steps.append({"part": st.part, "base": list(st.base), "pose_in_base": {
            "translation": [_num(v / s) for v in st.T_base_part[:3, 3]],
            "rotation": {"quat_wxyz": [float(v) for v in q]}}})
    out = {"format": FORMAT, "name": asm.name, "units": asm.units, "parts": parts, "steps": steps}
    if asm.camera is not None:
        out["camera"] = camera_to_dict(asm.camera)
    registration = registration_to_dict(asm.registration)
    if registration:  # defaults are not written
        out["registration"] = registration
    return out


def dump_assembly(asm: Assembly, folder: Path) -> str:
    """The YAML text of an assembly as a new file (mesh paths relative to `folder` where possible)."""
    return roundtrip_yaml(None, assembly_to_dict(asm, folder))


def _same_pose(path: tuple, old, new) -> bool:
    """A step's pose written another way (Euler angles, a matrix, another unit's rounding) but equal
    to what would be written now: keep the user's way of writing it."""
    if len(path) != 3 or path[0] != "steps" or path[2] != "pose_in_base" or not isinstance(old, dict):
        return False
    c = _Checker("")
    t_old = c.numbers(old.get("translation"), "", 3)
    R_old = _rotation(c, old.get("rotation"), "")
    if c.problems or t_old is None or R_old is None:
        return False
    R_new = se3.quat_wxyz_to_matrix(new["rotation"]["quat_wxyz"])
    return np.allclose(t_old, new["translation"], rtol=0, atol=1e-9) and np.allclose(R_old, R_new, rtol=0, atol=1e-9)


def save_assembly(asm: Assembly, path: str | Path, backup: bool = False) -> Path:
    """Save atomically as YAML; mesh paths are written relative to the file's folder.

    Re-saving a hand-written file keeps its comments, key order and the way unchanged values are
    written (round-trip YAML); the file keeps its mode. With `backup`, the previous version is kept
    as NAME.yaml.bak."""
    path = Path(path).resolve()
    previous = None
    if path.is_file():
        try:
            previous = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            previous = None
    text = roundtrip_yaml(previous, assembly_to_dict(asm, path.parent), keep=_same_pose)
    atomic_write_text(path, text, backup=backup and previous is not None)
    return path
