"""The plane a scene stands on, fitted by a seeded RANSAC in numpy: the same points give the same plane
in every process (Open3D's segment_plane is multi-threaded and unseeded). Shared by the estimator's
upright search and the depth masks.

PLANE_ITERATIONS draws are enough for a stable fit: on 35 RealSense-like renders of the gearbox and
the planetary reducer (`benchmarks/tune.py` frames), the table normal from 20 seeds per frame was at
most 0.03 degrees from the renderer's true one; tests/test_plane.py checks 0.5 degrees over 10 seeds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PLANE_ITERATIONS = 200
SCORE_POINTS = 1000  # hypotheses are scored on this many points; the winner is refitted on all its inliers


def extent_of(points: np.ndarray) -> float:
    """The largest distance between two of the points: their size, the same in every frame (the diagonal
    of their box along the frame's axes, used before, grew and shrank as the frame turned). Quadratic in
    the points: callers pass a few hundred."""
    if len(points) < 2:
        return 0.0
    c = points - points.mean(axis=0)
    sq = np.einsum("ij,ij->i", c, c)
    return float(np.sqrt(max((sq[:, None] + sq[None] - 2.0 * c @ c.T).max(), 0.0)))


SUPPORT_TRIES = 8  # supported_counts asks this many planes one at a time, best first, before asking all the others


def supported_counts(counts: np.ndarray, signed: np.ndarray, above: np.ndarray, tol: float, reach: float) -> np.ndarray:
    """`counts` (inliers per plane) with -1 for each plane the object (its points `above`, their heights over each
    plane `signed`, (points, planes)) does not stand on: most of it on the camera's side (median height over `tol`)
    and touching it (5th percentile of the heights under max(10 tol, half the object's extent, `reach`)), as far
    as the winner, argmax, needs: planes are asked best first (ties: lowest index), and once one stands the rest
    cannot win (-1 too, unasked). The same argmax as asking every plane; on a frame of benchmarks/tune.py the
    first plane asked is the table (a median and a percentile of 200 planes' heights cost 2-3 ms). The extent is
    measured only where it can matter: it is at most twice the points' largest distance from their mean."""
    c = above - above.mean(axis=0)
    bound = 2.0 * (1.0 + 1e-9) * float(np.sqrt(np.einsum("ij,ij->i", c, c).max()))  # >= extent_of(above), rounding too
    limit = max(10 * tol, reach) if 0.5 * bound <= max(10 * tol, reach) else max(10 * tol, 0.5 * extent_of(above), reach)

    def stands(cols) -> np.ndarray:
        h = signed[:, cols]
        return (np.median(h, axis=0) > tol) & (np.percentile(h, 5, axis=0) < limit)

    order = np.lexsort((np.arange(len(counts)), -counts))  # most inliers first, ties by index (argmax's order)
    out = np.full_like(counts, -1)
    for j in order[:SUPPORT_TRIES]:
        if stands([j])[0]:
            out[j] = counts[j]  # the best plane the object stands on: no other can win
            return out
    rest = order[SUPPORT_TRIES:]
    if len(rest):
        ok = stands(rest)
        out[rest[ok]] = counts[rest[ok]]
    return out


def fit_plane(points: np.ndarray, tol: float, seed: int = 0, iterations: int = PLANE_ITERATIONS,
              towards: np.ndarray | None = None, above: np.ndarray | None = None,
              reach: float = 0.0) -> tuple[np.ndarray, float, np.ndarray] | None:
    """(unit normal n, offset d, inlier mask) of the plane n . x + d = 0 with the most points within `tol`.

    `towards`: orient n so that this point (the camera) is on its positive side. `above`: the points of
    an object standing on the plane: only planes it stands on count (most of it on the camera's side,
    and its lowest seen points within half its extent of the plane), so a bigger wall behind the
    object, a shelf above it or the floor far below its table is not taken for its table. Half: in
    clutter, things in front hide the object's foot, and a Kinect sees little of a dark object's sides
    (the lowest seen points of the planetary motor were 22 mm up on a 98 mm extent). `reach`: how far
    above the plane the lowest seen points may be whatever the seen extent (the object's own size, when
    known: a motor seen only from above, behind clutter, shows nothing but its top). None when no plane
    is found (fewer than 3 points, every draw degenerate, or no plane that the object stands on)."""
    points = np.asarray(points, float)
    n_pts = len(points)
    if n_pts < 3:
        return None
    rng = np.random.default_rng(seed)
    score = points[rng.choice(n_pts, min(n_pts, SCORE_POINTS), replace=False)]
    tri = score[rng.integers(0, len(score), (iterations, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-12
    if not ok.any():
        return None
    normals, tri = normals[ok] / norm[ok, None], tri[ok]
    offsets = -np.einsum("ij,ij->i", normals, tri[:, 0])
    if towards is not None:
        flip = normals @ towards + offsets < 0
        normals[flip], offsets[flip] = -normals[flip], -offsets[flip]
    heights = score @ normals.T  # (points, planes), in place from here: the same sums, fewer copies
    heights += offsets
    counts = (np.abs(heights, out=heights) < tol).sum(axis=0)
    if above is not None and towards is not None and len(above):
        above = above[:: max(1, len(above) // 500)]
        signed = above @ normals.T + offsets  # (points, planes): height of the object's points over each plane
        counts = supported_counts(counts, signed, above, tol, reach)  # -1: a plane the object does not stand on
    best = int(np.argmax(counts))
    if counts[best] < 3:
        return None
    n, d = normals[best], offsets[best]
    for _ in range(2):  # refit on every inlier (least squares), then count again
        inl = np.abs(points @ n + d) < tol
        if inl.sum() < 3:
            break
        c = points[inl].mean(axis=0)
        n_new = np.linalg.svd(points[inl] - c, full_matrices=False)[2][2]
        n, d = (n_new, -float(n_new @ c)) if n_new @ n >= 0 else (-n_new, float(n_new @ c))
    return n, float(d), np.abs(points @ n + d) < tol


TABLE_TOL = 0.006  # a point within this share of the median depth of the table plane is on it (3 mm at 0.5 m)


@dataclass
class TableFit:
    """The table under what a depth image shows: its valid pixels (vs, us) and their camera-frame points,
    the plane n . x + d = 0 (n towards the camera) and its tolerance; None where no plane was found."""

    vs: np.ndarray
    us: np.ndarray
    pts: np.ndarray
    median_depth: float
    tol: float
    plane: tuple[np.ndarray, float] | None

    def heights(self) -> np.ndarray | None:
        """(N,) metres above the plane of each valid pixel's point."""
        return None if self.plane is None else self.pts @ self.plane[0] + self.plane[1]


def fit_table(depth: np.ndarray, cam, tol: float | None = None, rng: np.random.Generator | None = None,
              sample: int = 20000) -> TableFit | None:
    """The table plane of a depth image (seeded RANSAC on `sample` of its points, objects on the camera's
    side); None when it has fewer than 100 valid pixels. `tol` defaults to TABLE_TOL of the median depth."""
    valid = np.isfinite(depth) & (depth > 0)
    if valid.sum() < 100:
        return None
    vs, us = np.nonzero(valid)
    pts = cam.backproject(us, vs, depth[vs, us])
    med = float(np.median(pts[:, 2]))
    tol = TABLE_TOL * med if tol is None else tol
    rng = np.random.default_rng(0) if rng is None else rng
    fit = fit_plane(pts[rng.choice(len(pts), min(len(pts), sample), replace=False)], tol, seed=0, towards=np.zeros(3))
    return TableFit(vs, us, pts, med, tol, None if fit is None else (fit[0], fit[1]))


def table_axes(n: np.ndarray, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes (e1, e2) in the plane with unit normal `n` (world), fixed to the camera: e1 along the
    image's x (the camera's x axis projected onto the plane; its y where x is nearly along n), e2 = n x e1.
    Grids laid on a table along them (the upright search's yaws, its slides) are the same grids in every
    world frame, so the answer does not depend on where the caller's world happens to be (a renderer's, a
    table's, a robot's)."""
    for axis in (T_world_camera[:3, 0], T_world_camera[:3, 1]):
        e1 = axis - (axis @ n) * n
        if np.linalg.norm(e1) > 1e-6:
            e1 = e1 / np.linalg.norm(e1)
            return e1, np.cross(n, e1)
    raise ValueError("table_axes: the normal is not a unit vector")


def table_frame(depth: np.ndarray, cam, min_share: float = 0.3, seed: int = 0) -> np.ndarray | None:
    """T_world_camera of a world frame on the plane most of the depth lies on (a table): z = 0 on it,
    z up (towards the camera), the origin where the optical axis meets it (else below the camera), x
    along the image's x. None when no plane holds `min_share` of the depth points."""
    valid = np.isfinite(depth) & (depth > 0)
    step = max(1, int(np.sqrt(depth.size / 20000)))
    sub = valid[::step, ::step]
    vs, us = np.nonzero(sub)
    if len(vs) < 100:
        return None
    pts = cam.backproject(us * step, vs * step, depth[::step, ::step][vs, us])
    fit = fit_plane(pts, 0.006 * float(np.median(pts[:, 2])), seed, towards=np.zeros(3))
    if fit is None or fit[2].mean() < min_share:
        return None
    n, d, _ = fit
    origin = np.array([0.0, 0.0, -d / n[2]]) if n[2] < -0.2 else -d * n  # the optical axis (+z) meets the plane
    x, y = table_axes(n, np.eye(4))
    T_camera_world = np.eye(4)
    T_camera_world[:3, :3] = np.stack([x, y, n], axis=1)
    T_camera_world[:3, 3] = origin
    return np.linalg.inv(T_camera_world)
