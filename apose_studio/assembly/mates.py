"""Mates: a step's pose given as geometric constraints between features of its base and of its part.

Format: "Optional step keys" of `ASSEMBLY_FORMAT.md` (shared docs). Everything here is metres and unit
vectors; the file's units are applied by the parser and undone by `mate_to_dict`.

The solver is sequential and exact for the five mate types: the rotation first (from the direction
pairs the mates impose, then the `angle` turn), then the translation as a linear least-squares
problem whose null space is the free sliding. What no mate fixes is kept from a guess (the step's
`pose_in_base`, or identity). Mates are added one at a time, so a contradiction names the first mate
that cannot hold together with those before it, with its residual.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from apose_studio.assembly.fileio import yaml_number as _num
from apose_studio.assembly.yamlcheck import Checker, kind, rotation
from apose_studio.geometry import se3
from apose_studio.geometry.camera import is_number
from apose_studio.geometry.units import MAX_ANGLE_DEG, MAX_COORDINATE_M

MATE_TYPES = ("coaxial", "contact", "aligned", "angle", "fixed")
LENGTH_TOL_M = 1e-6  # the format's tolerances for contradictions and a disagreeing pose_in_base
ANGLE_TOL_RAD = 1e-4
_REF_KEYS = {  # per type: (keys of the base reference, keys of the part reference, keys of the mate)
    "coaxial": (("part", "point", "direction"), ("point", "direction"), ("type", "base", "part", "flip")),
    "contact": (("part", "point", "normal"), ("point", "normal"), ("type", "base", "part", "offset")),
    "aligned": (("part", "point", "normal"), ("point", "normal"), ("type", "base", "part", "offset")),
    "angle": (("part", "direction"), ("direction",), ("type", "base", "part", "degrees")),
    "fixed": (("part", "translation", "rotation"), ("translation", "rotation"), ("type", "base", "part")),
}


@dataclass(frozen=True, eq=False)
class Ref:
    """One side of a mate, in its part's own frame: a point (m) and a unit direction or normal, or a frame."""

    point: np.ndarray | None = None
    direction: np.ndarray | None = None  # the axis of coaxial/angle, the normal of contact/aligned
    T: np.ndarray | None = None  # fixed: the frame (4x4)

    def __eq__(self, other) -> bool:
        def same(a, b):
            return (a is None) == (b is None) and (a is None or np.allclose(a, b, rtol=0, atol=1e-12))

        return isinstance(other, Ref) and all(same(getattr(self, k), getattr(other, k)) for k in ("point", "direction", "T"))

    def moved(self, T: np.ndarray) -> "Ref":
        """The same reference expressed in another frame (T maps this frame into it)."""
        return Ref(None if self.point is None else se3.transform_points(T, self.point[None])[0],
                   None if self.direction is None else T[:3, :3] @ self.direction,
                   None if self.T is None else T @ self.T)


@dataclass(frozen=True)
class Mate:
    type: str
    base: Ref
    part: Ref
    base_part: str | None = None  # the base part `base` is given in; None = base[0]
    offset: float = 0.0  # contact/aligned: gap along the base normal, metres
    degrees: float = 0.0  # angle
    flip: bool = False  # coaxial: axes opposed


@dataclass(frozen=True, eq=False)
class Approach:
    """The last straight motion of the part into place: a unit direction in base[0]'s frame and a length (m)."""

    direction: np.ndarray
    distance: float

    def __eq__(self, other) -> bool:
        return (isinstance(other, Approach) and np.allclose(self.direction, other.direction, rtol=0, atol=1e-12)
                and abs(self.distance - other.distance) < 1e-12)

    def start(self, T_world_part: np.ndarray, T_world_base: np.ndarray) -> np.ndarray:
        """T_world_part_approach: the assembly pose moved back by `distance` along the direction."""
        T = np.array(T_world_part, dtype=float)
        T[:3, 3] -= self.distance * (T_world_base[:3, :3] @ self.direction)
        return T


class MateError(ValueError):
    """A mate that cannot hold; `index` is its position in the step's `mates` (None: the whole step)."""

    def __init__(self, index: int | None, what: str):
        super().__init__(what)
        self.index, self.what = index, what


