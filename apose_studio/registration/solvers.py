"""A deterministic point-to-plane ICP in numpy, so that the same input gives the same pose bit for bit in
any process (preset setting `deterministic`, on by default).

Open3D 0.20's ICP sums across threads, and neither its seed nor OMP_NUM_THREADS=1 makes two runs agree
to the last bit (measured: 0 of 32 frames identical across two processes). This follows Open3D's
formulation (the linearised point-to-plane step, taken about the points' centre and as a rotation
vector, see icp_point_to_plane; its convergence criteria) with k-d tree queries (geometry.nn). Open3D's RANSAC does repeat once seeded and on one thread (apose_studio/__init__.py sets
OMP_NUM_THREADS=1); a RANSAC of our own in numpy, tried first, found fewer right poses than Open3D's
(free search, 36 frames: 18-22 against 28), so Open3D's stays.
"""

from __future__ import annotations

import numpy as np

from apose_studio.geometry.nn import NearestTree
from apose_studio.registration.side_by_side import check as check_wanted


def _small_rotation(w: np.ndarray) -> np.ndarray:
    """The turn by the rotation vector w (its length the angle; Rodrigues), the update of a linearised
    point-to-plane step. Open3D applies the step as Euler angles Rz Ry Rx about the frame's axes, which
    differ from w at second order by how the axes lie; the rotation vector turns alike in every frame."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def _solve_constrained(A: np.ndarray, b: np.ndarray, rcond: float = 1e-7) -> np.ndarray:
    """A x = b for the normal equations of ICP, moving only along directions the data constrains: a
    view of a box that shows two faces says nothing about sliding along their common edge, and solving
    exactly there sent a pose 4e11 m away. Directions with an eigenvalue under rcond x the largest
    are left still (the same as np.linalg.solve where the data constrains every direction)."""
    w, V = np.linalg.eigh(A)
    keep = w > rcond * max(float(w.max()), 1e-300)
    return V[:, keep] @ ((V[:, keep].T @ b) / w[keep])


def _jacobian(a: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(N, 6) rows [a x n, n]: the point-to-plane Jacobian. The cross product written out as np.cross
    computes it (the same products and differences, so the same bits), without its checks and copies:
    ICP builds one per iteration, tens of thousands a second."""
    J = np.empty((len(a), 6))
    a0, a1, a2, b0, b1, b2 = a[:, 0], a[:, 1], a[:, 2], n[:, 0], n[:, 1], n[:, 2]
    np.multiply(a1, b2, out=J[:, 0])
    J[:, 0] -= a2 * b1
    np.multiply(a2, b0, out=J[:, 1])
    J[:, 1] -= a0 * b2
    np.multiply(a0, b1, out=J[:, 2])
    J[:, 2] -= a1 * b0
    J[:, 3:] = n
    return J


def icp_point_to_plane(src: np.ndarray, tgt: np.ndarray, tgt_normals: np.ndarray, T_init: np.ndarray, threshold: float,
                       iterations: int, trace: list | None = None, tgt_tree: NearestTree | None = None,
                       viewpoint: np.ndarray | None = None, min_step: float = 0.0) -> np.ndarray:
    """T_target_source minimising sum ((T s - t) . n_t)^2 over pairs closer than `threshold`; stops when
    the fitness and inlier RMSE change by less than 1e-6 between iterations (Open3D's criteria). With
    `trace`, appends each iteration's T. `viewpoint` (the camera's position in the source's frame): pairs
    whose target normal faces away from it are dropped (a scene matched to a whole model: its far side).
    `min_step` (metres): also stop once an iteration moves the source by less than this (its translation, and
    its rotation times the source's extent).

    Each step turns about the matched points' centre. Linearised about the frame's origin instead (as
    Open3D's is), a small turn moves points a metre away by a metre times the angle, the turn and the
    shift trade off against each other, and the directions `_solve_constrained` drops depend on where the
    origin lies: with the world frame of a frame moved 0.9 m (the same camera, the same depth), every
    coarse pose of a fidget casing ended off the target. About the centre the step is the same wherever
    the caller's world frame is."""
    tree = tgt_tree if tgt_tree is not None else NearestTree(tgt)
    T = np.array(T_init, dtype=float)
    if len(src) == 0 or len(tgt) == 0:
        return T

    def match(T):
        p = src @ T[:3, :3].T + T[:3, 3]
        d, i = tree.query(p, distance_upper_bound=threshold)
        if viewpoint is not None:
            ok = np.isfinite(d)
            eye = T[:3, :3] @ viewpoint + T[:3, 3]
            ok[ok] = np.einsum("ij,ij->i", tgt_normals[i[ok]], tgt[i[ok]] - eye) < 0
            d = np.where(ok, d, np.inf)  # (a pair facing away counts as unmatched)
        return _matched(p, d, i)

    p, idx, fit, rmse = match(T)
    extent = 2.0 * float(np.linalg.norm(src - src.mean(axis=0), axis=1).max()) if min_step > 0 else 0.0  # any frame
    for _ in range(iterations):
        check_wanted()  # a reading computed ahead and no longer wanted stops here (side_by_side)
        if len(p) < 6:
            break
        step = _step(p, tgt[idx], tgt_normals[idx])
        if step is None:
            break
        update, x = step
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


