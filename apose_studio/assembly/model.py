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

from apose_studio import safeio
from apose_studio.assembly import mates as mt
from apose_studio.assembly.fileio import atomic_write_text, describe_path, parse_yaml, roundtrip_yaml
from apose_studio.assembly.fileio import yaml_number as _num
from apose_studio.assembly.grasps import Grasp, Gripper, check_widths, grasp_to_dict, gripper_to_dict, parse_grasps, parse_gripper
from apose_studio.assembly.mates import Approach, Mate, MateError, approach_to_dict, mate_to_dict, parse_approach, parse_mates
from apose_studio.assembly.roi import Roi, parse_roi, roi_to_dict
from apose_studio.assembly.yamlcheck import Checker, kind, rotation
from apose_studio.errors import AposeError, AssemblyError, Problem
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics, camera_from_dict, camera_to_dict
from apose_studio.geometry.units import MAX_COORDINATE_M, UNIT_TO_M, unit_name
from apose_studio.params import RegistrationConfig, registration_from_dict, registration_to_dict

FORMAT = "apose-assembly/1"
_TOP_KEYS = ("format", "name", "units", "parts", "steps", "camera", "registration", "gripper")
_PART_KEYS = ("mesh", "solid", "color", "symmetry", "grasps", "roi")
_SYM_KEYS = ("axis", "origin", "order")
_STEP_KEYS = ("part", "base", "pose_in_base", "mates", "approach")
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
    solid: str | None = None  # the named solid of a STEP file with several (None: the whole file)
    grasps: tuple[Grasp, ...] = ()  # how the gripper holds it (assembly/grasps.py); the first is the default
    roi: Roi | None = None  # as a base, only this region of the mesh is registered (assembly/roi.py)


@dataclass(frozen=True, eq=False)
class Step:
    """Place `part` on `base`; `T_base_part` (4x4, metres) is its pose in the frame of base[0]."""

    part: str
    base: tuple[str, ...]
    T_base_part: np.ndarray
    mates: tuple[Mate, ...] = ()  # when given, T_base_part is their solution (`mates.solve`)
    approach: Approach | None = None
    free: tuple[str, ...] = ()  # the degrees of freedom the mates leave free, in words (derived at load)

    def __eq__(self, other) -> bool:
        return (isinstance(other, Step) and self.part == other.part and self.base == other.base
                and np.allclose(self.T_base_part, other.T_base_part, rtol=0, atol=1e-12)
                and self.mates == other.mates and self.approach == other.approach)


@dataclass(frozen=True)
class StepView:
    """What the estimator needs for one step: the base object, the part to place and where it goes."""

    number: int  # 1-based
    part: str
    base: tuple[str, ...]
    root: str  # the root part the base hangs off
    T_base_part: np.ndarray
    T_base_members: dict[str, np.ndarray]  # pose of each base part in the frame of base[0]
    approach: Approach | None = None  # the part's last straight motion into place, in base[0]'s frame
    twins: tuple[str, ...] = ()  # the other instances of a one-part root base: roots with the same mesh (e.g. eight
    # identical seats on one engine, each its own root); `apose estimate --instances all` finds them all