@dataclass(frozen=True, eq=False)
class Solution:
    T_base_part: np.ndarray
    free: tuple[str, ...]  # the degrees of freedom no mate fixes, in words (silenced: symmetric turns)
    n_free: int  # how many (0 = the mates fix the pose)


# ---------------------------------------------------------------------------------------------- solve


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _turn_onto(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit w onto unit v."""
    axis = np.cross(w, v)
    s, c = np.linalg.norm(axis), float(np.dot(w, v))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        return se3.axis_angle_matrix(se3.perpendicular(w), np.pi)
    return se3.axis_angle_matrix(axis, np.arctan2(s, c))


def _pair(m: Mate) -> tuple[np.ndarray, np.ndarray] | None:
    """(u, v): the rotation must take the part's direction u onto v (base[0] frame)."""
    if m.type == "coaxial":
        return m.part.direction, -m.base.direction if m.flip else m.base.direction
    if m.type == "contact":
        return m.part.direction, -m.base.direction
    if m.type == "aligned":
        return m.part.direction, m.base.direction
    return None


def angle_axis(mates: list[Mate]) -> np.ndarray | None:
    for types in (("coaxial",), ("contact", "aligned")):
        for m in mates:
            if m.type in types:
                return m.base.direction
    return None


def _turn(m: Mate, axis: np.ndarray, R: np.ndarray) -> float:
    """Right-handed angle (rad) about `axis` from the base's reference direction to the part's, both
    projected across the axis."""
    x = m.base.direction - np.dot(m.base.direction, axis) * axis
    y = R @ m.part.direction
    y = y - np.dot(y, axis) * axis
    if np.linalg.norm(x) < 1e-9 or np.linalg.norm(y) < 1e-9:
        raise MateError(None, "its reference direction is parallel to the axis it turns about; pick a direction across it")
    return float(np.arctan2(np.dot(axis, np.cross(x, y)), np.dot(x, y)))


def _rotation(mates: list[Mate], R_guess: np.ndarray, w: list[float]) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """(R, free axis or None, free in every direction); `w` weighs the mates where they disagree."""
    fixed = [m for m in mates if m.type == "fixed"]
    pairs = [p for p in map(_pair, mates) if p is not None]
    pw = [wi for m, wi in zip(mates, w) if _pair(m) is not None]
    free_axis, all_free = None, False
    if fixed:
        R = (fixed[0].base.T @ se3.inv(fixed[0].part.T))[:3, :3]
    elif not pairs:
        R, all_free = R_guess, True
    elif max(np.linalg.norm(np.cross(v, pairs[0][1])) for _, v in pairs) > 1e-9:
        R = Rotation.align_vectors([v for _, v in pairs], [u for u, _ in pairs], weights=pw)[0].as_matrix()
    else:
        u, v = pairs[0]
        R = _turn_onto(R_guess @ u, v) @ R_guess  # the rotation nearest the guess that takes u onto v
        free_axis = v
    angles = [m for m in mates if m.type == "angle"]
    if angles:
        axis = angle_axis(mates)
        if axis is None:
            raise MateError(None, "an angle mate turns about a coaxial axis or a contact normal; add one of those first")
        if free_axis is not None:
            R = se3.axis_angle_matrix(axis, np.radians(angles[0].degrees) - _turn(angles[0], axis, R)) @ R
            free_axis = None
    return R, free_axis, all_free


def _translation(mates: list[Mate], R: np.ndarray, t_guess: np.ndarray, w: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """(t, null space basis (3, k)): rows a.t = b from every mate that places a point, weighed by `w`."""
    rows, rhs, weights = [], [], []
    for m, wi in zip(mates, w):
        n0 = len(rows)
        if m.type == "fixed":
            T = m.base.T @ se3.inv(m.part.T)
            rows += list(np.eye(3))
            rhs += list(T[:3, 3])
        elif m.type == "angle":
            continue
        elif m.type == "coaxial":
            gap = m.base.point - R @ m.part.point
            d = m.base.direction
            e1 = se3.perpendicular(d)
            for e in (e1, np.cross(d, e1)):
                rows.append(e)
                rhs.append(float(e @ gap))
        else:
            rows.append(m.base.direction)
            rhs.append(float(m.base.direction @ (m.base.point - R @ m.part.point)) + m.offset)
        weights += [wi] * (len(rows) - n0)
    if not rows:
        return t_guess, np.eye(3)
    A, b = np.array(rows), np.array(rhs)
    t0 = np.linalg.lstsq(A * np.array(weights)[:, None], b * np.array(weights), rcond=None)[0]
    _, s, Vt = np.linalg.svd(A)
    rank = int((s > 1e-9 * max(s.max(), 1.0)).sum())
    N = Vt[rank:].T
    return t0 + N @ (N.T @ (t_guess - t0)), N


def residual(m: Mate, T: np.ndarray, axis: np.ndarray | None = None) -> tuple[float, float]:
    """(metres, radians) by which pose T_base_part misses mate m (references in base[0]'s frame); an
    angle mate is measured about `axis` (`angle_axis` of its step's mates)."""
    R, t = T[:3, :3], T[:3, 3]
    if m.type == "fixed":
        D = se3.inv(m.base.T @ se3.inv(m.part.T)) @ T
        return float(np.linalg.norm(D[:3, 3])), np.radians(se3.rotation_angle_deg(D[:3, :3]))
    if m.type == "angle":
        d = np.radians(m.degrees) - _turn(m, axis, R)
        return 0.0, abs(float(np.arctan2(np.sin(d), np.cos(d))))
    u, v = _pair(m)
    ang = float(np.arccos(np.clip(np.dot(R @ u, v), -1.0, 1.0)))
    off = R @ m.part.point + t - m.base.point
    if m.type == "coaxial":
        d = m.base.direction
        return float(np.linalg.norm(off - np.dot(off, d) * d)), ang
    return abs(float(np.dot(m.base.direction, off)) - m.offset), ang


def _solve_once(mates: list[Mate], T_guess: np.ndarray):
    """Solve with the last mate weighed lightly, so that where it disagrees with the others it alone
    shows the residual; returns (T, free axis, all free, null space, the last mate's residual)."""
    w = [1e4] * (len(mates) - 1) + [1.0]
    R, free_axis, all_free = _rotation(mates, T_guess[:3, :3], w)
    t, N = _translation(mates, R, T_guess[:3, 3], w)
    T = se3.make_T(R, t)
    return T, free_axis, all_free, N, residual(mates[-1], T, angle_axis(mates))


def _fmt(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.3g}" for x in np.where(np.abs(v) < 1e-9, 0.0, v)) + "]"


def _free_words(mates: list[Mate], T: np.ndarray, free_axis, all_free: bool, N: np.ndarray,
                symmetry_axis: np.ndarray | None) -> tuple[list[str], int]:
    """(the free degrees of freedom in words, how many)."""
    out, n_rot = [], 0
    if all_free:
        out.append("rotation is free (no mate sets it: add a coaxial, contact, aligned or fixed mate)")
        n_rot = 3
    elif free_axis is not None:
        sym = symmetry_axis is not None and np.linalg.norm(np.cross(T[:3, :3] @ symmetry_axis, free_axis)) < 1e-6
        if not sym:  # a part symmetric about the axis looks the same at every turn: nothing to say
            about = "the coaxial axis" if any(m.type == "coaxial" for m in mates) else "the contact normal"
            out.append(f"rotation about {about} {_fmt(free_axis)} is free (add an angle mate)")
            n_rot = 1
    k = N.shape[1]
    if k == 1:
        out.append(f"sliding along {_fmt(N[:, 0])} is free")
    elif k == 2:
        out.append(f"sliding in the plane across {_fmt(np.cross(N[:, 0], N[:, 1]))} is free")
    elif k == 3:
        out.append("translation is free")
    return out, n_rot + k


def solve(mates: list[Mate], T_guess: np.ndarray | None = None, symmetry_axis=None) -> Solution:
    """The part's pose in base[0]'s frame from mates whose base references are already in that frame.

    `T_guess` supplies what the mates leave free (identity by default); `symmetry_axis` (the part's
    continuous symmetry axis, part frame) silences a free turn about it. Raises MateError with the
    index of the first mate that contradicts those before it."""
    T_guess = np.eye(4) if T_guess is None else np.asarray(T_guess, dtype=float)
    if not mates:
        return Solution(T_guess, ("every degree of freedom is free (no mates)",), 6)
    order = [i for i, m in enumerate(mates) if m.type != "angle"] + [i for i, m in enumerate(mates) if m.type == "angle"]
    for k in range(1, len(order) + 1):
        subset = [mates[i] for i in order[:k]]
        try:
            T, free_axis, all_free, N, (res_m, res_rad) = _solve_once(subset, T_guess)
        except MateError as e:
            raise MateError(order[k - 1], e.what) from None
        if res_m > LENGTH_TOL_M or res_rad > ANGLE_TOL_RAD:
            others = "the mates before it" if k > 1 else "itself"
            raise MateError(order[k - 1], f"contradicts {others}: a residual of {res_m * 1000:.4g} mm and "
                            f"{np.degrees(res_rad):.4g} deg remains; change its references or offset, or delete it")
    sym = None if symmetry_axis is None else _unit(symmetry_axis)
    words, n_free = _free_words(mates, T, free_axis, all_free, N, sym)
    return Solution(T, tuple(words), n_free)


def in_base_frame(mates, base0: str, T_base_members: dict[str, np.ndarray]) -> list[Mate]:
    """The mates with their base references moved into base[0]'s frame."""
    out = []
    for m in mates:
        T = T_base_members[m.base_part or base0]
        out.append(Mate(m.type, m.base.moved(T), m.part, None, m.offset, m.degrees, m.flip))
    return out


def disagreement(T_given: np.ndarray, T_solved: np.ndarray) -> tuple[float, float] | None:
    """(metres, radians) by which a given pose_in_base misses the solved one, or None within tolerance."""
    D = se3.inv(T_solved) @ T_given
    m, rad = float(np.linalg.norm(T_given[:3, 3] - T_solved[:3, 3])), np.radians(se3.rotation_angle_deg(D[:3, :3]))
    return (m, rad) if m > LENGTH_TOL_M or rad > ANGLE_TOL_RAD else None


# ---------------------------------------------------------------------------------------- parse / dump


def _vec(c: Checker, raw, key: str, scale: float = 1.0, unit: bool = False) -> np.ndarray | None:
    v = c.numbers(raw, key, 3, limit=None if unit else MAX_COORDINATE_M / scale)
    if v is None:
        return None
    v = np.asarray(v)
    if unit:
        if np.linalg.norm(v) < 1e-12:
            c.add(key, "expected a non-zero direction")
            return None
        return v / np.linalg.norm(v)
    return v * scale


def _ref(c: Checker, raw, key: str, keys: tuple[str, ...], scale: float) -> Ref | None:
    spec = c.mapping(raw, key, keys, "a mapping with " + ", ".join(k for k in keys if k != "part"))
    if spec is None:
        return None
    missing = [k for k in keys if k != "part" and k not in spec and k != "rotation"]
    if missing:
        c.add(f"{key}.{missing[0]}", f"missing; a {key.rsplit('.', 1)[-1]} reference needs {', '.join(k for k in keys if k != 'part')}")
        return None
    if "translation" in keys:
        t, R = _vec(c, spec["translation"], f"{key}.translation", scale), rotation(c, spec.get("rotation"), f"{key}.rotation")
        return None if t is None or R is None else Ref(T=se3.make_T(R, t))
    point = _vec(c, spec["point"], f"{key}.point", scale) if "point" in keys else None
    dk = "normal" if "normal" in keys else "direction"
    direction = _vec(c, spec[dk], f"{key}.{dk}", unit=True)
    if direction is None or ("point" in keys and point is None):
        return None
    return Ref(point=point, direction=direction)


def parse_mates(c: Checker, raw, key: str, base: tuple[str, ...] | None, scale: float) -> tuple[Mate, ...] | None:
    if not isinstance(raw, list) or not raw:
        c.add(key, f"expected a non-empty list of mates, got {kind(raw)}")
        return None
    out, n0 = [], len(c.problems)
    for j, m in enumerate(raw):
        mk = f"{key}[{j}]"
        t = m.get("type") if isinstance(m, dict) else None
        if t not in MATE_TYPES:
            c.add(f"{mk}.type" if isinstance(m, dict) else mk, f"expected a mate with type one of {', '.join(MATE_TYPES)}, "
                  f"got {kind(t) if isinstance(m, dict) else kind(m)}")
            continue
        base_keys, part_keys, mate_keys = _REF_KEYS[t]
        if c.mapping(m, mk, mate_keys, f"a {t} mate") is None:
            continue
        b = _ref(c, m.get("base"), f"{mk}.base", base_keys, scale)
        p = _ref(c, m.get("part"), f"{mk}.part", part_keys, scale)
        base_part = m["base"].get("part") if isinstance(m.get("base"), dict) else None
        if base_part is not None and (base is None or base_part not in base):
            c.add(f"{mk}.base.part", f"{kind(base_part)} is not in this step's base ({', '.join(base or ())})")
        offset, degrees, flip = m.get("offset", 0), m.get("degrees", 0 if t != "angle" else None), m.get("flip", False)
        if t in ("contact", "aligned") and not _within(offset, MAX_COORDINATE_M / scale):
            c.add(f"{mk}.offset", f"expected a gap in the file's units within 10 km, got {kind(offset)}")
        if t == "angle" and not _within(degrees, MAX_ANGLE_DEG):
            c.add(f"{mk}.degrees", f"expected the turn in degrees (at most {MAX_ANGLE_DEG:g} either way), got {kind(degrees)}")
        if not isinstance(flip, bool):
            c.add(f"{mk}.flip", f"expected true or false, got {kind(flip)}")
        if len(c.problems) == n0 and b is not None and p is not None:
            out.append(Mate(t, b, p, base_part, float(offset) * scale, float(degrees), flip))
    return tuple(out) if len(c.problems) == n0 else None


def _within(v, limit: float) -> bool:
    """A finite number (not a bool) at most `limit` from 0: a gap, a turn or a distance."""
    return is_number(v) and abs(float(v)) <= limit


def parse_approach(c: Checker, raw, key: str, scale: float) -> Approach | None:
    spec = c.mapping(raw, key, ("direction", "distance"), "{direction: [x, y, z], distance: d}")
    if spec is None:
        return None
    d = _vec(c, spec.get("direction"), f"{key}.direction", unit=True)
    dist = spec.get("distance")
    if not _within(dist, MAX_COORDINATE_M / scale) or dist <= 0:
        c.add(f"{key}.distance", f"expected a length > 0 in the file's units within 10 km, got {kind(dist)}")
        return None
    return None if d is None else Approach(d, float(dist) * scale)


def _nums(v, scale: float = 1.0) -> list:
    return [_num(x / scale) for x in v]


def mate_to_dict(m: Mate, scale: float) -> dict:
    """The YAML mapping of a mate (lengths in file units: metres / scale)."""
    base_keys, part_keys, _ = _REF_KEYS[m.type]

    def ref(r: Ref, keys) -> dict:
        out = {}
        if r.T is not None:
            return {"translation": _nums(r.T[:3, 3], scale),
                    "rotation": {"quat_wxyz": [float(x) for x in se3.matrix_to_quat_wxyz(r.T[:3, :3])]}}
        if "point" in keys:
            out["point"] = _nums(r.point, scale)
        out["normal" if "normal" in keys else "direction"] = _nums(r.direction)
        return out

    b = ({"part": m.base_part} if m.base_part else {}) | ref(m.base, base_keys)
    out = {"type": m.type, "base": b, "part": ref(m.part, part_keys)}
    if m.type in ("contact", "aligned") and m.offset:
        out["offset"] = _num(m.offset / scale)
    if m.type == "angle":
        out["degrees"] = _num(m.degrees)
    if m.flip:
        out["flip"] = True
    return out


def approach_to_dict(a: Approach, scale: float) -> dict:
    return {"direction": _nums(a.direction), "distance": _num(a.distance / scale)}
