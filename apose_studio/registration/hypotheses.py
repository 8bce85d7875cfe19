"""Masks that the model checks: other readings of a frame's mask, and how well a pose explains the frame.

A mask drawn from a prompt on a real desk takes in what touches the base: a tin lying on it, a box
standing in front of it. The estimate on the mask as given is kept when it is confident; otherwise
`pipeline.estimate` also estimates these readings of it, each a part of the mask:

- *below the base's height*: without the pixels higher above the table than the base can reach
  standing on it as modelled (what lies on top of it; needs a table in view);
- *without what stands in front*: without the mask's depth patches that stand in front of another of its
  patches where they meet and behind none (the front-most: an object between the camera and the base,
  which a box drawn around the little that is seen of the base takes in);
- *without colour k*: without one of the mask's two colour groups (k-means on chroma), when their
  colours clearly differ (a red tin on a grey box; needs the view's RGB);
- *without patch k*: without one of the mask's two largest depth patches (the mask split where the
  depth jumps), when each part is large enough to hold the base (an object in front, a neighbour);

and, with a prompt's box, before them all, *what lies wholly in the box* (`in_box`): not a part of the mask
but the depth patches that lie inside the box, for the prompt may have kept an object in front that fills
the box and lost the base it hides;

and keeps the estimate whose model explains the most of that depth (the mask's and the box's own) with the
least the camera sees past (`explained`), an estimate the depth does not contradict first
(`pipeline.uncontradicted`: a pose raised onto a plate lying on the base explains the plate's pixels too, more
than the right pose explains, and only its sides, seen past, give it away): the mask and the pose are found
together. When the best of these is still not
confident, its mask is read once more, by depth only (a tin on the base *and* a box in front: either
reading alone leaves the other in); when none of them beat the mask as given, what two of them both keep
(`both_out`) is estimated instead. Not by colour: once a foreign object is out, the two colour groups
left are mostly the base's own (a casing and its gear, a duck and its label), and leaving one out
dropped half the base (benchmarks/captures.py `real`: a label 8 mm off, confident). The readings are pure functions of
the view, the base and the table; `explained` is the judge's evidence counted over the mask and every reading.
"""

from __future__ import annotations

import cv2
import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.camera import box_region, valid_mask_pixels
from apose_studio.geometry.noise import depth_edges
from apose_studio.registration.base import BaseObject, raycast_source
from apose_studio.registration.scoring import MASK_MARGIN_PX, agreement_tolerance, depth_window, mask_edge
from apose_studio.registration.types import MIN_POINTS, RegistrationResult, View

MIN_PATCH_PX = 20  # depth patches smaller than this are noise (as prompt.py)
MIN_READING_SHARE = 0.1  # a reading keeps at least this share of the mask's pixels (else it cannot hold the base)
MIN_CUT_SHARE = 0.03  # ... and leaves out at least this share (else it is the mask as given)
PATCHES = 2  # the largest depth patches each left out in turn
MIN_CHROMA_GAP = 12.0  # two colour groups this far apart in Lab's (a, b) are two things, not one object's shading
MAX_READINGS = 4  # at most this many other readings are estimated (in the order of the module doc)
CONTRADICTION_WEIGHT = 5.0  # a pixel the camera sees past costs this many explained ones: a pose raised onto a flat
# object lying on the base confirms its pixels too, and only the sides seen past tell it from the right pose.
# benchmarks/captures.py (stacked, hidden, real; desk objects and helical gearbox, 108 frames): 2 -> 5 made 5
# frames right (4 confident), none worse, confident-and-wrong unchanged