@dataclass(frozen=True)
class Assembly:
    name: str
    units: str
    parts: dict[str, Part]
    steps: tuple[Step, ...]
    camera: CameraIntrinsics | None = None
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    path: Path | None = field(default=None, compare=False)  # the file it was loaded from
    gripper: Gripper | None = None  # the end effector, for drawing and width checks (assembly/grasps.py)

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
        return StepView(number, step.part, step.base, self.root_of(step.base[0]), step.T_base_part, members, step.approach,
                        self.twins_of(step.base))

    def base_is_region(self, number: int) -> bool:
        """Whether step `number`'s base has a member that is a region of a larger part (`roi`): its prompt is a
        box, whose pixels with depth are the target (masks.prompt.box_depth)."""
        return any(self.parts[p].roi is not None for p in self.steps[number - 1].base if p in self.parts)

    def twins_of(self, base: tuple[str, ...]) -> tuple[str, ...]:
        """The other roots made of the same mesh file as a one-part root `base` (its instances), in file order.
        A region (a part with `roi`) has none: the roots that share its mesh are other regions of one body."""
        if len(base) != 1 or base[0] not in self.roots or base[0] not in self.parts or self.parts[base[0]].roi is not None:
            return ()
        mesh = Path(self.parts[base[0]].mesh).resolve()
        return tuple(p for p in self.roots if p != base[0] and p in self.parts and self.parts[p].roi is None
                     and Path(self.parts[p].mesh).resolve() == mesh)

    def completed(self) -> dict[str, dict[str, np.ndarray]]:
        """The finished assembly: for each root, every part hanging off it with its T_root_part."""
        out: dict[str, dict[str, np.ndarray]] = {r: {} for r in self.roots}
        for p in self.parts:
            out[self.root_of(p)][p] = self.T_root_part(p)
        return out

    def with_steps(self, steps) -> "Assembly":
        return replace(self, steps=tuple(steps))


# --------------------------------------------------------------------------------------------- load


def _parse_parts(c: Checker, parts_raw, folder: Path, scale: float) -> dict[str, Part]:
    parts: dict[str, Part] = {}
    if not isinstance(parts_raw, dict) or not parts_raw:
        got = "an empty mapping (no parts yet)" if isinstance(parts_raw, dict) else kind(parts_raw)
        c.add("parts", f"expected a mapping of part ids to {{mesh: path}}, got {got}")
        return parts
    if len(parts_raw) > MAX_PARTS:
        c.add("parts", f"{len(parts_raw)} parts; at most {MAX_PARTS} are supported")
        return parts
    for pid, spec in parts_raw.items():
        key = f"parts.{pid}"
        if not isinstance(pid, str) or not PART_ID.fullmatch(pid):
            c.add(f"parts.{kind(pid)}" if not isinstance(pid, str) or len(pid) > 40 else key,
                  f"a part id is {PART_ID_RULE}; rename it (and where steps use it)")
            continue
        spec = c.mapping(spec, key, _PART_KEYS, "a mapping with mesh (and optional color, symmetry, grasps, roi)")
        if spec is None:
            continue
        mesh = spec.get("mesh")
        if not isinstance(mesh, str) or not mesh:
            c.add(f"{key}.mesh", f"expected a path to a mesh file, got {kind(mesh)}")
            continue
        mesh_path = (folder / mesh).resolve()
        if not mesh_path.is_file():
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
        solid = spec.get("solid")
        if solid is not None and not (isinstance(solid, str) and solid):
            c.add(f"{key}.solid", f"expected the name of a solid in the STEP file, got {kind(solid)}")
            solid = None
        grasps = parse_grasps(c, spec["grasps"], f"{key}.grasps", scale) if spec.get("grasps") is not None else ()
        roi = parse_roi(c, spec["roi"], f"{key}.roi", scale) if spec.get("roi") is not None else None
        parts[pid] = Part(pid, mesh_path, color, symmetry, solid, grasps, roi)
    return parts


def _parse_symmetry(c: Checker, raw, key: str, scale: float) -> Symmetry | None:
    sym = c.mapping(raw, key, _SYM_KEYS, "{axis: [x, y, z], order: n, origin: [x, y, z]}")
    if sym is None:
        return None
    axis = c.numbers(sym.get("axis"), f"{key}.axis", 3)
    origin = c.numbers(sym.get("origin", [0, 0, 0]), f"{key}.origin", 3, limit=MAX_COORDINATE_M / scale,
                       unit=f" {unit_name(scale)}")
    order = sym.get("order")
    if not (isinstance(order, int) and not isinstance(order, bool) and 0 <= order <= MAX_SYMMETRY_ORDER
            and order != 1):
        c.add(f"{key}.order", f"expected 0 (continuous) or a whole number n from 2 to {MAX_SYMMETRY_ORDER} (n-fold), "
              f"got {kind(order)}")
        return None
    if axis is None or origin is None:
        return None
    if np.linalg.norm(axis) < 1e-9:
        c.add(f"{key}.axis", "expected a non-zero direction")
        return None
    a = np.asarray(axis) / np.linalg.norm(axis)
    return Symmetry(tuple(float(x) for x in a), tuple(float(x) * scale for x in origin), order)


