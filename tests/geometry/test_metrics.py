"""Each metric against a case computed by hand."""

import numpy as np
import pytest

from apose_studio.geometry import metrics as M
from apose_studio.geometry.se3 import make_T


def Rz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


PTS = np.array([[1.0, 0, 0], [-1.0, 0, 0]])  # two points on the x axis
HALF_TURN = make_T(Rz(180))
TWO_FOLD = np.stack([np.eye(4), HALF_TURN])


def test_add_adi_mssd_on_a_half_turn():
    # turning the pair half round swaps the points: each moves by 2, but the set is unchanged
    assert M.add(HALF_TURN, np.eye(4), PTS) == pytest.approx(2.0)
    assert M.adi(HALF_TURN, np.eye(4), PTS) == pytest.approx(0.0, abs=1e-12)
    assert M.mssd(HALF_TURN, np.eye(4), PTS) == pytest.approx(2.0)
    assert M.mssd(HALF_TURN, np.eye(4), PTS, TWO_FOLD) == pytest.approx(0.0, abs=1e-12)


def test_translation_and_rotation_errors():
    T = make_T(Rz(30), [0.003, 0.004, 0])
    assert M.te(T, np.eye(4)) == pytest.approx(0.005)
    assert M.re_deg(T, np.eye(4)) == pytest.approx(30.0)
    # ADD of a pure shift is the shift; MSSD is the largest displacement: |(1,0,0) turned 30 deg - (1,0,0)| + shift
    shift = make_T(t=[0.01, 0, 0])
    assert M.add(shift, np.eye(4), PTS) == pytest.approx(0.01)
    turned = make_T(Rz(30))
    assert M.mssd(turned, np.eye(4), PTS) == pytest.approx(2 * np.sin(np.radians(15)))


def test_mspd_in_pixels():
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    pts = np.array([[0.0, 0, 0], [0.1, 0, 0]])
    gt = make_T(t=[0, 0, 1.0])
    est = make_T(t=[0.01, 0, 1.0])  # 1 cm sideways at 1 m with f = 100 px: 1 px
    assert M.mspd(est, gt, pts, K) == pytest.approx(1.0)


def test_recall_and_average_recall():
    d = 0.1
    errors = [0.001, 0.02, np.nan, 0.006]
    assert M.recall(errors, d) == pytest.approx(2 / 4)  # below 10 mm: 1 and 6 mm; NaN is a miss
    # thresholds 5..50 mm: 1 mm passes all 10, 6 mm passes 9, 20 mm passes 7 (25..50), NaN none
    assert M.average_recall(errors, d) == pytest.approx((10 + 9 + 7 + 0) / 40)
    assert np.isnan(M.recall([], d))


def test_fitness_and_inlier_rmse():
    target = np.array([[0, 0, 0], [1, 0, 0], [5, 0, 0]], float)
    source = np.array([[0, 0.1, 0], [1, 0.2, 0]], float)
    f, r = M.fitness_rmse(target, source, threshold=0.5)
    assert f == pytest.approx(2 / 3)
    assert r == pytest.approx(np.sqrt((0.1**2 + 0.2**2) / 2))
    assert M.fitness_rmse(target, source, threshold=0.05) == (0.0, 0.0)
    assert M.fitness_rmse(np.zeros((0, 3)), source, 1.0) == (0.0, 0.0)


# An asymmetric set, a right triangle with legs 1 (x) and 2 (y), turned a quarter about z at the
# origin. By hand: (0,0,0) stays; (1,0,0) -> (0,1,0), moved sqrt 2; (0,2,0) -> (-2,0,0), moved
# sqrt 8. So ADD = (0 + sqrt2 + 2 sqrt2) / 3 = sqrt2 and MSSD = 2 sqrt2 (max != mean). ADI, over the
# gt points, to the nearest turned point: 0, 1 (to the origin), 1 (to (0,1,0)): 2/3; the other way
# round (over the turned points) it would be (0 + 1 + 2) / 3 = 1.
TRI = np.array([[0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0]])
QUARTER = make_T(Rz(90))


