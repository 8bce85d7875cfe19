"""Walking a parsed YAML tree with validation: every problem is collected with the key path it sits at."""

from __future__ import annotations

import numpy as np

from apose_studio.errors import Problem
from apose_studio.geometry import se3
from apose_studio.geometry.camera import is_number
from apose_studio.geometry.units import MAX_ANGLE_DEG

MAX_FILE_NUMBER = 1e9  # no number an assembly file holds needs more (10 km is 1e7 mm); lengths have tighter limits


class Checker:
    """Collects problems while walking the YAML tree."""

    def __init__(self, file: str):
        self.file = file
        self.problems: list[Problem] = []

    def add(self, key: str, what: str) -> None:
        self.problems.append(Problem(self.file, key, what))

    def mapping(self, value, key: str, allowed: tuple[str, ...], what: str) -> dict | None:
        if not isinstance(value, dict):
            self.add(key, f"expected {what}, got {kind(value)}")
            return None
        for k in value:
            if k not in allowed:
                self.add(f"{key}.{k}" if key else str(k), f"unknown key; expected one of {', '.join(allowed)}")
        return value

    def numbers(self, value, key: str, n: int, what: str = "numbers", limit: float | None = None,
                unit: str = "") -> list[float] | None:
        """`n` finite numbers, each at most `limit` from 0 (named with `unit`; default MAX_FILE_NUMBER: a
        direction or quaternion of 1e308 overflows when normalised)."""
        if not isinstance(value, list):
            self.add(key, f"expected a list of {n} {what}, got {kind(value)}")
            return None
        if len(value) != n:
            self.add(key, f"expected {n} {what}, got {len(value)}")
            return None
        bad = [i for i, v in enumerate(value) if not is_number(v)]
        if bad:
            self.add(f"{key}[{bad[0]}]", f"expected a finite number, got {value[bad[0]]!r}")
            return None
        limit = MAX_FILE_NUMBER if limit is None else limit
        far = [i for i, v in enumerate(value) if abs(float(v)) > limit]
        if far:
            self.add(f"{key}[{far[0]}]", f"{float(value[far[0]]):g}{unit} is beyond belief (at most {limit:g}{unit}); check "
                     "the units, or the number")
            return None
        return [float(v) for v in value]


def kind(value) -> str:
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


def rotation(c: Checker, value, key: str) -> np.ndarray | None:
    forms = "one of {quat_wxyz: [w, x, y, z]}, {euler_deg: [a, b, c], order: xyz}, {matrix: 3x3}"
    if value is None:
        return np.eye(3)
    if not isinstance(value, dict):
        c.add(key, f"expected {forms}, got {kind(value)}")
        return None
    kinds = [k for k in ("quat_wxyz", "euler_deg", "matrix") if k in value]
    extra = [k for k in value if k not in ("quat_wxyz", "euler_deg", "matrix", "order")]
    if extra or len(kinds) != 1:
        c.add(f"{key}.{extra[0]}" if extra else key, f"expected {forms}")
        return None
    form = kinds[0]
    if "order" in value and form != "euler_deg":
        c.add(f"{key}.order", "only euler_deg takes an order")
        return None
    if form == "quat_wxyz":
        q = c.numbers(value["quat_wxyz"], f"{key}.quat_wxyz", 4)
        if q is None:
            return None
        n = float(np.linalg.norm(q))
        if n < 1e-9:
            c.add(f"{key}.quat_wxyz", "expected a non-zero quaternion [w, x, y, z], got all zeros")
            return None
        return se3.quat_wxyz_to_matrix(q)
    if form == "euler_deg":
        a = c.numbers(value["euler_deg"], f"{key}.euler_deg", 3, limit=MAX_ANGLE_DEG, unit="°")
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
