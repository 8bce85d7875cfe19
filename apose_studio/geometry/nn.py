"""Nearest-neighbour queries for the registration's hot paths (ICP correspondences, scoring, the pose's
spread): pykdtree's k-d tree behind scipy's `cKDTree.query` interface (k, distance_upper_bound; a
missing neighbour is distance inf and index len(points)).

Why pykdtree: on the clouds one ICP step queries (2-6 thousand points, three dimensions), its queries
took 0.40 ms against cKDTree's 0.85 ms, with the same neighbours and distances to the last bit
(benchmarks/tune.py --compare: identical poses), and its trees build faster. Each query point is
answered on its own, so the answer does not depend on threads. Evaluation code (geometry.metrics)
keeps scipy's tree: the yardstick stays independent of the code it measures.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree


class NearestTree:
    """A k-d tree of (N, 3) float points, queried like scipy's cKDTree."""

    __slots__ = ("n", "_tree")

    def __init__(self, points: np.ndarray, leafsize: int = 16):
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.n = len(pts)
        self._tree = KDTree(pts, leafsize=leafsize) if self.n else None

    def query(self, x: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(distances, indices) of the k nearest points of each row of x, within distance_upper_bound (a
        neighbour beyond it: distance inf, index len(points)). Shapes as scipy's: (M,) for k=1, else (M, k)."""
        q = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        shape = (len(q),) if k == 1 else (len(q), k)
        if self.n == 0 or len(q) == 0:
            return np.full(shape, np.inf), np.full(shape, self.n, dtype=np.intp)
        kk = min(k, self.n)
        bound = None if not np.isfinite(distance_upper_bound) else float(distance_upper_bound)
        d, i = self._tree.query(q, k=kk, distance_upper_bound=bound)
        i = i.astype(np.intp)
        if kk < k:  # fewer points than asked for: the rest are missing, as scipy reports them
            d = np.concatenate([d.reshape(len(q), kk), np.full((len(q), k - kk), np.inf)], axis=1)
            i = np.concatenate([i.reshape(len(q), kk), np.full((len(q), k - kk), self.n, dtype=np.intp)], axis=1)
        missing = ~np.isfinite(d)
        if missing.any():
            i[missing] = self.n
        return d.reshape(shape), i.reshape(shape)
