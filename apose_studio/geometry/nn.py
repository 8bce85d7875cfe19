"""Nearest-neighbour queries for the registration's hot paths (ICP correspondences, scoring, the pose's
spread): pykdtree's k-d tree behind scipy's `cKDTree.query` interface (k, distance_upper_bound; a
missing neighbour is distance inf and index len(points)).

Why pykdtree: on the clouds one ICP step queries (2-6 thousand points, three dimensions), its queries
took 0.40 ms against cKDTree's 0.85 ms, with the same neighbours and distances to the last bit
(benchmarks/tune.py --compare: identical poses), and its trees build faster. Each query point is
answered on its own, so the answer does not depend on threads. Evaluation code (geometry.metrics)
keeps scipy's tree: the yardstick stays independent of the code it measures.

Threads: pykdtree answers a batch of queries with an OpenMP loop, each query point on its own, so the
answer is the same on any number of threads. apose_studio sets OMP_NUM_THREADS=1 for Open3D (whose
sums across threads are not repeatable); pykdtree ships its own OpenMP runtime, so its thread count is
set apart: up to 4 of the CPUs this process may use (APOSE_NN_THREADS overrides). Its threads wait asleep
(OMP_WAIT_POLICY=PASSIVE, apose_studio/__init__.py): spinning, they took the cores from other work on a busy
machine (2,500 points: 0.95 ms on one thread, 0.70 ms on two, 7.3 ms on two spinning with the cores busy;
benchmarks/nn_threads.py).
"""

from __future__ import annotations

import ctypes
import glob
import os

import numpy as np
import pykdtree
from pykdtree.kdtree import KDTree


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity where the system tells it, else the machine's), at least 1."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _thread_count() -> int:
    """APOSE_NN_THREADS when it is a whole number from 1 to the CPUs this process may use (more threads than
    CPUs only wait on each other; 99999 would try to start as many), else up to 4 of those CPUs."""
    cpus = usable_cpus()
    wanted = os.environ.get("APOSE_NN_THREADS", "").strip()
    if wanted.isascii() and wanted.isdigit() and int(wanted) > 0:
        return min(int(wanted), max(cpus, 1))
    return max(1, min(4, cpus))


def _pykdtree_openmp():
    """omp_set_num_threads of the OpenMP runtime pykdtree's wheel bundles (None when it bundles none,
    e.g. a build against the system's: it then follows OMP_NUM_THREADS)."""
    libs = sorted(glob.glob(os.path.join(os.path.dirname(pykdtree.__file__), os.pardir, "pykdtree.libs", "libgomp*.so*")))
    if not libs:
        return None
    try:
        fn = ctypes.CDLL(libs[0]).omp_set_num_threads
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_int], None
    return fn


_SET_THREADS = _pykdtree_openmp()
NN_THREADS = _thread_count()


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
        if not np.isfinite(q).all():  # pykdtree would answer a far, wrong neighbour; scipy refuses, and so do we
            raise ValueError("nearest-neighbour query with non-finite points (NaN or inf)")
        shape = (len(q),) if k == 1 else (len(q), k)
        if self.n == 0 or len(q) == 0:
            return np.full(shape, np.inf), np.full(shape, self.n, dtype=np.intp)
        kk = min(k, self.n)
        bound = None if not np.isfinite(distance_upper_bound) else float(distance_upper_bound)
        if _SET_THREADS is not None:  # per calling thread (OpenMP keeps the count per thread): the studio's workers too
            _SET_THREADS(NN_THREADS)
        d, i = self._tree.query(q, k=kk, distance_upper_bound=bound)
        i = i.astype(np.intp)
        if kk < k:  # fewer points than asked for: the rest are missing, as scipy reports them
            d = np.concatenate([d.reshape(len(q), kk), np.full((len(q), k - kk), np.inf)], axis=1)
            i = np.concatenate([i.reshape(len(q), kk), np.full((len(q), k - kk), self.n, dtype=np.intp)], axis=1)
        missing = ~np.isfinite(d)
        if missing.any():
            i[missing] = self.n
        return d.reshape(shape), i.reshape(shape)


def local_normals(points: np.ndarray, k: int = 12) -> np.ndarray:
    """(N, 3) unit normal of each point: the direction of least spread of its k nearest points (itself
    included), the normal of the plane fitted to them. Sign arbitrary. Needs N >= k.

    The 3 x 3 scatter matrices' smallest eigenvectors in closed form (the trigonometric eigenvalue of a
    symmetric 3 x 3 matrix, then the widest cross product of two rows of A - lambda I), vectorised: on
    2,500 points of a noisy cylinder 7.8 ms against 10.3 ms with numpy's batched eigh, the normals within
    1e-5 degrees of eigh's (tests/geometry/test_nn.py). Where the two smallest spreads are equal (a line of points) any direction across it is a normal,
    as with eigh."""
    _, nb = NearestTree(points).query(points, k=k)
    x = points[nb]
    d = x - x.mean(axis=1, keepdims=True)
    a00, a11, a22 = (d[..., 0] ** 2).sum(1), (d[..., 1] ** 2).sum(1), (d[..., 2] ** 2).sum(1)
    a01, a02, a12 = (d[..., 0] * d[..., 1]).sum(1), (d[..., 0] * d[..., 2]).sum(1), (d[..., 1] * d[..., 2]).sum(1)
    q = (a00 + a11 + a22) / 3.0
    off = a01 ** 2 + a02 ** 2 + a12 ** 2
    pp = np.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * off) / 6.0)
    safe = np.where(pp > 0, pp, 1.0)
    b00, b11, b22 = (a00 - q) / safe, (a11 - q) / safe, (a22 - q) / safe
    b01, b02, b12 = a01 / safe, a02 / safe, a12 / safe
    det = b00 * (b11 * b22 - b12 ** 2) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    lam = q + 2.0 * pp * np.cos(phi + 2.0 * np.pi / 3.0)  # the smallest eigenvalue
    r0 = np.stack([a00 - lam, a01, a02], axis=1)
    r1 = np.stack([a01, a11 - lam, a12], axis=1)
    r2 = np.stack([a02, a12, a22 - lam], axis=1)
    cands = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)  # (N, 3, 3)
    norms = np.linalg.norm(cands, axis=2)
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(points))
    v, nv = cands[rows, best], norms[rows, best]
    # A - lambda I of rank < 2 (a line of points, or no spread at all): its rows' cross products are rounding
    # noise; eigh picks a direction across the line there
    fallback = nv <= 1e-9 * (3.0 * q) ** 2
    out = v / np.where(fallback, 1.0, nv)[:, None]
    if fallback.any():
        out[fallback] = np.linalg.eigh(np.einsum("nki,nkj->nij", d[fallback], d[fallback]))[1][:, :, 0]
    return out
