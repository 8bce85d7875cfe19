"""Deterministic solvers: point-to-plane ICP and feature-matching RANSAC in numpy, so that the same input
gives the same pose bit for bit in any process (preset setting `deterministic`, on by default).

Open3D's ICP and RANSAC sum and sample across threads, and neither its seed nor OMP_NUM_THREADS makes
two runs agree to the last bit (measured: 0 of 32 frames identical across two processes, poses up to
0.1 mm apart; Open3D issue #7475). These follow the same formulation as Open3D's (the same linearised
point-to-plane step, correspondence checks and confidence-based early stop), with k-d tree queries
from scipy and random draws from numpy's seeded generator.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


QUERY_WORKERS = 1  # more threads cost more than they save on the few thousand points of one ICP step


def _small_rotation(a: float, b: float, c: float) -> np.ndarray:
    """Rz(c) @ Ry(b) @ Rx(a), the update of a linearised point-to-plane step (as Open3D's)."""
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    return np.array([[cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa],
                     [sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa],
                     [-sb, cb * sa, cb * ca]])


def icp_point_to_plane(src: np.ndarray, tgt: np.ndarray, tgt_normals: np.ndarray, T_init: np.ndarray, threshold: float,
                       iterations: int, trace: list | None = None, tgt_tree: cKDTree | None = None) -> np.ndarray:
    """T_target_source minimising sum ((T s - t) . n_t)^2 over pairs closer than `threshold`; stops when
    the fitness and inlier RMSE change by less than 1e-6 between iterations (Open3D's criteria). With
    `trace`, appends each iteration's T."""
    tree = tgt_tree if tgt_tree is not None else cKDTree(tgt)
    T = np.array(T_init, dtype=float)
    if len(src) == 0 or len(tgt) == 0:
        return T

    def match(T):
        p = src @ T[:3, :3].T + T[:3, 3]
        d, i = tree.query(p, distance_upper_bound=threshold, workers=QUERY_WORKERS)
        ok = np.isfinite(d)
        fit = float(ok.mean())
        rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else 0.0
        return p[ok], i[ok], fit, rmse

    p, idx, fit, rmse = match(T)
    for _ in range(iterations):
        if len(p) < 6:
            break
        q, n = tgt[idx], tgt_normals[idx]
        J = np.hstack([np.cross(p, n), n])
        r = np.einsum("ij,ij->i", p - q, n)
        JtJ, Jtr = J.T @ J, J.T @ r
        try:
            x = np.linalg.solve(JtJ, -Jtr)
        except np.linalg.LinAlgError:
            break
        update = np.eye(4)
        update[:3, :3], update[:3, 3] = _small_rotation(*x[:3]), x[3:]
        T = update @ T
        if trace is not None:
            trace.append(T.copy())
        p, idx, fit_new, rmse_new = match(T)
        done = abs(fit_new - fit) < 1e-6 and abs(rmse_new - rmse) < 1e-6
        fit, rmse = fit_new, rmse_new
        if done:
            break
    return T


def _kabsch(S: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(B, 4, 4) rigid transforms taking each batch of points S (B, n, 3) onto D (B, n, 3), least squares."""
    cs, cd = S.mean(axis=1, keepdims=True), D.mean(axis=1, keepdims=True)
    H = np.einsum("bni,bnj->bij", S - cs, D - cd)
    U, _, Vt = np.linalg.svd(H)
    det = np.sign(np.linalg.det(np.einsum("bij,bjk->bik", Vt.transpose(0, 2, 1), U.transpose(0, 2, 1))))
    Dg = np.tile(np.eye(3), (len(S), 1, 1))
    Dg[:, 2, 2] = det
    R = Vt.transpose(0, 2, 1) @ Dg @ U.transpose(0, 2, 1)
    T = np.tile(np.eye(4), (len(S), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = cd[:, 0] - np.einsum("bij,bj->bi", R, cs[:, 0])
    return T


def ransac_feature_matching(src: np.ndarray, tgt: np.ndarray, f_src: np.ndarray, f_tgt: np.ndarray, distance: float,
                            edge_similarity: float, max_iterations: int, confidence: float, seed: int,
                            matches: int = 1, batch: int = 256, deadline: float = float("inf")) -> np.ndarray:
    """T_target_source from FPFH correspondences (each source point to its `matches` nearest target
    features), by RANSAC: three random correspondences whose pairwise lengths agree within
    `edge_similarity` and which land within `distance` after the fit; the hypothesis with the most
    correspondences within `distance` wins (then the lower RMSE), refitted on them. Stops early once
    `confidence` is reached for the best inlier share (as Open3D's RANSACConvergenceCriteria), or at
    `deadline` (time.perf_counter()) with the best so far."""
    import time

    if len(src) < 3 or len(tgt) < 3:
        return np.eye(4)
    _, j = cKDTree(f_tgt).query(f_src, k=matches)
    j = np.asarray(j).reshape(len(src), -1)
    cs = np.repeat(src, j.shape[1], axis=0)
    ct = tgt[j.reshape(-1)]
    n = len(cs)
    rng = np.random.default_rng(seed)
    best = (-1, np.inf, np.eye(4))  # (inliers, rmse, T)
    needed, done = max_iterations, 0
    while done < min(max_iterations, needed) and (done == 0 or time.perf_counter() < deadline):
        b = min(batch, min(max_iterations, needed) - done)
        done += b
        pick = rng.integers(0, n, (b, 3))
        S, D = cs[pick], ct[pick]  # (b, 3, 3)
        ds = np.linalg.norm(S[:, [0, 0, 1]] - S[:, [1, 2, 2]], axis=2)
        dt = np.linalg.norm(D[:, [0, 0, 1]] - D[:, [1, 2, 2]], axis=2)
        ok = np.all((ds >= edge_similarity * dt) & (dt >= edge_similarity * ds), axis=1)
        if not ok.any():
            continue
        T = _kabsch(S[ok], D[ok])
        moved3 = np.einsum("bij,bnj->bni", T[:, :3, :3], S[ok]) + T[:, None, :3, 3]
        T = T[np.all(np.linalg.norm(moved3 - D[ok], axis=2) < distance, axis=1)]
        if not len(T):
            continue
        moved = np.einsum("bij,nj->bni", T[:, :3, :3], cs) + T[:, None, :3, 3]
        err = np.linalg.norm(moved - ct[None], axis=2)
        inl = err < distance
        count = inl.sum(axis=1)
        rmse = np.sqrt(np.where(inl, err ** 2, 0.0).sum(axis=1) / np.maximum(count, 1))
        k = int(np.lexsort((rmse, -count))[0])
        if count[k] > best[0] or (count[k] == best[0] and rmse[k] < best[1]):
            best = (int(count[k]), float(rmse[k]), T[k])
            share = best[0] / n
            if 0 < share < 1:
                needed = int(np.ceil(np.log(1 - confidence) / np.log(1 - share ** 3)))
            elif share >= 1:
                needed = 0
    count, _, T = best
    if count < 3:
        return T
    inl = np.linalg.norm(cs @ T[:3, :3].T + T[:3, 3] - ct, axis=1) < distance
    return _kabsch(cs[inl][None], ct[inl][None])[0]
