"""Length units: conversion to metres at the edges, and a guess at the unit a mesh was drawn in."""

from __future__ import annotations

import math

UNIT_TO_M: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}

# The farthest a coordinate may lie from its origin, metres (10 km): anything further is a unit or
# export mistake, and numbers near 1e308 overflow the geometry. Meshes, poses in an assembly file, BOP
# poses, results files and the studio's fields all use this one limit.
MAX_COORDINATE_M = 1e4
MAX_ANGLE_DEG = 3600.0  # a typed or written angle: ten turns either way (1e308° has no meaningful sine)

# A CAD part that a robot assembles is rarely smaller than 2 mm or larger than 5 m across.
PLAUSIBLE_DIAMETER_M = (0.002, 5.0)


def unit_name(scale: float) -> str:
    """The unit whose metres-per-unit is `scale` ("" when none is)."""
    return next((u for u, s in UNIT_TO_M.items() if s == scale), "")


def to_metres(value: float, unit: str) -> float:
    return value * UNIT_TO_M[unit]


def suspicious_unit(diameter_raw: float, unit: str) -> str | None:
    """The unit a part of `diameter_raw` (in file units) most likely uses, if `unit` looks wrong.

    Returns None when the declared unit gives a plausible size; otherwise the unit whose size in
    metres is closest (in log scale) to 10 cm, the typical size of an assembled part.
    """
    lo, hi = PLAUSIBLE_DIAMETER_M
    d = diameter_raw * UNIT_TO_M[unit]
    if lo <= d <= hi or diameter_raw <= 0:
        return None
    best = min(UNIT_TO_M, key=lambda u: abs(math.log10(diameter_raw * UNIT_TO_M[u] / 0.1)))
    return best if best != unit else None
