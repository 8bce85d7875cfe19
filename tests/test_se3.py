"""Rigid transforms."""

"""The estimator's stages on small data, and degenerate inputs that must fail cleanly."""

import numpy as np

from apose_studio import se3


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