def _parse_steps(c: Checker, steps_raw, parts: dict[str, Part], scale: float) -> tuple[list[Step], dict[int, bool]]:
    steps: list[Step] = []
    if not isinstance(steps_raw, list):
        c.add("steps", f"expected a list of steps, got {kind(steps_raw)}")
        return steps, {}
    if len(steps_raw) > MAX_STEPS:
        c.add("steps", f"{len(steps_raw)} steps; at most {MAX_STEPS} are supported")
        return steps, {}
    placed_by: dict[str, int] = {}
    given: dict[int, bool] = {}  # step index -> whether pose_in_base was written beside mates
    for i, raw in enumerate(steps_raw):
        key = f"steps[{i}]"
        raw = c.mapping(raw, key, _STEP_KEYS, "a mapping with part, base, pose_in_base (or mates)")
        if raw is None:
            continue
        n_before = len(c.problems)
        part = raw.get("part")
        if not isinstance(part, str):
            c.add(f"{key}.part", f"expected a part id, got {kind(part)}")
        elif part not in parts:
            c.add(f"{key}.part", f"unknown part {part!r}; parts are {', '.join(parts)}")
        elif part in placed_by:
            c.add(f"{key}.part", f"{part!r} is already placed by steps[{placed_by[part]}]; a part is placed at most once")
        base = _parse_base(c, raw.get("base"), f"{key}.base", part, parts)
        mates = parse_mates(c, raw["mates"], f"{key}.mates", base, scale) if "mates" in raw else ()
        approach = parse_approach(c, raw["approach"], f"{key}.approach", scale) if "approach" in raw else None
        pose = raw.get("pose_in_base")
        T = None
        if pose is None and "mates" in raw:
            T = np.eye(4)
        elif c.mapping(pose, f"{key}.pose_in_base", _POSE_KEYS, "a mapping with translation (and optional rotation)") is not None:
            t = c.numbers(pose.get("translation"), f"{key}.pose_in_base.translation", 3,
                          limit=MAX_COORDINATE_M / scale, unit=f" {unit_name(scale)}")
            R = rotation(c, pose.get("rotation"), f"{key}.pose_in_base.rotation")
            if t is not None and R is not None:
                T = se3.make_T(R, np.asarray(t) * scale)
        if len(c.problems) == n_before and T is not None:
            steps.append(Step(part, tuple(base), T, mates or (), approach))
            given[len(steps) - 1] = pose is not None
            placed_by[part] = i
        elif isinstance(part, str):
            placed_by.setdefault(part, i)
    return steps, given


def _parse_base(c: Checker, base, key: str, part, parts: dict[str, Part]) -> list[str] | None:
    if not (isinstance(base, list) and base and all(isinstance(b, str) for b in base)):
        c.add(key, f"expected a non-empty list of part ids, got {kind(base)}")
        return None
    for j, b in enumerate(base):
        if b not in parts:
            c.add(f"{key}[{j}]", f"unknown part {b!r}; parts are {', '.join(parts)}")
        elif b == part:
            c.add(f"{key}[{j}]", f"{b!r} cannot be part of its own base")
        elif base.index(b) != j:
            c.add(f"{key}[{j}]", f"{b!r} is listed twice")
    return base


def solve_step_mates(step: Step, T_base_members: dict[str, np.ndarray], part: Part):
    """The mates' solution (`mates.Solution`) for a step whose base parts sit at `T_base_members` (in
    base[0]'s frame); what the mates leave free comes from the step's current pose. Raises MateError."""
    sym = part.symmetry
    axis = np.asarray(sym.axis) if sym is not None and sym.order == 0 else None
    return mt.solve(mt.in_base_frame(step.mates, step.base[0], T_base_members), step.T_base_part, axis)


