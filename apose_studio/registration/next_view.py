"""Where to look next when one look cannot settle the placement (an `ambiguous` or not `confident`
result): the camera pose from which the rival placements look most different.

The rivals are the result's alternatives (ambiguous), else its other distinct candidates, else the
chosen pose turned by the base's close twins. Candidate cameras are poses on the hemisphere around
the base at the current distance (12 yaws x 3 elevations), or a list of reachable poses the user
gives. For each, the model is ray-cast at every rival placement (at a quarter of the resolution) and
the depth images compared: a pixel separates two rivals when one shows the base there and the other
does not, or their depths differ by more than the tolerance. The camera chosen tells the most pairs
of rivals apart (what it sees of the features that differ), then the most pairs with the chosen
placement, then the most such pixels, then the smallest turn from a current camera; `separation_mm`
is the mean depth difference over the pixels where any two differ (a pixel where only one shows the base counts the distance to the other's
surface behind, capped at one diameter). Clutter that may hide the feature from there is not
modelled: the studio draws the advised camera so the user can judge.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.registration.base import BaseObject, raycast_source
from apose_studio.registration.scoring import depth_buffer, distinct_placements
from apose_studio.registration.types import RegistrationResult

ADVICE_YAWS = 12
ADVICE_PITCHES_DEG = (30.0, 50.0, 70.0)
ADVICE_SCALE = 0.25  # the rivals are compared at this fraction of the image's resolution


@dataclass
class NextView:
    T_world_camera: np.ndarray
    separation_mm: float  # mean depth difference where the rivals differ, seen from there
    pixels: int  # how many full-resolution pixels show a difference from there
    pixels_now: int  # ... and from the current camera
    why: str

    def to_json(self) -> dict:
        return {"T_world_camera": self.T_world_camera.tolist(), "separation_mm": round(self.separation_mm, 2),
                "pixels": self.pixels, "pixels_now": self.pixels_now, "why": self.why}


def rivals(result: RegistrationResult, base: BaseObject, limit: int = 4) -> list[np.ndarray]:
    """T_world_base of the chosen placement and its rivals (see the module's docstring)."""
    if result.alternatives:
        others = [c.T_world_base for c in result.alternatives]
    else:
        others = [c.T_world_base for c in distinct_placements(result.candidates, result.voxel, base.symmetries)[1:]]
        if not others:
            others = [result.T_world_base @ S for S in base.close_twins]
    return [result.T_world_base] + others[: limit - 1]


def hemisphere(centre: np.ndarray, distance: float) -> list[np.ndarray]:
    """Cameras looking at `centre` from `distance`, ADVICE_YAWS yaws x ADVICE_PITCHES_DEG elevations."""
    out = []
    for pitch in np.radians(ADVICE_PITCHES_DEG):
        for yaw in np.linspace(0, 2 * np.pi, ADVICE_YAWS, endpoint=False):
            eye = centre + distance * np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
            out.append(se3.look_at(eye, centre))
    return out


def _depth_image(base: BaseObject, T_world_base: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics) -> np.ndarray:
    return depth_buffer(raycast_source(base, T_world_base, T_world_camera, cam)[0], T_world_camera, cam)


SEPARATED_PX = 12  # a pair of placements is told apart from a camera that sees them differ on this many
# pixels (at ADVICE_SCALE: about 190 full-resolution pixels)


@dataclass
class Separation:
    pairs: int  # pairs of placements this camera tells apart (differing on SEPARATED_PX or more)
    pairs_with_chosen: int  # ... of them, pairs with the chosen placement (the first)
    pixels: int  # pixels where any two placements differ (at the camera's resolution)
    gap: float  # mean depth difference over those pixels, metres

    def key(self) -> tuple:
        return (self.pairs, self.pairs_with_chosen, self.pixels)


def separation(base: BaseObject, placements: list[np.ndarray], T_world_camera: np.ndarray, cam: CameraIntrinsics,
               tol: float) -> Separation:
    """How well this camera tells the placements apart (at the resolution of `cam`): every pair's
    differing pixels, where one shows the base and the other not or their depths differ by > tol."""
    images = [_depth_image(base, T, T_world_camera, cam) for T in placements]
    differ = np.zeros(images[0].shape, bool)
    gap = np.zeros(images[0].shape)
    pairs = with_chosen = 0
    for a in range(len(images)):
        for b in range(a + 1, len(images)):
            za, zb = images[a], images[b]
            fa, fb = np.isfinite(za), np.isfinite(zb)
            d = np.zeros(za.shape)
            d[fa & fb] = np.abs(za[fa & fb] - zb[fa & fb])
            d[fa ^ fb] = base.diameter  # one shows the base there, the other does not
            d = np.minimum(d, base.diameter)
            here = d > tol
            if here.sum() >= SEPARATED_PX:
                pairs += 1
                with_chosen += a == 0
            differ |= here
            gap = np.maximum(gap, d)
    n = int(differ.sum())
    return Separation(pairs, with_chosen, n, float(gap[differ].mean()) if n else 0.0)


def next_view(result: RegistrationResult, base: BaseObject, T_world_cameras: list[np.ndarray], cam: CameraIntrinsics,
              reachable: list[np.ndarray] | None = None, tol: float | None = None) -> NextView | None:
    """The camera pose that best separates the result's rival placements (see the module's docstring);
    None when there is nothing to separate (a confident result, or no rival)."""
    if not result.ok or (result.confident and not result.ambiguous):
        return None
    placements = rivals(result, base)
    if len(placements) < 2:
        return None
    small = replace(cam, width=max(8, int(cam.width * ADVICE_SCALE)), height=max(8, int(cam.height * ADVICE_SCALE)),
                    fx=cam.fx * ADVICE_SCALE, fy=cam.fy * ADVICE_SCALE, cx=cam.cx * ADVICE_SCALE, cy=cam.cy * ADVICE_SCALE)
    tol = tol if tol is not None else max(2 * result.voxel, 0.002)
    centre = se3.transform_points(result.T_world_base, base.centre[None])[0]
    distance = float(np.median([np.linalg.norm(T[:3, 3] - centre) for T in T_world_cameras]))
    options = list(reachable) if reachable else hemisphere(centre, distance)
    scale = 1.0 / ADVICE_SCALE**2
    now = max((separation(base, placements, T, small, tol) for T in T_world_cameras), key=Separation.key)
    scored = [(separation(base, placements, T, small, tol), T) for T in options]
    sep, best = max(scored, key=lambda s: s[0].key() + (-_turn_from(s[1], T_world_cameras),))
    if sep.pairs == 0:
        return None
    where = "from the reachable poses given" if reachable else f"on the hemisphere at {distance * 1000:.0f} mm"
    n_pairs = len(placements) * (len(placements) - 1) // 2
    why = (f"{len(placements)} placements fit the data; {where}, this camera tells {sep.pairs} of their {n_pairs} pairs "
           f"apart (the current view {now.pairs}), seeing about {int(sep.pixels * scale)} pixels where they differ")
    return NextView(best, sep.gap * 1000.0, int(sep.pixels * scale), int(now.pixels * scale), why)


def _turn_from(T: np.ndarray, cameras: list[np.ndarray]) -> float:
    """Degrees from T to the nearest of the current cameras (ties go to the smaller move)."""
    return min(se3.rotation_angle_deg(T[:3, :3].T @ C[:3, :3]) for C in cameras)