def readings(view: View, base: BaseObject, table: tuple[np.ndarray, float] | None, tol: float,
             colour: bool = True, box: bool = True) -> list[tuple[str, np.ndarray]]:
    """(name, mask) of the other readings of `view.mask` (see the module doc): with `box` and a prompt's
    box, first what lies wholly in the box (`in_box`) where the mask missed it; then parts of the mask,
    each leaving out at least MIN_CUT_SHARE and keeping at least MIN_READING_SHARE of its pixels with
    depth, none two alike. `table`: the world plane (unit normal towards the camera, offset) the base
    stands on, or None; `tol`: how far a surface may lie off its place (metres); `colour`: the colour
    readings too."""
    mask, depth = view.mask, view.depth
    valid = mask & np.isfinite(depth) & (depth > 0)
    n = int(valid.sum())
    own = in_box(view, table, tol) if box else None
    first = [(IN_BOX_NAME, own)] if own is not None and _iou(own, valid) <= 0.9 else []
    if n < 2 * MIN_POINTS:
        return first
    out: list[tuple[str, np.ndarray]] = []

    def add(name: str, reading: np.ndarray) -> None:
        kept = int((reading & valid).sum())
        if not (max(MIN_POINTS, MIN_READING_SHARE * n) <= kept <= (1 - MIN_CUT_SHARE) * n):
            return
        if any(_iou(reading, m) > 0.9 for _, m in out):
            return
        out.append((name, reading))

    if table is not None:
        add("below the base's height", mask & ~too_high(view, base, table, tol))
    patches = depth_patches(depth, mask)  # split once, read twice below
    front = front_most(depth, mask, patches)
    if front.any():
        add("without what stands in front", mask & ~front)
    if colour and view.rgb is not None and view.rgb.ndim == 3 and view.rgb.shape[2] == 3:
        for k, group in enumerate(colour_groups(view.rgb, mask), start=1):
            add(f"without colour {k}", mask & ~group)
    for k, patch in enumerate(largest_patches(depth, mask, PATCHES, patches), start=1):
        add(f"without depth patch {k}", mask & ~patch)
    return first + out[:MAX_READINGS]


def both_out(todo: list[tuple[str, np.ndarray]]) -> list[tuple[str, np.ndarray]]:
    """Readings that leave out what two of `todo`'s readings (parts of one mask) each leave out, in their order
    (what lies wholly in the box, not a part of the mask, is not paired), none two alike, at most MAX_READINGS:
    a tin on the base and a box in front of it, each left out by one reading, the other still pulling its pose
    off."""
    parts = [(name, m) for name, m in todo if name != IN_BOX_NAME]
    out: list[tuple[str, np.ndarray]] = []
    for i, (n1, a) in enumerate(parts):
        for n2, b in parts[i + 1:]:
            both = a & b
            if both.sum() >= MIN_POINTS and not any(_iou(both, m) > 0.9 for _, m in [*parts, *out]):
                out.append((f"{n1}, {n2}", both))
    return out[:MAX_READINGS]


IN_BOX_NAME = "what lies wholly in the box"
IN_BOX_SHARE = 0.9  # a depth patch with this share of its pixels inside the prompt's box is the box's own