def _solve_mates(c: Checker, steps: list[Step], parts: dict[str, Part], given: dict[int, bool]) -> None:
    """Solve every step's mates in order (a base part's pose comes from the steps before), in place.
    Step indices in key paths count the steps as written; these are the parsed ones, which match
    when nothing was rejected (this runs only then)."""
    T_root: dict[str, np.ndarray] = {}
    for i, s in enumerate(steps):
        T_root_base0 = T_root.get(s.base[0], np.eye(4))
        if s.mates:
            T_base_root = se3.inv(T_root_base0)
            members = {b: T_base_root @ T_root.get(b, np.eye(4)) for b in s.base}
            try:
                with np.errstate(all="ignore"):  # a result beyond belief is named below, not warned about
                    sol = solve_step_mates(s, members, parts[s.part])
            except MateError as e:
                c.add(f"steps[{i}].mates" + (f"[{e.index}]" if e.index is not None else ""), e.what)
                continue
            except (ValueError, np.linalg.LinAlgError) as e:  # numbers each within range that still break the solver
                c.add(f"steps[{i}].mates", f"cannot be solved ({type(e).__name__}); check their numbers")
                continue
            T = sol.T_base_part
            if not (np.all(np.isfinite(T)) and np.linalg.norm(T[:3, 3]) <= MAX_COORDINATE_M):
                c.add(f"steps[{i}].mates", "solve to a pose beyond 10 km of the base (or no number at all); check "
                      "their offsets and points")
                continue
            off = mt.disagreement(s.T_base_part, sol.T_base_part) if given.get(i) and sol.n_free == 0 else None
            if off is not None:
                c.add(f"steps[{i}].pose_in_base", f"disagrees with the mates, which fix the pose, by {off[0] * 1000:.4g} mm "
                      f"and {np.degrees(off[1]):.4g} deg; delete pose_in_base (the mates give it) or correct it")
            steps[i] = s = replace(s, T_base_part=sol.T_base_part, free=sol.free)
        T_root[s.part] = T_root_base0 @ s.T_base_part


def _check_order(c: Checker, steps: list[Step], parts: dict[str, Part]) -> None:
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
    c = Checker(file)
    data = c.mapping(data, "", _TOP_KEYS, "a mapping with format, name, units, parts, steps")
    if data is None:
        raise AssemblyError(c.problems)
    if data.get("format") != FORMAT:
        c.add("format", f"expected {FORMAT!r}, got {kind(data.get('format'))}")
    name = data.get("name")
    if not isinstance(name, str) or not name.strip():
        c.add("name", f"expected a name, got {kind(name)}")
    elif (bad := safeio.unsafe_char(name)) is not None:
        c.add("name", f"holds the control or invisible character {bad}; write the name on one line without it")
    units = data.get("units")
    if units not in UNIT_TO_M:
        c.add("units", f"expected one of {', '.join(UNIT_TO_M)}, got {kind(units)}")
        units = "m"
    scale = UNIT_TO_M[units]
    parts = _parse_parts(c, data.get("parts"), folder, scale)
    steps, given = _parse_steps(c, data.get("steps"), parts, scale)
    if not c.problems:
        _check_order(c, steps, parts)
    if not c.problems:
        _solve_mates(c, steps, parts, given)
    gripper = parse_gripper(c, data["gripper"], folder, scale) if data.get("gripper") is not None else None
    check_widths(c, parts, gripper)
    camera, cam_problems = camera_from_dict(data.get("camera"), file)
    registration, reg_problems = registration_from_dict(data.get("registration"), file)
    c.problems += cam_problems + reg_problems
    if c.problems:
        raise AssemblyError(c.problems)
    return Assembly(name, units, parts, tuple(steps), camera, registration, Path(file).resolve(), gripper)