def test_add_adi_mssd_on_an_asymmetric_set():
    assert M.add(QUARTER, np.eye(4), TRI) == pytest.approx(np.sqrt(2))
    assert M.adi(QUARTER, np.eye(4), TRI) == pytest.approx(2 / 3)
    assert M.mssd(QUARTER, np.eye(4), TRI) == pytest.approx(2 * np.sqrt(2))
    # the same error seen from anywhere: both poses moved by one rigid motion (a turn and a shift)
    W = make_T(Rz(30), [1.0, 2.0, 3.0])
    assert M.add(W @ QUARTER, W, TRI) == pytest.approx(np.sqrt(2))
    assert M.adi(W @ QUARTER, W, TRI) == pytest.approx(2 / 3)
    assert M.mssd(W @ QUARTER, W, TRI) == pytest.approx(2 * np.sqrt(2))
    # a pure shift of 1 cm: every point moves 1 cm, ADD = MSSD = 0.01; ADI's nearest is the shifted twin
    shift = make_T(t=[0.0, 0.0, 0.01])
    assert M.add(shift, np.eye(4), TRI) == pytest.approx(0.01)
    assert M.adi(shift, np.eye(4), TRI) == pytest.approx(0.01)
    assert M.mssd(shift, np.eye(4), TRI) == pytest.approx(0.01)


def test_mssd_takes_the_best_symmetry_wherever_it_is_in_the_list():
    # S_good undoes the quarter turn and adds 0.1 along the part's x: T_est S_good = W (I, (0, 0.1, 0))
    # in the part frame turned by Rz(90): every point 0.1 off, so 0.1; the others give 2 sqrt2 (I) and,
    # for Rz(180) (T_est S = W Rz(270)): (1,0,0) -> (0,-1,0) sqrt2 off, (0,2,0) -> (2,0,0) 2 sqrt2 off.
    W = make_T(Rz(30), [1.0, 2.0, 3.0])
    est = W @ QUARTER
    good = make_T(Rz(-90), [0.1, 0, 0])
    for syms in ([np.eye(4), good, make_T(Rz(180))], [good, np.eye(4)], [make_T(Rz(180)), np.eye(4), good]):
        assert M.mssd(est, W, TRI, np.stack(syms)) == pytest.approx(0.1)
    assert M.mssd(est, W, TRI, np.stack([make_T(Rz(180))])) == pytest.approx(2 * np.sqrt(2))


def test_project_pinhole_by_hand():
    K = np.array([[100.0, 0, 50], [0, 200.0, 40], [0, 0, 1]])
    pts = np.array([[0.1, -0.2, 2.0], [0.0, 0.0, 4.0]])
    # u = fx x / z + cx = 100 * 0.05 + 50 = 55, v = fy y / z + cy = 200 * -0.1 + 40 = 20; the axis point: (cx, cy)
    np.testing.assert_allclose(M.project(np.eye(4), pts, K), [[55, 20], [50, 40]], atol=1e-12)
    # the pose applies first: 1 m further away halves the offsets from the centre
    np.testing.assert_allclose(M.project(make_T(t=[0, 0, 2.0]), pts[:1], K), [[52.5, 30]], atol=1e-12)


def test_mspd_on_an_asymmetric_set():
    # f = 100 px, centre (50, 50); the triangle scaled by 0.1 at z = 2 m projects to (50,50), (55,50),
    # (50,60). Turned a quarter about its own z: (50,50), (50,55), (40,50). Pixel shifts 0, 5 sqrt2,
    # 10 sqrt2: MSPD 10 sqrt2 (the mean would be 5 sqrt2).
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    pts = TRI * 0.1
    gt = make_T(t=[0, 0, 2.0])
    est = make_T(Rz(90), [0, 0, 2.0])
    assert M.mspd(est, gt, pts, K) == pytest.approx(10 * np.sqrt(2))
    # with symmetries: Rz(180) leaves Rz(270) (shifts 0, 5 sqrt2, 10 sqrt2 again); the one that undoes
    # the turn and moves 1 cm along the part's x leaves 1 cm along y at 2 m: 0.5 px for every point
    syms = np.stack([make_T(Rz(180)), make_T(Rz(-90), [0.01, 0, 0])])
    assert M.mspd(est, gt, pts, K, syms) == pytest.approx(0.5)
    assert M.mspd(est, gt, pts, K, syms[:1]) == pytest.approx(10 * np.sqrt(2))


