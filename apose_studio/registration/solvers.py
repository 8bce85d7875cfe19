"""A deterministic point-to-plane ICP in numpy, so that the same input gives the same pose bit for bit in
any process (preset setting `deterministic`, on by default).

Open3D 0.20's ICP sums across threads, and neither its seed nor OMP_NUM_THREADS=1 makes two runs agree
to the last bit (measured: 0 of 32 frames identical across two processes). This follows Open3D's
formulation (the same linearised point-to-plane step and convergence criteria) with k-d tree queries
(geometry.nn). Open3D's RANSAC does repeat once seeded and on one thread (apose_studio/__init__.py sets
OMP_NUM_THREADS=1); a RANSAC of our own in numpy, tried first, found fewer right poses than Open3D's
(free search, 36 frames: 18-22 against 28), so Open3D's stays.
"""

from __future__ import annotations

import numpy as np

from apose_studio.geometry.nn import NearestTree


def _small_rotation(a: float, b: float, c: float) -> np.ndarray:
    """Rz(c) @ Ry(b) @ Rx(a), the update of a linearised point-to-plane step (as Open3D's)."""
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    return np.array([[cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa],
                     [sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa],
                     [-sb, cb * sa, cb * ca]])


def _solve_constrained(A: np.ndarray, b: np.ndarray, rcond: float = 1e-7) -> np.ndarray:
    """A x = b for the normal equations of ICP, moving only along directions the data constrains: a
    view of a box that shows two faces says nothing about sliding along their common edge, and solving
    exactly there sent a pose 4e11 m away. Directions with an eigenvalue under rcond x the largest
    are left still (the same as np.linalg.solve where the data constrains every direction)."""
    w, V = np.linalg.eigh(A)
    keep = w > rcond * max(float(w.max()), 1e-300)
    return V[:, keep] @ ((V[:, keep].T @ b) / w[keep])


def icp_point_to_plane(src: np.ndarray, tgt: np.ndarray, tgt_normals: np.ndarray, T_init: np.ndarray, threshold: float,
                       iterations: int, trace: list | None = None, tgt_tree: NearestTree | None = None,
                       viewpoint: np.ndarray | None = None, min_step: float = 0.0) -> np.ndarray:
    """T_target_source minimising sum ((T s - t) . n_t)^2 over pairs closer than `threshold`; stops when
    the fitness and inlier RMSE change by less than 1e-6 between iterations (Open3D's criteria). With
    `trace`, appends each iteration's T. `viewpoint` (the camera's position in the source's frame): pairs
    whose target normal faces away from it are dropped (a scene matched to a whole model: its far side).
    `min_step` (metres): also stop once an iteration moves the source by less than this (its translation, and
    its rotation times the source's extent)."""
    tree = tgt_tree if tgt_tree is not None else NearestTree(tgt)
    T = np.array(T_init, dtype=float)
    if len(src) == 0 or len(tgt) == 0:
        return T

    def match(T):
        p = src @ T[:3, :3].T + T[:3, 3]
        d, i = tree.query(p, distance_upper_bound=threshold)
        ok = np.isfinite(d)
        if viewpoint is not None:
            eye = T[:3, :3] @ viewpoint + T[:3, 3]
            ok[ok] = np.einsum("ij,ij->i", tgt_normals[i[ok]], tgt[i[ok]] - eye) < 0
        fit = float(ok.mean())
        rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else 0.0
        return p[ok], i[ok], fit, rmse

    p, idx, fit, rmse = match(T)
    extent = float(np.ptp(src, axis=0).max()) if min_step > 0 else 0.0
    for _ in range(iterations):
        if len(p) < 6:
            break
        q, n = tgt[idx], tgt_normals[idx]
        J = np.hstack([np.cross(p, n), n])
        r = np.einsum("ij,ij->i", p - q, n)
        JtJ, Jtr = J.T @ J, J.T @ r
        try:
            x = _solve_constrained(JtJ, -Jtr)
        except np.linalg.LinAlgError:
            break
        update = np.eye(4)
        update[:3, :3], update[:3, 3] = _small_rotation(*x[:3]), x[3:]
        T = update @ T
        if trace is not None:
            trace.append(T.copy())
        if min_step > 0 and np.linalg.norm(x[3:]) < min_step and np.linalg.norm(x[:3]) * extent < min_step:
            break
        p, idx, fit_new, rmse_new = match(T)
        done = abs(fit_new - fit) < 1e-6 and abs(rmse_new - rmse) < 1e-6
        fit, rmse = fit_new, rmse_new
        if done:
            break
    return T
