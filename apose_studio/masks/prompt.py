"""Prompted masks on cluttered benches, with no training: the user (or a detector) gives a 2D box or a
click on the base object, and the mask follows from depth and colour.

1. The table plane is fitted (seeded RANSAC, `plane.fit_plane`) and removed.
2. Depth discontinuities are hard borders: what stands on the table splits into surface patches
   where the (median-filtered) depth jumps.
3. The patches the prompt picks (the clicked one; those mostly inside the box) seed OpenCV's GrabCut
   as "probably the object", the rest of the box as "probably not", the table and everything outside
   the box as "surely not". GrabCut's colour models then cut what depth cannot: an object standing
   against the base at the same depth.
4. The result keeps only pixels above the table (or without depth: sensor holes on the object), as
   one connected piece around the prompt.

Pixels (u, v) are image columns and rows; a box is (x0, y0, x1, y1) with x1, y1 exclusive.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from apose_studio.errors import AposeError
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.noise import depth_edges
from apose_studio.geometry.plane import fit_table

MIN_PATCH_PX = 20  # depth patches smaller than this are noise


class PromptError(AposeError):
    """A prompt that cannot pick an object: a box off the image, a click on the table or on no depth."""


@dataclass
class PromptedMask:
    mask: np.ndarray  # (H, W) bool
    method: str  # "depth+colour" or "depth"
    seconds: float
    notes: list[str] = field(default_factory=list)


def parse_box(text: str, where: str = "--box") -> tuple[int, int, int, int]:
    """'x0,y0,x1,y1' (pixels) -> a box; PromptError naming `where` the text came from (the flag, or the studio's
    field: a page's user never typed --box) otherwise."""
    try:
        x0, y0, x1, y1 = (int(round(float(t))) for t in text.split(","))
    except (ValueError, OverflowError):  # OverflowError: inf, 1e309
        raise PromptError(f"{where} {text}: expected four pixel numbers x0,y0,x1,y1 (left, top, right, bottom)") from None
    return x0, y0, x1, y1


def parse_point(text: str, where: str = "--point") -> tuple[int, int]:
    """'u,v' (pixels) -> a point; PromptError naming `where` the text came from otherwise."""
    try:
        u, v = (int(round(float(t))) for t in text.split(","))
    except (ValueError, OverflowError):  # OverflowError: inf, 1e309
        raise PromptError(f"{where} {text}: expected two pixel numbers u,v (column, row)") from None
    return u, v


MIN_BOX_PX = 4  # a box narrower than this holds no object to segment


def check_box(box, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The box clipped to the image; PromptError when it is empty, inverted or (mostly) off the image."""
    h, w = shape
    x0, y0, x1, y1 = (int(v) for v in box)
    if x1 <= x0 or y1 <= y0:
        # what was likely meant: corners given the other way round (a box dragged up from its bottom right), or a
        # COCO/BOP bbox's width and height; each offered only where it makes a box that lies in the image
        swapped = (min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
        sized = (x0, y0, x0 + x1, y0 + y1)
        hints = []
        if x0 != x1 and y0 != y1 and swapped[0] >= 0 and swapped[1] >= 0 and swapped[2] <= w and swapped[3] <= h:
            hints.append("if its corners are the other way round, the box is " + ",".join(map(str, swapped)))
        if x1 > 0 and y1 > 0 and x0 >= 0 and y0 >= 0 and sized[2] <= w and sized[3] <= h:
            hints.append(f"if {x1},{y1} are its width and height (x,y,w,h, as a COCO or BOP bbox gives it), the box is "
                         + ",".join(map(str, sized)))
        raise PromptError(f"box {x0},{y0},{x1},{y1}: expected x0 < x1 and y0 < y1 (left, top, right, bottom in "
                          f"pixels)" + "".join("; " + t for t in hints))
    if (x1 - x0 < MIN_BOX_PX or y1 - y0 < MIN_BOX_PX) and 0 <= x0 and x1 <= w and 0 <= y0 and y1 <= h:
        raise PromptError(f"box {x0},{y0},{x1},{y1} is {x1 - x0}x{y1 - y0} pixels; draw it around the whole object "
                          f"(at least {MIN_BOX_PX}x{MIN_BOX_PX} pixels), or click on the object instead")
    cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if cx1 - cx0 < MIN_BOX_PX or cy1 - cy0 < MIN_BOX_PX or (cx1 - cx0) * (cy1 - cy0) < 0.5 * (x1 - x0) * (y1 - y0):
        raise PromptError(f"box {x0},{y0},{x1},{y1} lies outside the {w}x{h} image (or mostly so); give it in this "
                          "image's pixels")
    return cx0, cy0, cx1, cy1


@dataclass
class Surfaces:
    """The depth image split into surface patches standing on the table."""

    labels: np.ndarray  # (H, W) int32 patch id, 0 = none (table, no depth, an edge)
    table: np.ndarray  # (H, W) bool: on the table plane
    above: np.ndarray  # (H, W) bool: valid depth above the table
    valid: np.ndarray  # (H, W) bool: depth present
    specks: np.ndarray  # (H, W) bool: patches under MIN_PATCH_PX (specks of valid depth amid sensor holes)


def surfaces(depth: np.ndarray, cam: CameraIntrinsics) -> Surfaces:
    """Table plane removed (`plane.fit_table`), the rest cut at depth discontinuities."""
    h, w = depth.shape
    z = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    valid = z > 0
    table = np.zeros((h, w), bool)
    above = valid.copy()
    fit = fit_table(z, cam)
    if fit is not None and fit.plane is not None:
        height = fit.heights()
        table[fit.vs, fit.us] = height <= fit.tol
        above[fit.vs, fit.us] = height > fit.tol
    smooth = cv2.medianBlur(z, 5)
    smooth = np.where(valid, smooth, 0)
    edges = depth_edges(smooth, rel=0.012, floor=0.004) & valid
    region = (above & ~edges).astype(np.uint8)
    _, labels = cv2.connectedComponents(region, connectivity=4)
    small = np.bincount(labels.ravel()) < MIN_PATCH_PX
    small[0] = False
    return Surfaces(labels.astype(np.int32), table, above, valid, small[labels])


def _seed_patches(s: Surfaces, box, point, shown=None) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) bool twice: the patches the prompt picks (clipped to the box), and those of them that
    lie wholly in the box (a clicked patch counts as whole). `shown`: the box as the user gave it, for messages
    (`box` is in the window's pixels)."""
    h, w = s.labels.shape
    if point is not None:
        u, v = point
        if not (0 <= u < w and 0 <= v < h):
            raise PromptError(f"point {u},{v} lies outside the {w}x{h} image; give it in this image's pixels")
        win = s.labels[max(v - 4, 0):v + 5, max(u - 4, 0):u + 5]
        ids, counts = np.unique(win[win > 0], return_counts=True)
        if not len(ids):
            if not s.valid[v, u]:
                raise PromptError(f"point {u},{v} falls on a pixel without depth (a sensor hole); click on the object "
                                  "where it has depth")
            if s.table[v, u]:
                raise PromptError(f"point {u},{v} falls on the table, not on an object standing on it; click on the object")
            raise PromptError(f"point {u},{v} falls on a depth edge; click inside the object")
        picked = s.labels == ids[np.argmax(counts)]
        return picked, picked
    x0, y0, x1, y1 = box
    inside = np.zeros((h, w), bool)
    inside[y0:y1, x0:x1] = True
    n = int(s.labels.max()) + 1
    total = np.bincount(s.labels.ravel(), minlength=n)
    within = np.bincount(s.labels[inside], minlength=n)
    # a patch mostly inside the box, or a big piece of the box (the base merged with something touching
    # it at the same depth: the box's part of it is the seed, colour cuts the rest)
    pick = (within >= MIN_PATCH_PX) & ((within >= 0.5 * total) | (within >= 0.1 * inside.sum()))
    pick[0] = False
    if not pick.any():
        raise PromptError(f"box {shown or ','.join(map(str, box))} holds nothing standing on the table (only table, or "
                          "no depth); "
                          "draw it around the object")
    whole = pick & (within >= 0.9 * total)
    return pick[s.labels] & inside, whole[s.labels]


def _largest_near(mask: np.ndarray, seed: np.ndarray, gap: int = 9) -> np.ndarray:
    """The pieces of `mask` around the one that overlaps `seed` most: pieces closer than `gap` pixels
    count as one (an object's patches are split by its own depth edges); groups with under 20 % of the
    best group's overlap leave."""
    grouped = cv2.dilate(mask.astype(np.uint8), np.ones((gap, gap), np.uint8))
    n, lab = cv2.connectedComponents(grouped, connectivity=8)
    if n <= 1:
        return mask
    overlap = np.bincount(lab[seed & mask], minlength=n)
    overlap[0] = 0
    if overlap.max() == 0:
        return mask
    return np.isin(lab, np.flatnonzero(overlap >= 0.2 * overlap.max())) & mask


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """The mask with every region it encloses filled (the low floor of a housing, a gap inside the object)."""
    pad = np.pad(mask, 1).astype(np.uint8)
    flood = pad.copy()
    cv2.floodFill(flood, np.zeros((pad.shape[0] + 2, pad.shape[1] + 2), np.uint8), (0, 0), 2)
    return (flood != 2)[1:-1, 1:-1]


def _nearer_colour(lab: np.ndarray, query: np.ndarray, ours: np.ndarray, theirs: np.ndarray) -> np.ndarray:
    """(H, W) bool over `query` pixels: nearer (Lab, mean distance to the 5 nearest of up to 2000 samples)
    to the colours of the `ours` pixels than to those of `theirs`, decided per little area (5x5 median),
    not per noisy pixel. Each distinct colour (to 4 levels per channel) is looked up once."""
    rng = np.random.default_rng(0)

    def samples(m: np.ndarray) -> np.ndarray:
        c = lab[m].astype(np.float32)
        return c[rng.choice(len(c), min(len(c), 2000), replace=False)]

    cells = lab[query] // 4
    key = (cells[:, 0].astype(np.int32) * 64 + cells[:, 1]) * 64 + cells[:, 2]
    uniq, inverse = np.unique(key, return_inverse=True)
    centres = np.stack([uniq // 4096, (uniq // 64) % 64, uniq % 64], axis=1).astype(np.float32) * 4 + 1.5
    d_ours = cKDTree(samples(ours)).query(centres, k=5)[0].mean(axis=1)
    d_theirs = cKDTree(samples(theirs)).query(centres, k=5)[0].mean(axis=1)
    out = np.zeros(query.shape, np.uint8)
    out[query] = (d_ours <= d_theirs)[inverse].astype(np.uint8) * 255
    return (cv2.medianBlur(out, 5) > 127) & query


def sensor_holes(mask: np.ndarray, s: Surfaces, in_box: np.ndarray, lab: np.ndarray) -> np.ndarray:
    """Pixels the depth cannot place that belong to the object: in the box, off the table, without depth
    or with only specks of it (no patch), reached from the mask through such pixels, and nearer the
    object's colours than the table's (a dark or glossy surface the sensor barely sees, as Kinect on a
    black motor)."""
    holes = in_box & ~s.table & (~s.valid | (s.labels == 0) | s.specks)
    # the table's colours from table pixels with table all round: the foot of an object, within the
    # plane's tolerance of the table, is labelled table but has the object's colour (a black motor's
    # lower sides taught "table" its own black and kept its sensor holes out of the mask)
    table = (cv2.erode(s.table.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0) & in_box
    if not holes.any() or mask.sum() < 20 or table.sum() < 20:
        return np.zeros_like(mask)
    like = _nearer_colour(lab, holes, mask & s.valid, table)
    n, comp = cv2.connectedComponents((like | mask).astype(np.uint8), connectivity=8)
    keep = np.unique(comp[mask])
    return like & np.isin(comp, keep[keep > 0])


def complete(mask: np.ndarray, s: Surfaces, in_box: np.ndarray, lab: np.ndarray | None = None) -> np.ndarray:
    """What depth patches miss of an object: its rim (depth edges, steep faces and sensor holes next to
    it, up to 2 % of the box's diagonal), larger holes in its depth that look like it (with `lab`, the
    image in Lab colours), and what it encloses (a housing's floor near table height), closed over small
    gaps; never another patch that the mask does not touch."""
    free = (s.labels == 0) & s.valid & ~s.table & in_box  # holes join by colour only (a projector's shadow is table)
    m = mask.copy()
    if lab is not None:
        m |= sensor_holes(mask, s, in_box, lab)
    k3 = np.ones((3, 3), np.uint8)
    ys, xs = np.nonzero(in_box)
    diagonal = float(np.hypot(np.ptp(xs) + 1, np.ptp(ys) + 1))
    for _ in range(max(3, int(0.02 * diagonal))):
        m |= (cv2.dilate(m.astype(np.uint8), k3) > 0) & free
    size = max(5, int(0.03 * diagonal) | 1)

    def close(k: int) -> np.ndarray:
        return cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0

    closed, bridged = close(size), close(3 * size)  # bridged: gaps in a rim up to ~9 % of the box closed
    out = (closed | (fill_holes(bridged) & ~bridged)) & in_box  # plus what the bridged rim encloses
    touched = np.unique(s.labels[m & (s.labels > 0)])
    other = (s.labels > 0) & ~np.isin(s.labels, touched) & ~s.specks
    return out & ~other


def box_depth(depth: np.ndarray, box) -> np.ndarray:
    """(H, W) bool: the pixels of `box` (checked) with depth. The target of a base that is a region of a larger
    part (a part's `roi`): the region is the part's own surface running on, of its colour and at its depth, so
    neither the patches nor the colour cut can tell it from the rest of the part, and in a box around a seat on an
    engine head the deck is the widest plane, which the table fit takes for the table. The registration counts
    only what lies in the region at a pose (registration.base.BaseObject.belongs)."""
    h, w = depth.shape
    x0, y0, x1, y1 = check_box(box, (h, w))
    out = np.zeros((h, w), bool)
    out[y0:y1, x0:x1] = np.isfinite(depth[y0:y1, x0:x1]) & (depth[y0:y1, x0:x1] > 0)
    return out


def prompted_mask(rgb: np.ndarray, depth: np.ndarray, cam: CameraIntrinsics, box=None, point=None,
                  colour: bool = True, region: bool = False) -> PromptedMask:
    """The base object's mask from a box (x0, y0, x1, y1) or a click (u, v). `colour=False`: depth
    patches only. A box is worked on in a window around it (the box and one box size on every side:
    enough table for the plane, and where touching things run out of the box), a click on the image.
    `region`: the base is a region of a larger part (an roi): the box's pixels with depth (box_depth); a
    click cannot say how far a region reaches, and is refused."""
    t0 = time.perf_counter()
    h, w = depth.shape
    if rgb.shape[:2] != (h, w):
        raise PromptError(f"RGB is {rgb.shape[1]}x{rgb.shape[0]} but depth is {w}x{h}; align depth to colour first")
    if box is None and point is None:
        raise PromptError("give a box (x0,y0,x1,y1) or a point (u,v) on the object")
    if box is not None and point is not None:  # (the box alone was used, the point dropped unsaid: the API, serve's pick)
        raise PromptError("a box and a point: give one prompt, a box (x0,y0,x1,y1) round the object or a point (u,v) on it")
    if region:
        if box is None:
            raise PromptError(f"point {point[0]},{point[1]}: this step's base is a region of a larger part (its roi), and "
                              "a click cannot say how far the region reaches; draw a box around the region instead")
        mask = box_depth(depth, box)
        if mask.sum() < MIN_PATCH_PX:
            raise PromptError(f"box {','.join(map(str, box))} holds {int(mask.sum())} pixels with depth; draw it around "
                              "the region where the camera sees depth")
        return PromptedMask(mask, "region box", time.perf_counter() - t0)
    if box is None:
        out = _prompted(rgb, depth, cam, None, tuple(int(v) for v in point), colour)
    else:
        x0, y0, x1, y1 = check_box(box, (h, w))
        shown = ",".join(str(int(v)) for v in box)  # as given; where the image cut it, the part used too
        if (x0, y0, x1, y1) != tuple(int(v) for v in box):
            shown += f" (within the {w}x{h} image: {x0},{y0},{x1},{y1})"
        m = max(x1 - x0, y1 - y0)
        wx0, wy0, wx1, wy1 = max(x0 - m, 0), max(y0 - m, 0), min(x1 + m, w), min(y1 + m, h)
        sub_cam = replace(cam, width=wx1 - wx0, height=wy1 - wy0, cx=cam.cx - wx0, cy=cam.cy - wy0)
        out = _prompted(rgb[wy0:wy1, wx0:wx1], depth[wy0:wy1, wx0:wx1], sub_cam,
                        (x0 - wx0, y0 - wy0, x1 - wx0, y1 - wy0), None, colour, shown=shown)
        full = np.zeros((h, w), bool)
        full[wy0:wy1, wx0:wx1] = out.mask
        out.mask = full
    out.seconds = time.perf_counter() - t0
    return out


def _prompted(rgb, depth, cam, box, point, colour: bool, shown=None) -> PromptedMask:
    """prompted_mask on an image (or a window of it); its caller times it."""
    h, w = depth.shape
    s = surfaces(depth, cam)
    if box is None:  # a click: the clicked patch, then the patches in a box around it (its extent and a margin)
        clicked, _ = _seed_patches(s, None, point)
        ys, xs = np.nonzero(clicked)
        mx, my = int(0.15 * (np.ptp(xs) + 1)) + 4, int(0.15 * (np.ptp(ys) + 1)) + 4
        box = (max(xs.min() - mx, 0), max(ys.min() - my, 0), min(xs.max() + 1 + mx, w), min(ys.max() + 1 + my, h))
        seed, whole = _seed_patches(s, box, None, shown)
        seed, whole = seed | clicked, whole | clicked
    else:
        seed, whole = _seed_patches(s, box, None, shown)
    x0, y0, x1, y1 = box
    in_box = np.zeros((h, w), bool)
    in_box[y0:y1, x0:x1] = True
    depth_only = _largest_near(seed & in_box, seed)
    merged = seed & ~whole  # patches that run out of the box: the base and something touching it
    if not colour:
        return PromptedMask(complete(depth_only, s, in_box), "depth", 0.0)
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB)
    if not merged.any():
        return PromptedMask(complete(depth_only, s, in_box, lab), "depth+colour", 0.0)
    # colour decides the merged patches only. The other thing's colours: its pixels outside the box. The
    # object's: the patches wholly in the box, and the merged pixels deep inside the box (far from where
    # the other thing comes in). Each merged pixel in the box goes to the nearer colour.
    ids = np.unique(s.labels[merged])
    other = np.isin(s.labels, ids) & ~in_box
    reach = cv2.distanceTransform((~other).astype(np.uint8), cv2.DIST_L2, 3)
    deep = merged & (reach > 0.25 * max(x1 - x0, y1 - y0))
    if (whole | deep).sum() < 20 or other.sum() < 20:
        return PromptedMask(complete(depth_only, s, in_box, lab), "depth", 0.0,
                            ["too few pixels to learn colours from; the depth patches are the mask"])
    drop = merged & ~_nearer_colour(lab, merged, whole | deep, other)
    fg = _largest_near(depth_only & ~drop, seed & ~drop)
    return PromptedMask(complete(fg, s, in_box, lab), "depth+colour", 0.0)
