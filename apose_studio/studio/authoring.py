"""Editing an assembly as the studio does it: pure functions from one `Assembly` to the next.

Every edit returns a new Assembly (the dataclasses are frozen), so the studio can keep the last
valid one and never lose the user's work to a bad edit. `problems()` validates a draft with exactly
the loader's rules, by a round trip through the YAML mapping, so what the studio accepts the
headless core reads. Typed poses are millimetres and degrees (extrinsic xyz Euler), the core metres.
"""

from __future__ import annotations

import re
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from apose_studio.assembly.mates import Approach, Mate, MateError, Ref, angle_axis, disagreement, in_base_frame
from apose_studio.assembly.mesh import STEP_EXTENSIONS, step_solids
from apose_studio.assembly.model import Assembly, Part, Step, assembly_from_dict, assembly_to_dict, solve_step_mates
from apose_studio.errors import AposeError, AssemblyError, Problem
from apose_studio.geometry import se3

EULER_ORDER = "xyz"


def new_assembly(name: str = "untitled", units: str = "mm", folder: str | Path = ".") -> Assembly:
    """An empty assembly whose file would live in `folder`."""
    return Assembly(name=name, units=units, parts={}, steps=(), path=Path(folder).resolve() / f"{name}.yaml")


def folder_of(asm: Assembly) -> Path:
    return asm.path.parent if asm.path is not None else Path.cwd()


def unique_part_id(asm: Assembly, wanted: str) -> str:
    """A valid, unused part id from a file name, spelt as the file is ('Nema17.step' -> 'Nema17', 'Left
    Gear.stl' -> 'Left_Gear', 'm3-bolt.stl' -> 'm3-bolt'): what PART_ID refuses becomes '_'. Unused
    whatever the case ('left_gear' beside 'Left_Gear' becomes 'left_gear_2'): two ids that differ only by
    case would read as one part in a list."""
    base = re.sub(r"[^0-9A-Za-z_.\-]+", "_", wanted).strip("_.-")[:48] or "part"  # fits assembly.PART_ID
    taken = {p.lower() for p in asm.parts}
    pid, k = base, 2
    while pid.lower() in taken:
        pid, k = f"{base}_{k}", k + 1
    return pid


def add_part(asm: Assembly, mesh_path: str | Path, part_id: str | None = None,
             solid: str | None = None) -> tuple[Assembly, str]:
    """Add a part by mesh path (the caller loads the mesh to check it). Returns the new assembly and id."""
    path = Path(mesh_path).expanduser().resolve()
    pid = unique_part_id(asm, part_id or solid or path.stem)
    parts = dict(asm.parts)
    parts[pid] = Part(pid, path, solid=solid)
    return replace(asm, parts=parts), pid


def add_mesh_parts(asm: Assembly, mesh_path: str | Path) -> tuple[Assembly, list[str]]:
    """Add a mesh file as a part, or a STEP file with several solids as one part per solid (named after
    them). Reads STEP files (to list their solids); raises MeshError on a bad one."""
    path = Path(mesh_path).expanduser().resolve()
    solids = list(step_solids(path)) if path.suffix.lower() in STEP_EXTENSIONS and path.is_file() else []
    if len(solids) <= 1:
        asm, pid = add_part(asm, path)
        return asm, [pid]
    ids = []
    for name in solids:
        asm, pid = add_part(asm, path, solid=name)
        ids.append(pid)
    return asm, ids


def remove_part(asm: Assembly, part_id: str) -> Assembly:
    users = [i + 1 for i, s in enumerate(asm.steps) if s.part == part_id or part_id in s.base]
    if users:
        raise AposeError(f"part {part_id!r} is used by step(s) {', '.join(map(str, users))}; delete or change those first")
    parts = {k: v for k, v in asm.parts.items() if k != part_id}
    return replace(asm, parts=parts)


def set_part_color(asm: Assembly, part_id: str, color) -> Assembly:
    parts = dict(asm.parts)
    parts[part_id] = replace(parts[part_id], color=tuple(float(c) for c in color))
    return replace(asm, parts=parts)


def set_part_roi(asm: Assembly, part_id: str, roi) -> Assembly:
    """The draft with part `part_id`'s region of interest (an assembly.roi.Roi in metres, or None: the whole part)."""
    parts = dict(asm.parts)
    parts[part_id] = replace(parts[part_id], roi=roi)
    return replace(asm, parts=parts)