def test_rotation_error_is_the_relative_turn():
    # 20 deg and 50 deg about z: 30 deg apart (R_est R_gt, not R_est^T R_gt, would say 70)
    assert M.re_deg(make_T(Rz(50)), make_T(Rz(20))) == pytest.approx(30.0)
    assert M.re_deg(make_T(Rz(20)), make_T(Rz(50))) == pytest.approx(30.0)
    assert M.te(make_T(t=[1, 2, 3]), make_T(t=[1, 2, 3])) == 0.0
    assert M.te(make_T(t=[1.0, 2, 3]), make_T(t=[4.0, 6, 3])) == pytest.approx(5.0)


def test_recall_is_strictly_below_the_threshold_and_thresholds_are_bops():
    np.testing.assert_allclose(M.BOP_MSSD_THRESHOLDS, [0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5])
    # diameter 1, fraction 0.5: below 0.5 counts, 0.5 itself does not ("below", as BOP's `<`)
    assert M.recall([0.25, 0.5, 0.75], 1.0, 0.5) == pytest.approx(1 / 3)
    assert M.recall([0.0], 2.0) == 1.0 and M.recall([0.3], 2.0) == 0.0  # default fraction 0.1 of 2: 0.2
    assert M.average_recall([np.nan], 1.0) == 0.0 and M.average_recall([0.0, 0.0], 1.0) == 1.0
    # one error of 0.3 on diameter 1: below 0.35 .. 0.5 (4 of 10 thresholds)
    assert M.average_recall([0.3], 1.0) == pytest.approx(0.4)
    assert np.isnan(M.average_recall([], 1.0))


def test_fitness_with_no_source_points():
    target = np.array([[0, 0, 0], [1, 0, 0]], float)
    assert M.fitness_rmse(target, np.zeros((0, 3)), 1.0) == (0.0, 0.0)
    # every target point explained: fitness 1, rmse the root mean square of 0.3 and 0.4
    f, r = M.fitness_rmse(target, target + [0, 0.3, 0], 0.5)
    assert f == 1.0 and r == pytest.approx(0.3)
    f, r = M.fitness_rmse(target, np.array([[0, 0.3, 0], [1, 0.4, 0]]), 0.5)
    assert f == 1.0 and r == pytest.approx(np.sqrt((0.09 + 0.16) / 2))


def test_add_adi_mssd_where_median_mean_and_max_differ():
    # Rx(180) keeps (0,0,0) and (1,0,0) and sends (0,2,0) to (0,-2,0): distances 0, 0, 4, so ADD = 4/3
    # (median 0), MSSD = 4; ADI: (0,2,0)'s nearest turned point is the origin, 2 away: 2/3
    Rx180 = make_T(np.diag([1.0, -1, -1]))
    assert M.add(Rx180, np.eye(4), TRI) == pytest.approx(4 / 3)
    assert M.adi(Rx180, np.eye(4), TRI) == pytest.approx(2 / 3)
    assert M.mssd(Rx180, np.eye(4), TRI) == pytest.approx(4.0)


def test_fitness_of_single_points_and_an_uneven_rmse():
    one = np.array([[0.0, 0, 0]])
    f, r = M.fitness_rmse(one, np.array([[0, 0.1, 0]]), 0.5)
    assert f == 1.0 and r == pytest.approx(0.1)
    f, r = M.fitness_rmse(np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([[0, 0.2, 0]]), 0.5)
    assert f == 0.5 and r == pytest.approx(0.2)
    # three inliers 0.1, 0.2, 0.4 away: RMS sqrt((0.01 + 0.04 + 0.16) / 3) (the median square would give 0.2)
    target = np.array([[0.0, 0, 0], [5, 0, 0], [10, 0, 0]])
    f, r = M.fitness_rmse(target, target + [[0, 0.1, 0], [0, 0.2, 0], [0, 0.4, 0]], 0.5)
    assert f == 1.0 and r == pytest.approx(np.sqrt(0.21 / 3))