def load_assembly(path: str | Path) -> Assembly:
    """Read and validate an assembly file; raises AssemblyError naming file, key path and expectation."""
    path = Path(path)
    try:
        data = safeio.read_bytes(path, "an assembly file (.yaml)", MAX_FILE_BYTES)
    except AposeError as e:
        message = str(e).split(": ", 1)[-1] if str(e).startswith(str(path)) else str(e)
        raise AssemblyError([Problem(str(path), "", message)]) from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise AssemblyError([Problem(str(path), "", "not a text file (an assembly file is YAML text)")]) from None
    return assembly_from_dict(parse_yaml(text, str(path)), path)


# --------------------------------------------------------------------------------------------- save


def assembly_to_dict(asm: Assembly, folder: Path) -> dict:
    """The YAML mapping of an assembly, with mesh paths relative to `folder` where possible."""
    s = asm.unit_scale
    parts = {}
    for pid, p in asm.parts.items():
        # relative when the mesh sits under the file's folder (the pair can move together), else absolute
        mesh = os.path.relpath(p.mesh, folder) if p.mesh.is_relative_to(folder) else str(p.mesh)
        spec: dict = {"mesh": Path(mesh).as_posix()}
        if p.solid is not None:
            spec["solid"] = p.solid
        if p.color is not None:
            spec["color"] = [_num(v) for v in p.color]
        if p.symmetry is not None:
            sym = {"axis": [_num(v) for v in p.symmetry.axis], "order": p.symmetry.order}
            if any(p.symmetry.origin):
                sym["origin"] = [_num(v / s) for v in p.symmetry.origin]
            spec["symmetry"] = sym
        if p.grasps:
            spec["grasps"] = [grasp_to_dict(g, s) for g in p.grasps]
        if p.roi is not None:
            spec["roi"] = roi_to_dict(p.roi, s)
        parts[pid] = spec
    steps = []
    for st in asm.steps:
        q = se3.matrix_to_quat_wxyz(st.T_base_part[:3, :3])
        step = {"part": st.part, "base": list(st.base)}
        if st.mates:
            step["mates"] = [mate_to_dict(m, s) for m in st.mates]
        step["pose_in_base"] = {"translation": [_num(v / s) for v in st.T_base_part[:3, 3]],
                                "rotation": {"quat_wxyz": [float(v) for v in q]}}
        if st.approach is not None:
            step["approach"] = approach_to_dict(st.approach, s)
        steps.append(step)
    out = {"format": FORMAT, "name": asm.name, "units": asm.units, "parts": parts, "steps": steps}
    if asm.camera is not None:
        out["camera"] = camera_to_dict(asm.camera)
    if asm.gripper is not None:
        out["gripper"] = gripper_to_dict(asm.gripper, s, folder)
    registration = registration_to_dict(asm.registration)
    if registration:  # defaults are not written
        out["registration"] = registration
    return out


def dump_assembly(asm: Assembly, folder: Path) -> str:
    """The YAML text of an assembly as a new file (mesh paths relative to `folder` where possible)."""
    return roundtrip_yaml(None, assembly_to_dict(asm, folder))


def _same_pose(path: tuple, old, new) -> bool:
    """A step's (or a grasp's) pose written another way (Euler angles, a matrix, another unit's rounding) but equal
    to what would be written now: keep the user's way of writing it."""
    step_pose = len(path) == 3 and path[0] == "steps" and path[2] == "pose_in_base"
    grasp_pose = len(path) == 5 and path[0] == "parts" and path[2] == "grasps" and path[4] == "pose_in_part"
    if not (step_pose or grasp_pose) or not isinstance(old, dict):
        return False
    c = Checker("")
    t_old = c.numbers(old.get("translation"), "", 3)
    R_old = rotation(c, old.get("rotation"), "")
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
            previous = safeio.read_text(path, "an assembly file", MAX_FILE_BYTES)
        except AposeError:  # unreadable or not ours to merge into: written afresh (the old one kept as .bak)
            previous = None
    text = roundtrip_yaml(previous, assembly_to_dict(asm, path.parent), keep=_same_pose)
    atomic_write_text(path, text, backup=backup and path.is_file())
    return path