def roi_handles(kind: str, centre: np.ndarray, size: np.ndarray,
                side: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where the 3D view's two region handles stand (part frame): the centre, and a box's corner (the +x+y+z one,
    or the one `side`'s signs pick: where the last drag left it) or a sphere's point on its surface along the
    part's x (or -x) (`size`: a box's full sides; a sphere's diameter first)."""
    centre, size = np.asarray(centre, float), np.asarray(size, float)
    signs = np.ones(3) if side is None else np.where(np.asarray(side, float) < 0, -1.0, 1.0)
    reach = np.abs(size) / 2 if kind == "box" else np.array([abs(size[0]) / 2, 0.0, 0.0])
    return centre, centre + signs * reach


def roi_from_handles(kind: str, centre: np.ndarray, corner: np.ndarray, least: float) -> np.ndarray:
    """A region's size (a box's full sides; a sphere's diameter three times) from its handles (roi_handles), no
    side under `least`: a corner dragged onto the centre leaves the smallest region, not an empty one."""
    d = np.asarray(corner, float) - np.asarray(centre, float)
    if kind == "box":
        return np.maximum(2 * np.abs(d), least)
    return np.full(3, max(2 * float(np.linalg.norm(d)), least))


def unplaced_parts(asm: Assembly) -> list[str]:
    """Parts no step places yet, in file order (candidates for a new step's part)."""
    placed = {s.part for s in asm.steps}
    return [p for p in asm.parts if p not in placed]


def default_new_step(asm: Assembly) -> Step:
    """A sensible next step: place the first unplaced non-root-looking part on everything so far.

    The base is the first root plus every part already placed on it; the part is the first part that
    is neither a root in use nor placed. Raises AposeError when there is nothing left to place.
    """
    if len(asm.parts) < 2:
        raise AposeError("add at least two parts first: a step places one part on another")
    placed = [s.part for s in asm.steps]
    first_root = asm.steps[0].base[0] if asm.steps else next(iter(asm.parts))
    base = [first_root] + [p for p in placed if asm.root_of(p) == first_root and p != first_root]
    free = [p for p in asm.parts if p not in placed and p not in base]
    if not free:
        raise AposeError("every part is already placed; add a part before adding a step")
    return Step(free[0], tuple(base), np.eye(4))


def add_step(asm: Assembly, step: Step | None = None, at: int | None = None) -> Assembly:
    steps = list(asm.steps)
    steps.insert(len(steps) if at is None else at, step if step is not None else default_new_step(asm))
    return asm.with_steps(steps)


def delete_step(asm: Assembly, index: int) -> Assembly:
    steps = list(asm.steps)
    del steps[index]
    return asm.with_steps(steps)


def move_step(asm: Assembly, index: int, delta: int) -> Assembly:
    """Move step `index` (0-based) by `delta` places, clamped to the list."""
    steps = list(asm.steps)
    j = int(np.clip(index + delta, 0, len(steps) - 1))
    steps.insert(j, steps.pop(index))
    return asm.with_steps(steps)


def edit_step(asm: Assembly, index: int, part: str | None = None, base=None, T_base_part=None) -> Assembly:
    """A step with another part, base or pose; its mates and approach stay (a pose that breaks the
    mates is the caller's to settle: `broken_mates`)."""
    s = asm.steps[index]
    return _with_step(asm, index, replace(
        s, part=part if part is not None else s.part, base=tuple(base) if base is not None else s.base,
        T_base_part=np.array(T_base_part, dtype=float) if T_base_part is not None else s.T_base_part))


def _with_step(asm: Assembly, index: int, step: Step) -> Assembly:
    return asm.with_steps([*asm.steps[:index], step, *asm.steps[index + 1:]])


def problems(asm: Assembly) -> list[Problem]:
    """Everything the loader would reject in this draft (empty when it would load)."""
    file = str(asm.path) if asm.path is not None else "untitled.yaml"
    folder = folder_of(asm)
    try:
        assembly_from_dict(assembly_to_dict(asm, folder), file, folder)
    except AssemblyError as e:
        return e.problems
    if not asm.steps:
        return [Problem(file, "steps", "no steps yet: add a step that places one part on another")]
    return []


_STEP_KEY = re.compile(r"^steps\[(\d+)\]")


def problem_steps(found: list[Problem]) -> set[int]:
    """0-based indices of the steps named by problems (to highlight them)."""
    out = set()
    for p in found:
        m = _STEP_KEY.match(p.key)
        if m:
            out.add(int(m.group(1)))
    return out


# ------------------------------------------------------------------------------- typed poses


def typed_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(translation in mm, extrinsic xyz Euler angles in degrees) of a 4x4 pose in metres."""
    return T[:3, 3] * 1000.0, Rotation.from_matrix(T[:3, :3]).as_euler(EULER_ORDER, degrees=True)


def pose_from_typed(t_mm, euler_deg) -> np.ndarray:
    t = np.asarray(t_mm, dtype=float)
    e = np.asarray(euler_deg, dtype=float)
    if t.shape != (3,) or e.shape != (3,) or not (np.isfinite(t).all() and np.isfinite(e).all()):
        raise AposeError("a pose needs three finite numbers for translation (mm) and three for rotation (deg)")
    return se3.make_T(se3.euler_deg_to_matrix(e, EULER_ORDER), t / 1000.0)


def snap_pose(T: np.ndarray, step_mm: float = 0.0, step_deg: float = 0.0, since: np.ndarray | None = None) -> np.ndarray:
    """Round translation to multiples of step_mm and the Euler angles to multiples of step_deg (0 = off).
    `since`: the pose a drag started from; only the values the drag changed are rounded, so dragging the
    x arrow leaves a typed y = 0.3 mm as it is (a one-axis drag re-snapped the other axes)."""
    t, e = typed_pose(T)
    t0, e0 = typed_pose(since) if since is not None else (None, None)

    def snapped(v, v0, step):
        r = np.round(v / step) * step
        return r if v0 is None else np.where(np.abs(v - v0) > 1e-3, r, v0)  # 1 µm, 0.001°: unchanged

    if step_mm > 0:
        t = snapped(t, t0, step_mm)
    if step_deg > 0:
        e = snapped(e, e0, step_deg)
    return pose_from_typed(t, e)


# ----------------------------------------------------------------------------------- preview


def insertion_direction(asm: Assembly, index: int, centres: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """The unit direction, in the frame of base[0], along which step `index` (0-based) brings its part in:
    from the base part's centre towards the part's, snapped to the nearest axis of that frame (a gear
    put on a shaft comes along the shaft; a lid comes from above). +z where the two centres coincide.
    `centres` are the parts' box centres in their own frames (default: their origins)."""
    centres = centres or {}
    s = asm.steps[index]
    c_part = s.T_base_part[:3, :3] @ centres.get(s.part, np.zeros(3)) + s.T_base_part[:3, 3]
    v = c_part - centres.get(s.base[0], np.zeros(3))
    if np.linalg.norm(v) < 1e-6:
        return np.array([0.0, 0.0, 1.0])
    k = int(np.argmax(np.abs(v)))
    d = np.zeros(3)
    d[k] = np.sign(v[k])
    return d


def body_of(asm: Assembly, pid: str) -> str | None:
    """The mesh file a region (a part with `roi`) is a region of: regions of one file are one body, laid out and
    drawn once (seats of one engine head); None for a whole part."""
    part = asm.parts[pid]
    return str(part.mesh.resolve()) if part.roi is not None else None


def preview_poses(asm: Assembly, upto: int, diameters: dict[str, float], explode: float = 0.0,
                  centres: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """T_world_part of every part shown after the first `upto` steps (0 = only the roots).

    Roots stand side by side along x (a gap of their diameter), regions of one mesh (body_of) on one spot;
    parts placed by steps <= upto sit on them. `explode` (0..1) pulls each placed part out along its step's insertion direction, later steps
    farther, and parts placed on it move with it, so the order reads at a glance. Parts not placed yet
    are left out.
    """
    roots = [r for r in asm.roots if any(asm.root_of(p) == r for p in asm.parts)]
    T_world_root, x, bodies = {}, 0.0, {}
    for r in roots:
        body = body_of(asm, r)
        if body in bodies:  # a region of a part already laid out (another seat of one head): on that part
            T_world_root[r] = T_world_root[bodies[body]]
            continue
        if body is not None:
            bodies[body] = r
        d = diameters.get(r, 0.1)
        T_world_root[r] = se3.make_T(t=np.array([x, 0.0, 0.0]))
        x += 1.5 * d
    out = {r: T_world_root[r] for r in roots}
    n = max(len(asm.steps), 1)
    for i, s in enumerate(asm.steps[:upto]):
        root = asm.root_of(s.part)
        if root not in T_world_root or s.base[0] not in out:
            continue
        T_world_base = out[s.base[0]]
        T = T_world_base @ s.T_base_part
        if explode > 0:
            T = T.copy()
            T[:3, 3] += T_world_base[:3, :3] @ insertion_direction(asm, i, centres) * (
                explode * diameters.get(root, 0.1) * (i + 1) / n)
        out[s.part] = T
    return out


# ----------------------------------------------------------------------------------- mates


def set_mates(asm: Assembly, index: int, mates) -> Assembly:
    """Step `index` (0-based) with these mates (metres; base references in their base part's frame), its
    pose solved from them. Raises AposeError naming the mate that cannot hold."""
    s = replace(asm.steps[index], mates=tuple(mates))
    if not s.mates:
        return _with_step(asm, index, replace(s, free=()))
    view = asm.step_view(index + 1)
    try:
        sol = solve_step_mates(s, view.T_base_members, asm.parts[s.part])
    except MateError as e:
        which = f"mate {e.index + 1}" if e.index is not None else "the mates"
        raise AposeError(f"step {index + 1}, {which}: {e.what}") from None
    return _with_step(asm, index, replace(s, T_base_part=sol.T_base_part, free=sol.free))


def mate_from_picks(asm: Assembly, index: int, kind: str, base_part: str, base_feature, part_feature,
                    offset_m: float = 0.0):
    """A mate of `kind` between a picked feature of a base part and one of the step's part (each a
    `picking.Feature` in its own part's frame). A coaxial mate is flipped when that turns the part less
    (a fitted axis has no sign)."""
    s = asm.steps[index]
    bp = None if base_part == s.base[0] else base_part
    b = Ref(point=base_feature.point.copy(), direction=base_feature.direction.copy())
    p = Ref(point=part_feature.point.copy(), direction=part_feature.direction.copy())
    if kind == "coaxial":
        T_b = asm.step_view(index + 1).T_base_members[base_part]
        flip = float((s.T_base_part[:3, :3] @ p.direction) @ (T_b[:3, :3] @ b.direction)) < 0
        return Mate("coaxial", b, p, bp, flip=flip)
    if kind not in ("contact", "aligned"):
        raise AposeError(f"no mate of kind {kind!r} between two picked faces")
    return Mate(kind, b, p, bp, offset=float(offset_m))


def lock_turn(asm: Assembly, index: int) -> Assembly:
    """Add an angle mate that holds the part's present turn about its coaxial axis (or contact normal)."""
    s = asm.steps[index]
    moved = in_base_frame(s.mates, s.base[0], asm.step_view(index + 1).T_base_members)
    axis = angle_axis(moved)
    if axis is None:
        raise AposeError("an angle needs a coaxial or contact mate first: pick two round or two flat faces")
    ref = se3.perpendicular(axis)
    mate = Mate("angle", Ref(direction=ref), Ref(direction=s.T_base_part[:3, :3].T @ ref), None, degrees=0.0)
    return set_mates(asm, index, [*s.mates, mate])


def edit_mate(asm: Assembly, index: int, k: int, **changes) -> Assembly:
    """Mate k of step `index` with `offset` (m), `degrees` or `flip` changed, solved again."""
    s = asm.steps[index]
    mates = list(s.mates)
    mates[k] = replace(mates[k], **changes)
    return set_mates(asm, index, mates)


def broken_mates(asm: Assembly, index: int, T_base_part: np.ndarray) -> bool:
    """Whether a pose for step `index` breaks its mates (the pose the mates would solve to differs)."""
    s = asm.steps[index]
    if not s.mates:
        return False
    try:
        solved = set_mates(edit_step(asm, index, T_base_part=T_base_part), index, s.mates).steps[index].T_base_part
    except AposeError:
        return True
    return disagreement(np.asarray(T_base_part, float), solved) is not None


def set_approach(asm: Assembly, index: int, direction, distance_m: float) -> Assembly:
    """Step `index` with an approach (a direction in base[0]'s frame and a length in metres), or none."""
    s = asm.steps[index]
    approach = None
    if direction is not None:
        d = np.asarray(direction, dtype=float)
        if not (np.isfinite(d).all() and np.linalg.norm(d) > 1e-9 and np.isfinite(distance_m) and distance_m > 0):
            raise AposeError("an approach needs a direction and a length above 0 mm")
        approach = Approach(d / np.linalg.norm(d), float(distance_m))
    return _with_step(asm, index, replace(s, approach=approach))


class History:
    """Undo and redo over whole drafts (Assemblies are immutable, so a snapshot is a reference)."""

    TYPING_GAP_S = 2.0  # edits of one field closer together than this are one undo step (keystrokes of a number)

    def __init__(self, limit: int = 200):
        self.undo_stack: list[Assembly] = []
        self.redo_stack: list[Assembly] = []
        self.limit = limit
        self._typing: tuple[object, float] | None = None  # (the field, when) of the last typed edit recorded

    def record(self, before: Assembly, typing: object = None, now: float | None = None) -> None:
        """Call before an edit replaces `before`; a new edit forgets what was undone. `typing`: the field
        being typed in (any key, e.g. ("translation", step)); its edits within TYPING_GAP_S of the last one
        are one undo step, as a word typed is one undo step in an editor (typing 30 fired "3", then "30")."""
        now = time.monotonic() if now is None else now
        last, self._typing = self._typing, ((typing, now) if typing is not None else None)
        if typing is not None and last is not None and last[0] == typing and now - last[1] < self.TYPING_GAP_S \
                and self.undo_stack:
            return  # the same field still being typed in: its first edit's snapshot stays the undo step
        if self.undo_stack and self.undo_stack[-1] is before:
            return
        self.undo_stack.append(before)
        del self.undo_stack[:-self.limit]
        self.redo_stack.clear()

    def clear(self) -> None:
        """Forget every step (another file was opened, or a new one started)."""
        self.undo_stack.clear()
        self.redo_stack.clear()
        self._typing = None

    def undo(self, current: Assembly) -> Assembly:
        if not self.undo_stack:
            raise AposeError("nothing to undo")
        self._typing = None
        self.redo_stack.append(current)
        return self.undo_stack.pop()

    def redo(self, current: Assembly) -> Assembly:
        if not self.redo_stack:
            raise AposeError("nothing to redo")
        self._typing = None
        self.undo_stack.append(current)
        return self.redo_stack.pop()


PENETRATION_SHARE = 0.05  # a placed part with more of its surface samples than this inside a base part ...
PENETRATION_DEPTH = 0.0005  # ... deeper than this (metres) goes through it. Measured on the samples as authored:
# at most 3.3 % (a label pressed into the toy duck; 2.1 % for the reducer's carrier in its housing); the gearbox's
# wheel typed 14-34 mm off its place, through the casing's thin wall: 6.8-9.8 %


def penetrations(asm: Assembly, index: int, models: dict) -> list[tuple[str, float, float]]:
    """(base part, share of the part's surface samples inside it deeper than PENETRATION_DEPTH, deepest in
    metres) for each of step `index`'s base parts the part goes into by more than PENETRATION_SHARE at the
    draft's pose: a typed pose that puts a wheel through the casing's wall. Bases that are not watertight
    (whose inside is not defined) are skipped. The samples' signed distances come from Open3D's
    RaycastingScene (the BVH cached per mesh). Every sample assembly's steps give none (a shaft in its
    bore, a label on its tin touch but do not go in)."""
    import open3d as o3d

    from apose_studio.geometry import se3
    from apose_studio.geometry.raycast import body

    s = asm.steps[index]
    part = models[s.part]
    tol = PENETRATION_DEPTH
    out = []
    for b in s.base:
        base = models.get(b)
        if base is None or not base.mesh.is_watertight:
            continue
        T_base_part = np.linalg.inv(asm.T_root_part(b)) @ asm.T_root_part(s.part)
        pts = se3.transform_points(T_base_part, part.samples).astype(np.float32)
        sd = body(base.mesh).scene.compute_signed_distance(o3d.core.Tensor(pts)).numpy()
        share = float(np.mean(sd < -tol))
        if share > PENETRATION_SHARE:
            out.append((b, share, float(-sd.min())))
    return out


def add_grasp(asm: Assembly, part_id: str, grasp) -> Assembly:
    """The part with one more grasp (assembly.grasps.Grasp); its name made unique within the part."""
    part = asm.parts[part_id]
    taken = {g.name for g in part.grasps}
    name, k = grasp.name, 2
    while name in taken:
        name, k = f"{grasp.name}_{k}", k + 1
    parts = dict(asm.parts)
    parts[part_id] = replace(part, grasps=part.grasps + (replace(grasp, name=name),))
    return replace(asm, parts=parts)


def delete_grasp(asm: Assembly, part_id: str, name: str) -> Assembly:
    part = asm.parts[part_id]
    if name not in {g.name for g in part.grasps}:
        raise AposeError(f"{part_id} has no grasp {name!r}")
    parts = dict(asm.parts)
    parts[part_id] = replace(part, grasps=tuple(g for g in part.grasps if g.name != name))
    return replace(asm, parts=parts)
