"""geometry.nn: the k-d tree answers as scipy's does, and the closed-form normals agree with eigh's."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from apose_studio.geometry.nn import NearestTree, local_normals


def test_nearest_tree_answers_as_scipy_does_with_missing_neighbours_marked_alike():
    rng = np.random.default_rng(3)
    pts, q = rng.random((500, 3)), rng.random((200, 3)) * 1.4 - 0.2
    for k, bound in [(1, np.inf), (1, 0.05), (4, 0.08)]:
        d0, i0 = cKDTree(pts).query(q, k=k, distance_upper_bound=bound)
        d1, i1 = NearestTree(pts).query(q, k=k, distance_upper_bound=bound)
        assert d1.shape == d0.shape and i1.shape == i0.shape
        np.testing.assert_array_equal(d1, d0)
        np.testing.assert_array_equal(i1, i0)
    assert np.isinf(NearestTree(pts).query(q, distance_upper_bound=1e-6)[0]).any()  # the bound was used


def test_the_answer_is_the_same_on_one_thread_and_on_several(monkeypatch):
    """pykdtree answers a batch with an OpenMP loop; the registration's determinism rests on each query
    point being answered on its own, whatever the thread count (nn.NN_THREADS, set per query)."""
    from apose_studio.geometry import nn

    if nn._SET_THREADS is None:
        pytest.skip("this pykdtree build bundles no OpenMP runtime of its own: its thread count is not ours to set")
    rng = np.random.default_rng(5)
    pts, q = rng.random((20000, 3)), rng.random((20000, 3))
    answers = []
    for threads in (1, 2, 4):
        monkeypatch.setattr(nn, "NN_THREADS", threads)
        answers.append(NearestTree(pts).query(q, k=3, distance_upper_bound=0.05))
    for d, i in answers[1:]:
        np.testing.assert_array_equal(d, answers[0][0])
        np.testing.assert_array_equal(i, answers[0][1])


@pytest.mark.parametrize("value", ["99999", "abc", "0", "-2", "1e3", "\uff13"])
def test_the_thread_count_setting_stays_within_the_cpus(monkeypatch, value):
    """APOSE_NN_THREADS: a mistyped or huge value never starts more threads than the process has CPUs."""
    import os

    from apose_studio.geometry import nn

    monkeypatch.setenv("APOSE_NN_THREADS", value)
    n = nn._thread_count()
    assert 1 <= n <= len(os.sched_getaffinity(0))


def test_nearest_tree_of_nothing_and_of_too_few_points():
    d, i = NearestTree(np.zeros((0, 3))).query(np.ones((2, 3)))
    assert np.isinf(d).all() and (i == 0).all()
    d, i = NearestTree(np.zeros((2, 3))).query(np.ones((1, 3)), k=3)
    assert d.shape == (1, 3) and np.isinf(d[0, 2]) and i[0, 2] == 2


@pytest.mark.parametrize("shape", ["cylinder", "plane", "line", "sphere"])
def test_local_normals_agree_with_eigh_of_the_same_neighbourhoods(shape):
    rng = np.random.default_rng(7)
    n = 800
    a, b = rng.uniform(0, np.pi, n), rng.uniform(0, 0.05, n)
    p = {"cylinder": np.c_[0.03 * np.cos(a), 0.03 * np.sin(a), b],
         "plane": np.c_[a * 0.01, b, 0.002 * a],
         "line": np.c_[b, 2 * b, -b],  # every neighbourhood a line: any direction across is a normal
         "sphere": 0.04 * (g := rng.normal(size=(n, 3))) / np.linalg.norm(g, axis=1, keepdims=True)}[shape]
    p = p + rng.normal(scale=1e-4 if shape != "line" else 0.0, size=p.shape)
    got = local_normals(p, 12)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-9)
    _, nb = cKDTree(p).query(p, k=12)
    d = p[nb] - p[nb].mean(axis=1, keepdims=True)
    w, V = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    if shape == "line":  # the normal must lie across the line: no spread along it
        spread = np.einsum("nki,ni->nk", d, got)
        assert np.abs(spread).max() < 1e-9
        return
    cos = np.abs(np.einsum("ni,ni->n", got, V[:, :, 0]))
    well_defined = w[:, 1] > 4 * w[:, 0]  # a plane's normal, not a tie between two directions
    assert well_defined.mean() > 0.5
    assert np.degrees(np.arccos(np.clip(cos[well_defined], 0, 1))).max() < 1e-3


def test_a_non_finite_query_is_refused_as_scipy_refuses_it():
    """pykdtree answers a NaN or inf query point with a far, wrong neighbour (index 2**32 - 1); the wrapper
    refuses it, as scipy's cKDTree does, so that no such answer reaches a registration."""
    tree = NearestTree(np.random.default_rng(0).random((50, 3)))
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="non-finite"):
            tree.query(np.array([[0.5, bad, 0.5]]))