def _step(p: np.ndarray, q: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """One linearised point-to-plane step for matched points p (moved source), q and n (target points and
    normals): (the 4 x 4 update, the solution [rotation vector, translation]), or None where the solve fails."""
    c = p.mean(axis=0)  # linearised about the matched points' centre, not the frame's origin (icp_point_to_plane)
    J = _jacobian(p - c, n)
    r = np.einsum("ij,ij->i", p - q, n)
    JtJ, Jtr = J.T @ J, J.T @ r
    try:
        x = _solve_constrained(JtJ, -Jtr)
    except np.linalg.LinAlgError:
        return None
    R = _small_rotation(x[:3])
    update = np.eye(4)
    update[:3, :3], update[:3, 3] = R, x[3:] + c - R @ c  # the turn about c
    return update, x


def _matched(p: np.ndarray, d: np.ndarray, i: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The matched pairs of moved source points p, given their neighbours' distances d (inf: none within the
    threshold) and indices i: (p matched, their target indices, fitness, inlier RMSE)."""
    ok = np.isfinite(d)
    n_ok = int(np.count_nonzero(ok))
    if n_ok == len(ok):  # every point matched: no copies
        return p, i, 1.0, float(np.sqrt(np.mean(d ** 2)))
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if n_ok else 0.0
    return p[ok], i[ok], n_ok / len(ok), rmse


def icp_point_to_plane_many(srcs: list[np.ndarray], tgt: np.ndarray, tgt_normals: np.ndarray, T_inits: list[np.ndarray],
                            threshold: float, iterations: int, tgt_tree: NearestTree | None = None,
                            traces: list[list | None] | None = None) -> list[np.ndarray]:
    """icp_point_to_plane of each source from its own start onto one target, the same poses to the last bit,
    with one k-d tree query a round for all the sources still iterating instead of one per source and step:
    the upright search refines a dozen starts of a few hundred points each by 8 steps, where a query's fixed
    cost and the threads' wake-up outweigh its work. Each point's neighbour is found on its own, and every
    other sum runs over each source's own points as before, so nothing depends on the batch. `traces`: per
    source, a list to append each iteration's T to (or None)."""
    tree = tgt_tree if tgt_tree is not None else NearestTree(tgt)
    Ts = [np.array(T, dtype=float) for T in T_inits]
    if len(tgt) == 0:
        return Ts

    def match(ids: list[int]) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
        moved = [srcs[k] @ Ts[k][:3, :3].T + Ts[k][:3, 3] for k in ids]
        d, i = tree.query(np.concatenate(moved), distance_upper_bound=threshold)
        out, o = [], 0
        for p in moved:
            out.append(_matched(p, d[o:o + len(p)], i[o:o + len(p)]))
            o += len(p)
        return out

    live = [k for k in range(len(srcs)) if len(srcs[k])]
    state = dict(zip(live, match(live))) if live else {}
    for _ in range(iterations):
        check_wanted()
        stepped = []
        for k in live:
            p, idx = state[k][0], state[k][1]
            step = _step(p, tgt[idx], tgt_normals[idx]) if len(p) >= 6 else None
            if step is not None:
                Ts[k] = step[0] @ Ts[k]
                stepped.append(k)
                if traces is not None and traces[k] is not None:
                    traces[k].append(Ts[k].copy())
        if not stepped:
            break
        live = []
        for k, m in zip(stepped, match(stepped)):
            fit, rmse = state[k][2], state[k][3]
            state[k] = m
            if not (abs(m[2] - fit) < 1e-6 and abs(m[3] - rmse) < 1e-6):
                live.append(k)
    return Ts