def in_box(view: View, table: tuple[np.ndarray, float] | None, tol: float) -> np.ndarray | None:
    """(H, W) bool: the depth patches (split where the depth jumps, in a window of one box size around the
    prompt's box, off the table by more than `tol` when a table is known) with at least IN_BOX_SHARE of
    their pixels inside the box; None without a box or with fewer than MIN_POINTS such pixels.

    A box is drawn around what is seen of the base. When an object in front hides most of it, that object
    runs out of the box and the base does not; the prompted mask, which keeps what fills the box, can then
    hold the object in front and none of the base (benchmarks/captures.py `hidden`)."""
    if view.box is None:
        return None
    depth = view.depth
    x0, y0, x1, y1 = (int(v) for v in view.box)
    window = box_region(depth.shape, view.box, max(x1 - x0, y1 - y0))
    inside = box_region(depth.shape, view.box)
    keep = window & np.isfinite(depth) & (depth > 0)
    if table is not None:
        vs, us = np.nonzero(keep)
        pts = se3.transform_points(view.T_world_camera, view.camera.backproject(us, vs, depth[vs, us]))
        normal, offset = table
        on_table = pts @ normal + offset <= tol
        keep[vs[on_table], us[on_table]] = False
    count, labels, _ = depth_patches(depth, keep)
    sizes = np.bincount(labels.ravel(), minlength=count)
    within = np.bincount(labels[inside], minlength=count)
    own = (within >= IN_BOX_SHARE * sizes) & (sizes >= MIN_PATCH_PX)
    own[0] = False
    out = own[labels]
    # the jumps they were split off at (as with_edge: an outline's pixels pin a flat face's place), not the
    # pixels of patches that run out of the box
    out |= (cv2.dilate(out.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0) & keep & inside & (labels == 0)
    # the largest group of them (pieces closer than 9 px are one: an object's own depth edges split it), and
    # groups at least a fifth its size: not a speck of something small that happens to lie in the box too
    n, group = cv2.connectedComponents((cv2.dilate(out.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0).astype(np.uint8))
    size = np.bincount(group[out], minlength=n)
    out &= size[group] >= 0.2 * size.max()
    return out if out.sum() >= MIN_POINTS else None


def colour_groups(rgb: np.ndarray, mask: np.ndarray, iterations: int = 10) -> list[np.ndarray]:
    """The mask's pixels in two groups by colour (k-means on Lab's chroma a, b with lightness at a third of
    its weight, so one object's faces lit differently stay together; started from the two most different
    colours, so it is deterministic), each cleaned of specks; [] when the two groups' chroma lie less
    than MIN_CHROMA_GAP apart or one is under MIN_READING_SHARE of the mask."""
    lab = cv2.cvtColor(cv2.medianBlur(np.ascontiguousarray(rgb, dtype=np.uint8), 5), cv2.COLOR_RGB2LAB).astype(np.float32)
    px = lab[mask] * np.float32([1 / 3, 1, 1])
    if len(px) < 2 * MIN_POINTS:
        return []
    sample = px[:: max(1, len(px) // 3000)]
    a = sample[np.argmax(np.linalg.norm(sample - np.median(sample, axis=0), axis=1))]
    centres = np.stack([a, sample[np.argmax(np.linalg.norm(sample - a, axis=1))]])
    for _ in range(iterations):
        near = np.argmin(((sample[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        if np.bincount(near, minlength=2).min() == 0:
            return []
        centres = np.stack([sample[near == j].mean(axis=0) for j in range(2)])
    if np.linalg.norm(centres[0, 1:] - centres[1, 1:]) < MIN_CHROMA_GAP:
        return []
    near = np.argmin(((px[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
    groups = []
    for j in range(2):
        g = np.zeros(mask.shape, np.uint8)
        g[mask] = near == j
        g = cv2.morphologyEx(g, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
        if g.sum() < MIN_READING_SHARE * mask.sum():
            return []
        groups.append(g)
    return groups


def too_high(view: View, base: BaseObject, table: tuple[np.ndarray, float], tol: float) -> np.ndarray:
    """(H, W) bool: masked pixels whose depth lies higher above the table than the base reaches standing
    on it as modelled (its CAD z extent), by more than `tol`."""
    mask, depth, cam = view.mask, view.depth, view.camera
    vs, us = valid_mask_pixels(mask, depth)
    pts = se3.transform_points(view.T_world_camera, cam.backproject(us, vs, depth[vs, us]))
    normal, offset = table
    lo, hi = np.asarray(base.mesh.bounds)
    high = pts @ normal + offset > float(hi[2] - lo[2]) + tol
    out = np.zeros(mask.shape, bool)
    out[vs[high], us[high]] = True
    return out


EDGE_REL, EDGE_FLOOR = 0.012, 0.004  # a depth jump over max(EDGE_FLOOR, EDGE_REL * z) splits patches (as prompt.py)
MIN_FRONT_SHARE = 0.02  # a patch this small a share of the mask does not count as standing in front
BORDER_PX = 4  # how far across a depth jump two patches are compared


def depth_patches(depth: np.ndarray, mask: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """(count, labels, z): the mask split where the (median-filtered) depth jumps, 4-connected pieces
    labelled 1.. (0: outside the mask, no depth, or on a jump), and the mask's depth (0 elsewhere)."""
    z = np.where(mask & np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    region = ((z > 0) & ~depth_edges(cv2.medianBlur(z, 5), rel=EDGE_REL, floor=EDGE_FLOOR)).astype(np.uint8)
    count, labels = cv2.connectedComponents(region, connectivity=4)
    return count, labels, z


def with_edge(labels: np.ndarray, i: int, mask: np.ndarray) -> np.ndarray:
    """Patch `i` and the edge pixels around it (the jump it was split off at), within the mask."""
    return (cv2.dilate((labels == i).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0) & mask


def largest_patches(depth: np.ndarray, mask: np.ndarray, k: int, patches=None) -> list[np.ndarray]:
    """The `k` largest pieces of the mask split where the depth jumps (each at least MIN_READING_SHARE of
    it), largest first: the base and what stands in front of or beside it at another depth. `patches`:
    depth_patches(depth, mask) when already split."""
    count, labels, z = patches if patches is not None else depth_patches(depth, mask)
    if count <= 2:
        return []  # one piece: nothing to leave out
    sizes = np.bincount(labels.ravel(), minlength=count)
    sizes[0] = 0
    total = int((z > 0).sum())
    order = [i for i in np.argsort(-sizes, kind="stable")[:k] if sizes[i] >= MIN_READING_SHARE * total]
    return [with_edge(labels, i, mask) for i in order]


def front_most(depth: np.ndarray, mask: np.ndarray, patches=None) -> np.ndarray:
    """(H, W) bool: the mask's depth patches (at least MIN_FRONT_SHARE of it) that stand in front of another
    of its patches where the two meet, and behind none, with the edge pixels around them. Where two patches
    meet (within BORDER_PX across the jump), the nearer is the one whose median depth there is smaller by
    more than the jump that split them. An occluder between the camera and a mostly hidden base is the
    front-most; the base behind it is not, even when it stands in front of something further back.
    `patches`: depth_patches(depth, mask) when already split."""
    count, labels, z = patches if patches is not None else depth_patches(depth, mask)
    out = np.zeros(mask.shape, bool)
    if count <= 2:
        return out
    sizes = np.bincount(labels.ravel(), minlength=count)
    big = [i for i in range(1, count) if sizes[i] >= max(MIN_POINTS, MIN_FRONT_SHARE * sizes[1:].sum())]
    if len(big) < 2:
        return out
    kernel = np.ones((2 * BORDER_PX + 1, 2 * BORDER_PX + 1), np.uint8)
    near = {i: cv2.dilate((labels == i).astype(np.uint8), kernel) > 0 for i in big}
    in_front_of: dict[int, set[int]] = {i: set() for i in big}
    behind: dict[int, set[int]] = {i: set() for i in big}
    for n, a in enumerate(big):
        for b in big[n + 1:]:
            meet = near[a] & near[b]
            za, zb = z[meet & (labels == a)], z[meet & (labels == b)]
            if len(za) < 5 or len(zb) < 5:
                continue  # they do not meet
            da, db = float(np.median(za)), float(np.median(zb))
            jump = max(EDGE_FLOOR, EDGE_REL * max(da, db))
            if da < db - jump:
                in_front_of[a].add(b)
                behind[b].add(a)
            elif db < da - jump:
                in_front_of[b].add(a)
                behind[a].add(b)
    for i in big:
        if in_front_of[i] and not behind[i]:
            out |= with_edge(labels, i, mask)
    return out


def explained(result: RegistrationResult, view: View, base: BaseObject, region: np.ndarray | None = None) -> float:
    """How well `result`'s pose explains the frame: pixels of `region` (default `view.mask`) whose depth
    the model's surface there confirms (within the agreement tolerance), less CONTRADICTION_WEIGHT times
    the pixels anywhere where the camera sees past the model's surface (its outline's 2 px left out: mixed
    pixels) or where it shows the base far outside the prompt's box. -inf for a failed result. Comparable
    across readings of one mask when `region` holds them all (the mask as given and every reading)."""
    if not result.ok or result.T_world_base is None:
        return float("-inf")
    seen, _ = raycast_source(base, result.T_world_base, view.T_world_camera, view.camera)
    # every pixel counted below is one the model shows: the window round them (wider than the outline's margin,
    # so that mask_edge reads there as in the whole image) gives the same counts as the whole image
    zbuf, box = depth_window(seen, view.T_world_camera, view.camera, MASK_MARGIN_PX + 2)
    if box is None:  # (fewer than 3 of its points in the image) the model is not in view
        return float("-inf")
    win = np.s_[box[0]:box[1], box[2]:box[3]]
    shown = np.isfinite(zbuf)
    d = view.depth[win]
    valid = shown & np.isfinite(d) & (d > 0)
    tol = agreement_tolerance(result.voxel, result.depth_noise)
    with np.errstate(invalid="ignore"):
        confirmed = valid & (view.mask if region is None else region)[win] & (np.abs(d - zbuf) < tol)
        past = valid & (d > zbuf + tol) & ~mask_edge(shown)
        outside = view.outside_box()
        if outside is not None:  # shown where the user's box says the base is not (and nothing nearer hides it)
            past |= shown & outside[win] & ~(valid & (d < zbuf - tol))
    return float(confirmed.sum()) - CONTRADICTION_WEIGHT * float(past.sum())


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum()) / float(union) if union else 1.0
