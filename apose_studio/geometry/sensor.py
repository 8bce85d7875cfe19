"""The depth sensor, modelled from the frame itself: how coarsely it quantises depth where the object
is (no calibration file: a Kinect v1 reads in disparity steps that grow with z squared, most sensors in
whole millimetres, a render in 0.1 mm), and how far its depth image lies shifted against the colour
image it was registered to (a Kinect's registration is a few pixels off). With the noise measured from
the depth's second differences (noise.estimate_depth_noise) the step sets how far a model surface may lie
from the depth and still agree. Pure functions of numpy arrays; metres, pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from apose_studio.geometry.camera import box_region


def nearest_within(z: np.ndarray, px: int) -> np.ndarray:
    """(H, W) float32: the least of `z` (a depth image, inf where none) within `px` pixels of each pixel (the
    (2 px + 1)-wide square round it): the nearer surface winning, a model's depth widened by px, a splat's gaps
    closed. Beyond the image's edge there is nothing (inf). OpenCV's own border for a float erosion is FLT_MAX, a
    finite depth: the outermost px pixels of every image or window would read as 3e38 m away, finite, so a
    silhouette's or a window's edge would count as shown."""
    return cv2.erode(np.asarray(z, np.float32), np.ones((2 * px + 1, 2 * px + 1), np.uint8),
                     borderType=cv2.BORDER_CONSTANT, borderValue=float("inf"))


def quantisation_step(depth: np.ndarray, region: np.ndarray) -> float:
    """The sensor's depth step at the region's depth (metres): the median gap between neighbouring distinct
    depth values there (a Kinect v1 reads in disparity steps, about 3 mm apart at 1 m; most sensors in
    whole millimetres). 0 when too few distinct values are seen (a fine or float depth)."""
    d = depth[region & np.isfinite(depth) & (depth > 0)]
    if len(d) < 200:
        return 0.0
    lo, hi = np.percentile(d, [10, 90])
    values = np.unique(np.round(d[(d >= lo) & (d <= hi)], 6))
    if len(values) < 8:
        return float(np.median(np.diff(values))) if len(values) > 1 else 0.0
    counts = len(d) / len(values)
    return float(np.median(np.diff(values))) if counts >= 4 else 0.0  # sparse values: not steps but noise


def shift_image(image: np.ndarray, du: int, dv: int) -> np.ndarray:
    """image moved du pixels right and dv down; what comes in at the border is 0 (no depth)."""
    out = np.zeros_like(image)
    h, w = image.shape[:2]
    out[max(dv, 0):h + min(dv, 0), max(du, 0):w + min(du, 0)] = image[max(-dv, 0):h + min(-dv, 0), max(-du, 0):w + min(-du, 0)]
    return out


SHIFT_MAX_PX = 6  # the misregistration searched for, each way
BLEED_MAX_PX = 3  # ... and how far near surfaces may bleed into far ones beside it (shift_and_bleed)
SHIFT_MIN_PX = 2  # a shift found shorter than this (along both axes) is not applied: edge bleeding alone (a Kinect's
# near surfaces reach a pixel into far ones, and the camera sees more top and right edges than others) moved
# the depth's edges by (1, -1) against the colour's on renders registered exactly
SHIFT_GAIN = 0.8  # ... nor one whose edges lie no nearer the colour's than this share of their distance unshifted
SHIFT_MIN_EDGES = 100  # fewer depth-edge pixels than this in the window: nothing to align
EDGE_DIST_CAP_PX = 5.0  # a depth edge farther than this from any colour edge counts this far (edges of one image only)
WINDOW_MARGIN_PX = 40  # the edges are compared in the prompt's box this much wider per side
COLOUR_PAD_PX = 40  # the colour image's edges are found this far round the depth's edges (see depth_colour_shift)
MAX_EDGE_PX = 20000  # at most this many depth-edge pixels are compared (every k-th in image order beyond): a box over a
# whole noisy 1080p frame held a million, and 169 shifts of them took 3 s


def colour_edge_distance(rgb: np.ndarray, explained: np.ndarray | None = None) -> np.ndarray:
    """(H, W) float32: each pixel's distance to the nearest colour edge (Canny on the grey image, blurred 3x3),
    capped at EDGE_DIST_CAP_PX. `explained` ((H, W) bool, or None): colour edges within a pixel of these are left
    out (an object's own creases and inner outlines, raycast.own_edges: shading changes there anyway)."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb[..., :3], dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    colour = cv2.Canny(cv2.GaussianBlur(grey, (3, 3), 0), 40, 100) > 0
    if explained is not None and explained.any():
        colour &= cv2.dilate(explained.astype(np.uint8), np.ones((3, 3), np.uint8)) == 0
    return np.minimum(cv2.distanceTransform((~colour).astype(np.uint8), cv2.DIST_L2, 3), EDGE_DIST_CAP_PX)


def depth_jump(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Where neighbouring depths a and b (metres) lie apart by more than 4 mm or 1.2 % of the nearer: an outline
    (occluding_edges; raycast.own_edges for a model's inner outlines)."""
    return np.abs(a - b) > np.maximum(0.004, 0.012 * np.minimum(a, b))


def occluding_edges(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: the near side of each depth jump between two valid neighbours (median-filtered 5x5; a jump
    larger than 4 mm or 1.2 % of the depth): an object's outline as the depth sees it. Holes (no depth) make no
    edge: a Kinect's projector shadows and dropouts lie beside outlines, not on them."""
    return occluding_edges_toward(depth)[0]


def occluding_edges_toward(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(edges, sx, sy): occluding_edges, and at each of its pixels which way the farther surface lies (int8: sx +1
    right, -1 left, sy +1 down, -1 up; 0 where neither way, or both ways). A sensor that bleeds near surfaces into
    far ones moves each outline that way (noise.bleed); a misregistration moves every outline alike."""
    valid = np.isfinite(depth) & (depth > 0)
    z = np.where(valid, depth, 0).astype(np.float32)
    z = np.where(valid, cv2.medianBlur(z, 5), 0)
    valid &= z > 0
    edges = np.zeros(z.shape, bool)
    sx, sy = np.zeros(z.shape, np.int8), np.zeros(z.shape, np.int8)
    a, b = z[:, :-1], z[:, 1:]  # left and right neighbours
    jump = valid[:, :-1] & valid[:, 1:] & depth_jump(a, b)
    near_a, near_b = jump & (a < b), jump & (b < a)
    edges[:, :-1] |= near_a
    edges[:, 1:] |= near_b
    sx[:, :-1] += near_a
    sx[:, 1:] -= near_b
    a, b = z[:-1], z[1:]  # upper and lower neighbours
    jump = valid[:-1] & valid[1:] & depth_jump(a, b)
    near_a, near_b = jump & (a < b), jump & (b < a)
    edges[:-1] |= near_a
    edges[1:] |= near_b
    sy[:-1] += near_a
    sy[1:] -= near_b
    return edges, sx, sy


def depth_colour_shift(rgb: np.ndarray, depth: np.ndarray, box: tuple[int, int, int, int] | None = None) -> tuple[int, int]:
    """(du, dv): how many pixels right and down the depth image lies shifted against the colour image (the
    depth at (u, v) shows what the colour shows at (u - du, v - dv)); (0, 0) when no shift is clear
    (shift_evidence, gated by SHIFT_MIN_PX and SHIFT_GAIN): the edges compared as a shift alone must find it, and
    compared allowing a bleed of the depth's outlines too, to within a pixel each way (that one's shift is returned:
    a bleed explains a pixel of the alone's); a shift the bleed explains away is none, and a bleed never suggests a
    shift the edges alone do not (shift_looks)."""
    def gated(du: int, dv: int, ratio: float) -> bool:
        return max(abs(du), abs(dv)) >= SHIFT_MIN_PX and ratio < SHIFT_GAIN

    confirmed = shift_looks(rgb, depth, box, None, gated)[1]
    return (0, 0) if confirmed is None else confirmed[0]


Shift = tuple[tuple[int, int], float]  # ((du, dv), ratio): a shift of the depth against the colour, as shift_evidence


def shift_looks(rgb: np.ndarray, depth: np.ndarray, box, explained: np.ndarray | None,
                gate) -> tuple[Shift | None, Shift | None]:
    """(alone, confirmed): the shift the edges compared as a shift alone find, when `gate(du, dv, ratio)` passes it;
    and that shift as the comparison allowing a bleed too (shift_and_bleed) confirms it: passed by the gate and
    within a pixel of the alone's each way (its shift, exact where the alone's is a pixel off toward the bleed).
    Either None where there is none. Both comparisons read the same edges, prepared once (EdgeComparison); the one
    beside a bleed is made only where the alone's passes."""
    comparison = EdgeComparison(rgb, depth, box, explained)
    (du, dv), _, ratio = comparison.search(0)
    if not gate(du, dv, ratio):
        return None, None
    (bu, bv), _, b_ratio = comparison.search()
    confirmed = ((bu, bv), b_ratio) if gate(bu, bv, b_ratio) and max(abs(bu - du), abs(bv - dv)) <= 1 else None
    return ((du, dv), ratio), confirmed


def shift_evidence(rgb: np.ndarray, depth: np.ndarray, box: tuple[int, int, int, int] | None = None,
                   explained: np.ndarray | None = None, bleed: bool = True) -> tuple[tuple[int, int], float]:
    """((du, dv), ratio): the shift of the depth image against the colour image that lays their edges nearest,
    and their mean distance there over unshifted (1.0, and (0, 0), when there is nothing to compare).

    The depth's occluding edges are compared with the colour's edges (Canny) in `box` (the prompt's, wider by
    WINDOW_MARGIN_PX; None: the whole image) for every shift up to SHIFT_MAX_PX each way: the shift whose depth
    edges lie nearest the colour's (their mean distance, each capped at EDGE_DIST_CAP_PX) wins; depth_colour_shift
    takes it if it is at least SHIFT_MIN_PX long and brings them nearer by SHIFT_GAIN. Measured on
    benchmarks/captures.py's renders with the prompt's box: on the `real` row (depth registered 3 px off) the shift of 23 of 24 frames found to
    within a pixel along each axis; on the 504 frames of the other rows (registered exactly) a shift found on
    13, 6 of them gearbox frames under Kinect-like noise (near surfaces bleeding into far ones, projector
    shadows hiding one side of each object), so it is applied only when asked (estimation.colour_registered).
    Over the whole image instead of the box, 9 of the 24 were missed and desk frames without noise shifted.
    With a box the depth's edges are found in the window alone (their filters reach 3 px: the window is read
    4 px wider); the colour's over the whole image (Canny's hysteresis follows an edge beyond any window).
    `explained` ((H, W) bool): colour edges that say nothing about the shift, left out (colour_edge_distance):
    the base's own creases and inner outlines at its estimated pose (estimation.colour_checked)."""
    (du, dv), _, ratio = shift_and_bleed(rgb, depth, box, explained, BLEED_MAX_PX if bleed else 0)
    return (du, dv), ratio


def shift_and_bleed(rgb: np.ndarray, depth: np.ndarray, box: tuple[int, int, int, int] | None = None,
                    explained: np.ndarray | None = None, bleed_max: int | None = None) -> tuple[tuple[int, int], int, float]:
    """((du, dv), bleed, ratio): shift_evidence's search, the depth's outlines allowed to lie up to BLEED_MAX_PX
    pixels beyond the colour's too, each toward whatever lies behind it (occluding_edges_toward): a sensor's
    correlation window bleeds near surfaces into far ones (noise.bleed). A shift moves every outline alike; a bleed
    moves each away from its own near surface, so a Kinect-like frame registered exactly, its outlines bled right
    and up (the projector's shadow leaves no outline on an object's left, the table none at its foot), showed a
    "shift" of 2-3 px and moved its depth by it (benchmarks/captures.py's `bleed` row: four confident poses 2-5 mm
    off). Where only the outline's ways bleed and shift cannot tell apart, the shorter shift wins (ties: the
    shortest shift, then the least bleed). Used to confirm a shift the edges alone show, never to suggest one
    (depth_colour_shift, estimation.edge_look): joined with a shift, a bleed can explain edges neither
    explains alone. `ratio`: the best shift's mean distance over the best with no shift.
    `bleed_max`: the most bleed tried (default BLEED_MAX_PX; 0: a shift alone, as shift_evidence(bleed=False))."""
    return EdgeComparison(rgb, depth, box, explained).search(bleed_max)


class EdgeComparison:
    """shift_and_bleed's inputs, prepared once for several searches (a shift alone, then beside a bleed:
    shift_looks): the depth's occluding edges in the window (their pixels and which way each one's far side lies) and
    the colour image's edge distances round them. The searches' scores are kept per bleed, so a second search
    repeats none of the first's work; each search returns what shift_and_bleed alone returns, to the bit."""

    def __init__(self, rgb: np.ndarray, depth: np.ndarray, box: tuple[int, int, int, int] | None = None,
                 explained: np.ndarray | None = None):
        self.ready = False
        self._scores: dict[tuple[int, bool], dict[tuple[int, int], float]] = {}
        if rgb is None or rgb.ndim != 3:
            return
        h, w = depth.shape
        if box is None:
            edges, sxs, sys_ = occluding_edges_toward(depth)
            vs, us = np.nonzero(edges)
            sx, sy = sxs[vs, us], sys_[vs, us]
        else:
            x0, y0, x1, y1 = (int(v) for v in box)
            m = WINDOW_MARGIN_PX
            cx0, cy0, cx1, cy1 = max(x0 - m - 4, 0), max(y0 - m - 4, 0), min(x1 + m + 4, w), min(y1 + m + 4, h)
            if cx1 <= cx0 or cy1 <= cy0:
                return
            edges, sxs, sys_ = occluding_edges_toward(depth[cy0:cy1, cx0:cx1])
            edges &= box_region(edges.shape, (x0 - cx0, y0 - cy0, x1 - cx0, y1 - cy0), m)
            vs, us = np.nonzero(edges)
            sx, sy = sxs[vs, us], sys_[vs, us]
            vs, us = vs + cy0, us + cx0
        if len(us) < SHIFT_MIN_EDGES:
            return
        if len(us) > MAX_EDGE_PX:
            step = -(-len(us) // MAX_EDGE_PX)
            vs, us, sx, sy = vs[::step], us[::step], sx[::step], sy[::step]
        # the colour's edges in the edges' box, COLOUR_PAD_PX wider (the filters and the distance transform then
        # read the same there as over the whole image, but where Canny's hysteresis follows an edge from afar)
        p = COLOUR_PAD_PX
        cx0, cy0 = max(int(us.min()) - p, 0), max(int(vs.min()) - p, 0)
        cx1, cy1 = min(int(us.max()) + p + 1, w), min(int(vs.max()) + p + 1, h)
        self.dist = colour_edge_distance(rgb[cy0:cy1, cx0:cx1],
                                         None if explained is None else explained[cy0:cy1, cx0:cx1])
        self.us, self.vs, self.w, self.h = us - cx0, vs - cy0, cx1 - cx0, cy1 - cy0
        self.sx, self.sy = sx.astype(np.int64), sy.astype(np.int64)
        self.flat, self.at = self.dist.ravel(), self.vs * self.w + self.us
        self.ready = True

    def _clear(self, r: int) -> bool:
        """No move of up to r pixels takes an edge out of the colour's crop."""
        return bool(self.us.min() >= r and self.vs.min() >= r and self.us.max() < self.w - r and self.vs.max() < self.h - r)

    def _scored(self, k: int, clear: bool) -> dict[tuple[int, int], float]:
        """The mean capped distance of the edges moved by every shift and a bleed of k pixels."""
        key = (k, clear)
        if key in self._scores:
            return self._scores[key]
        us, vs, sx, sy, w, h, dist = self.us, self.vs, self.sx, self.sy, self.w, self.h, self.dist
        s_max = SHIFT_MAX_PX
        shifts = [(du, dv) for dv in range(-s_max, s_max + 1) for du in range(-s_max, s_max + 1)]
        if clear:  # every shift in one gather: row j holds the distances under the edges moved by shifts[j] and k
            moved = self.at - k * (sy * w + sx)
            means = self.flat[moved[None, :] - np.array([dv * w + du for du, dv in shifts])[:, None]].mean(axis=1)
            out = {(du, dv): float(m) for (du, dv), m in zip(shifts, means)}
        else:  # some moves leave the crop: only the edges inside count
            out = {}
            for du, dv in shifts:
                u, v = us - du - k * sx, vs - dv - k * sy
                inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
                out[(du, dv)] = float(dist[v[inside], u[inside]].mean()) if inside.any() else EDGE_DIST_CAP_PX
        self._scores[key] = out
        return out

    def search(self, bleed_max: int | None = None) -> tuple[tuple[int, int], int, float]:
        """shift_and_bleed's answer: ((du, dv), bleed, ratio) for bleeds up to `bleed_max` (default BLEED_MAX_PX)."""
        bleed_max = BLEED_MAX_PX if bleed_max is None else bleed_max
        if not self.ready:
            return (0, 0), 0, 1.0
        clear = self._clear(SHIFT_MAX_PX + bleed_max)  # how far any shift and bleed together may move an edge
        scores = {(du, dv, k): m for k in range(bleed_max + 1) for (du, dv), m in self._scored(k, clear).items()}
        # ties: the shortest shift, then the least bleed, then a fixed order
        best = min(scores, key=lambda t: (scores[t], abs(t[0]) + abs(t[1]), t[2], t))
        unshifted = min(scores[(0, 0, k)] for k in range(bleed_max + 1))
        return (best[0], best[1]), best[2], scores[best] / max(unshifted, 1e-9)


def outline_shift_ratio(rgb: np.ndarray, outline: np.ndarray, du: int, dv: int,
                        explained: np.ndarray | None = None) -> float:
    """How near the colour image's edges a model's outline at its pose lies once moved back by (du, dv) (the shift
    the depth may lie off the colour image), over how near it lies as it is: their mean distances (each capped at
    EDGE_DIST_CAP_PX). A pose fitted to depth registered (du, dv) off lies that far off the colour's outline, so the
    outline moved back lies nearer (a ratio well under 1); a pose fitted to depth that only bleeds past its outlines
    lies on the colour's (a ratio of 1 or more). 1.0 when there is no outline to compare. `explained`: colour edges
    left out, as in shift_evidence (the model's own creases and inner outlines: a casing's inner wall runs a wall's
    thickness inside its outer outline, where the rim is as grey as the table)."""
    return outline_shift_ratios(rgb, outline, [(du, dv)], explained)[0]


def outline_shift_ratios(rgb: np.ndarray, outline: np.ndarray, shifts, explained: np.ndarray | None = None) -> list[float]:
    """outline_shift_ratio for each (du, dv) of `shifts`, the colour image's edge distances computed once (Canny and a
    distance transform: estimation.colour_checked asks for the nine shifts within a pixel of one)."""
    vs, us = np.nonzero(outline)
    if len(us) < SHIFT_MIN_EDGES or rgb is None or rgb.ndim != 3:
        return [1.0] * len(shifts)
    h, w = outline.shape
    p = COLOUR_PAD_PX
    cx0, cy0 = max(int(us.min()) - p, 0), max(int(vs.min()) - p, 0)
    cx1, cy1 = min(int(us.max()) + p + 1, w), min(int(vs.max()) + p + 1, h)
    dist = colour_edge_distance(rgb[cy0:cy1, cx0:cx1], None if explained is None else explained[cy0:cy1, cx0:cx1])
    us, vs = us - cx0, vs - cy0
    out = []
    for du, dv in shifts:
        u, v = us - du, vs - dv
        inside = (u >= 0) & (u < cx1 - cx0) & (v >= 0) & (v < cy1 - cy0)
        if not inside.any():
            out.append(1.0)
            continue
        as_is = float(dist[vs[inside], us[inside]].mean())
        out.append(float(dist[v[inside], u[inside]].mean()) / max(as_is, 1e-9))
    return out
