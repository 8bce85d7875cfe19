"""Each metric against a case computed by hand."""

import numpy as np
import pytest

from apose_studio import metrics as M
from apose_studio.se3 import make_T


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
