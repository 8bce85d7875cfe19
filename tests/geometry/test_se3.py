"""Rigid transforms, each against a case worked out by hand (or scipy's, for the vectorised Rodrigues)."""

import numpy as np
import pytest

from apose_studio.geometry import se3


def test_rotations_vectorised_and_rigid_fit():
    from scipy.spatial.transform import Rotation

    axis = np.array([0.3, -1.0, 2.0])
    angles = np.array([0.0, 0.4, 2.5, np.pi])
    Rs = se3.axis_angle_matrix(axis, angles)
    assert Rs.shape == (4, 3, 3)
    for R, a in zip(Rs, angles):
        np.testing.assert_allclose(R, Rotation.from_rotvec(axis / np.linalg.norm(axis) * a).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(se3.axis_angle_matrix(axis, a), R, atol=1e-15)
    src = np.random.default_rng(0).normal(size=(50, 3))
    T = se3.make_T(Rs[2], [0.1, -0.2, 0.3])
    np.testing.assert_allclose(se3.fit_rigid(src, se3.transform_points(T, src)), T, atol=1e-9)



def Rz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def Rx(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def random_transforms(n=20, seed=1):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    return [se3.make_T(R, rng.normal(size=3)) for R in Rotation.random(n, random_state=seed).as_matrix()]


def test_make_T_and_transform_points_by_hand():
    np.testing.assert_array_equal(se3.make_T(), np.eye(4))
    T = se3.make_T(Rz(90), np.array([[1.0], [2.0], [3.0]]))  # a column vector is fine
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    # (1, 0, 0) turned a quarter about z is (0, 1, 0), then moved by (1, 2, 3)
    np.testing.assert_allclose(se3.transform_points(T, np.array([[1.0, 0, 0], [0, 0, 1.0]])), [[1, 3, 3], [1, 2, 4]],
                               atol=1e-12)


def test_inverse_of_random_rigid_transforms():
    for T in random_transforms():
        Ti = se3.inv(T)
        np.testing.assert_allclose(Ti @ T, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(T @ Ti, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(Ti[3], [0, 0, 0, 1])
    # by hand: a quarter turn about z then (1, 2, 3); back: R^T, -R^T t = -(2, -1, 3)
    np.testing.assert_allclose(se3.inv(se3.make_T(Rz(90), [1, 2, 3]))[:3, 3], [-2, 1, -3], atol=1e-12)


def test_quaternions_wxyz_by_hand_and_round_trips():
    h = np.sqrt(0.5)
    np.testing.assert_allclose(se3.quat_wxyz_to_matrix([h, 0, 0, h]), Rz(90), atol=1e-12)  # w first
    np.testing.assert_allclose(se3.quat_wxyz_to_matrix([h, h, 0, 0]), Rx(90), atol=1e-12)
    np.testing.assert_allclose(se3.quat_wxyz_to_matrix([2.0, 0, 0, 0]), np.eye(3), atol=1e-12)  # normalised
    np.testing.assert_allclose(se3.quat_wxyz_to_matrix([-h, 0, 0, -h]), Rz(90), atol=1e-12)  # q and -q alike
    np.testing.assert_allclose(se3.matrix_to_quat_wxyz(Rz(90)), [h, 0, 0, h], atol=1e-12)
    np.testing.assert_allclose(se3.matrix_to_quat_wxyz(Rz(-90)), [h, 0, 0, -h], atol=1e-12)
    np.testing.assert_allclose(se3.matrix_to_quat_wxyz(np.diag([1.0, -1, -1])), [0, 1, 0, 0], atol=1e-12)
    negative = 0
    for T in random_transforms(50):
        R = T[:3, :3]
        q = se3.matrix_to_quat_wxyz(R)
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(se3.quat_wxyz_to_matrix(q), R, atol=1e-12)
        np.testing.assert_allclose(se3.quat_wxyz_to_matrix(-q), R, atol=1e-12)
        from scipy.spatial.transform import Rotation

        negative += Rotation.from_matrix(R).as_quat()[3] < 0
    assert negative > 0  # some of these come out of scipy with w < 0: the sign rule was exercised


def test_euler_degrees_extrinsic_and_intrinsic():
    np.testing.assert_allclose(se3.euler_deg_to_matrix([0, 0, 90], "xyz"), Rz(90), atol=1e-12)
    np.testing.assert_allclose(se3.euler_deg_to_matrix([90, 0, 0], "xyz"), Rx(90), atol=1e-12)
    # extrinsic x then z: R = Rz Rx; intrinsic X then Z: R = Rx Rz
    np.testing.assert_allclose(se3.euler_deg_to_matrix([90, 0, 90], "xyz"), Rz(90) @ Rx(90), atol=1e-12)
    np.testing.assert_allclose(se3.euler_deg_to_matrix([90, 0, 90], "XYZ"), Rx(90) @ Rz(90), atol=1e-12)


def test_rotation_angles_known():
    for deg in (0.0, 1.0, 30.0, 90.0, 135.0, 179.0, 180.0):
        assert se3.rotation_angle_deg(Rz(deg)) == pytest.approx(deg, abs=1e-6)
        assert se3.rotation_angle_deg(Rz(-deg)) == pytest.approx(deg, abs=1e-6)  # in [0, 180]
        assert se3.rotation_angle_deg(se3.axis_angle_matrix([1.0, 2.0, -2.0], np.radians(deg))) == pytest.approx(
            deg, abs=1e-6)
    # rounding that puts the cosine past +-1 still gives an angle, not NaN
    assert se3.rotation_angle_deg(np.eye(3) * (1 + 1e-12)) == 0.0
    assert se3.rotation_angle_deg(np.diag([1.0, -1, -1]) * (1 + 1e-12)) == 180.0
    # a quarter about an unnormalised axis, by hand
    np.testing.assert_allclose(se3.axis_angle_matrix([0, 0, 5.0], np.pi / 2), Rz(90), atol=1e-12)
    np.testing.assert_allclose(se3.axis_angle_matrix([0, 0, 1.0], [np.pi / 2, -np.pi / 2]), [Rz(90), Rz(-90)],
                               atol=1e-12)


def test_perpendicular_for_every_direction():
    rng = np.random.default_rng(2)
    # the helper crossed with v must never be parallel to it: along and between the axes, near x, tiny, huge
    vs = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [1, 1, 0], [1, 0, 1], [-1, -1, 0], [0, 1, 1], [1, 1, 1],
          [0.95, 0.1, 0.0], [0.89, 0.45, 0.0], [1e-8, 0, 0], [1e6, 1.0, 0.0], *rng.normal(size=(30, 3))]
    for v in vs:
        p = se3.perpendicular(v)
        assert np.linalg.norm(p) == pytest.approx(1.0), v
        assert abs(np.dot(p, v)) < 1e-9 * np.linalg.norm(v), v


def test_rigid_fit_is_a_rotation_never_a_mirror():
    src = np.random.default_rng(3).normal(size=(40, 3))
    T = se3.fit_rigid(src, src * [-1.0, 1, 1])  # the best orthogonal fit is the mirror; Kabsch must refuse it
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    # pure translation, by hand
    np.testing.assert_allclose(se3.fit_rigid(src, src + [1, 2, 3]), se3.make_T(t=[1, 2, 3]), atol=1e-12)


def _orthonormal(T):
    R = T[:3, :3]
    assert np.all(np.isfinite(T))
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_look_at_by_hand():
    # from (0, -1, 0) towards the origin with z up: z = +y, x = z x up = +x, y = z x x = -z (image down)
    T = se3.look_at([0, -1, 0], [0, 0, 0])
    _orthonormal(T)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0, -1, 0])
    # the target is straight ahead (camera z); a point above it is up in the image (v < 0)
    p = se3.transform_points(se3.inv(T), np.array([[0, 0, 0], [0, 0, 1.0]]))
    np.testing.assert_allclose(p, [[0, 0, 1], [0, -1, 1]], atol=1e-12)
    # straight down along up: another up is used; by hand up = +y, x = -z x +y = +x, y = -z x +x = -y
    down = se3.look_at([0, 0, 1], [0, 0, 0], up=(0, 0, 0.5))  # an unnormalised up
    _orthonormal(down)
    np.testing.assert_allclose(down[:3, :3], np.diag([1.0, -1, -1]), atol=1e-12)
    # along a y up: up = +x; x = +y x +x = -z, y = +y x -z = -x
    sideways = se3.look_at([0, -1, 0], [0, 0, 0], up=(0, 1, 0))
    _orthonormal(sideways)
    np.testing.assert_allclose(sideways[:3, :3], [[0, -1, 0], [0, 0, 1], [-1, 0, 0]], atol=1e-12)
    # straight down -y along a y up: up = +x again; x = -y x +x = +z, y = -y x +z = -x
    np.testing.assert_allclose(se3.look_at([0, 1, 0], [0, 0, 0], up=(0, 1, 0))[:3, :3], [[0, -1, 0], [0, 0, -1], [1, 0, 0]],
                               atol=1e-12)
    # along an x up: up = +y; x = +x x +y = +z, y = +x x +z = -y
    np.testing.assert_allclose(se3.look_at([-1, 0, 0], [0, 0, 0], up=(1, 0, 0))[:3, :3], [[0, 0, 1], [0, -1, 0], [1, 0, 0]],
                               atol=1e-12)
    # along an up of (0, 0.6, 0.8) (|z_y| = 0.6 < 0.9: up = +y): x = z x y / |.| = -x, y = z x x = (0, -0.8, 0.6)
    np.testing.assert_allclose(se3.look_at([0, -0.6, -0.8], [0, 0, 0], up=(0, 0.6, 0.8))[:3, :3],
                               [[-1, 0, 0], [0, -0.8, 0.6], [0, 0.6, 0.8]], atol=1e-12)
    # 1 deg off a y up (within the 0.999 cosine): up = +x; z = (0, c, s): x = z x +x = (0, s, -c), y = z x x = -x
    c, s = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
    np.testing.assert_allclose(se3.look_at([0, -c, -s], [0, 0, 0], up=(0, 1, 0))[:3, :3], [[0, -1, 0], [s, 0, c], [-c, 0, s]],
                               atol=1e-12)
    rng = np.random.default_rng(4)
    for _ in range(20):
        eye, target = rng.normal(size=3), rng.normal(size=3)
        T = se3.look_at(eye, target)
        _orthonormal(T)
        np.testing.assert_allclose(T[:3, 2], (target - eye) / np.linalg.norm(target - eye), atol=1e-12)
        assert abs(T[:3, 0] @ [0, 0, 1]) < 1e-12 and T[:3, 1] @ [0, 0, 1] <= 0  # x level, y down


def test_scale_motion_repeats_and_halves_a_motion():
    from apose_studio.geometry.se3 import axis_angle_matrix, make_T, scale_motion

    R = axis_angle_matrix(np.array([0.3, -0.5, 0.8]), 0.2)
    T = make_T(R, np.array([0.01, -0.02, 0.005]))
    np.testing.assert_allclose(scale_motion(T, 1.0), T, atol=1e-12)
    np.testing.assert_allclose(scale_motion(T, 2.0)[:3, :3], R @ R, atol=1e-12)
    half = scale_motion(T, 0.5)[:3, :3]
    np.testing.assert_allclose(half @ half, R, atol=1e-12)
    np.testing.assert_allclose(scale_motion(T, 3.0)[:3, 3], 3 * T[:3, 3])
    np.testing.assert_allclose(scale_motion(np.eye(4), 5.0), np.eye(4))
    np.testing.assert_allclose(scale_motion(T, 0.0), np.eye(4), atol=1e-12)


def test_turn_about_a_line_by_hand():
    """A quarter turn about the vertical line through (1, 0, 0): that line stays, the origin goes to (1, -1, 0);
    an array of angles gives the same turns stacked."""
    T = se3.turn_about([0.0, 0.0, 2.0], np.pi / 2, [1.0, 0.0, 0.0])
    assert np.allclose(se3.transform_points(T, np.array([[1.0, 0.0, 5.0], [0.0, 0.0, 0.0]])),
                       [[1.0, 0.0, 5.0], [1.0, -1.0, 0.0]])
    assert np.allclose(T[3], [0, 0, 0, 1])
    Ts = se3.turn_about([0.0, 0.0, 1.0], np.array([0.0, np.pi / 2]), [1.0, 0.0, 0.0])
    assert Ts.shape == (2, 4, 4) and np.allclose(Ts[0], np.eye(4)) and np.allclose(Ts[1], T)
