"""PROJ3D, RCAST and ICP by hand."""

import numpy as np
import pytest

from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.registration import icp, project_to_cloud, raycast_source
from apose_studio.registration.stages import cloud

from .conftest import CAM


def test_project_to_cloud_by_hand():
    depth = np.zeros((480, 640), np.float32)
    depth[240, 320] = 0.5  # the principal point: straight ahead
    depth[240, 443] = 1.0  # 123 px right of it at 1 m: x = 123 / 615 = 0.2 m
    depth[0, 0] = np.nan
    mask = np.ones_like(depth, bool)
    T_world_camera = se3.make_T(t=[0, 0, 2.0])
    pts = project_to_cloud(depth, mask, CAM, T_world_camera)
    np.testing.assert_allclose(sorted(pts.tolist()), [[0, 0, 2.5], [0.2, 0, 3.0]], atol=1e-6)
    with pytest.raises(AposeError, match="mask is 2x2 but depth is 640x480"):
        project_to_cloud(depth, np.ones((2, 2), bool), CAM, T_world_camera)


def test_icp_recovers_a_known_small_motion(gearbox_step2):
    _, base, _ = gearbox_step2
    T_world_camera = se3.look_at([0.25, -0.2, 0.3], [0, 0, 0.01])
    T_true = se3.make_T(se3.axis_angle_matrix([0.3, 0.2, 1.0], np.radians(40)), [0.01, -0.02, 0.0])
    target_w, target_n = raycast_source(base, T_true, T_world_camera, CAM)
    target = cloud(target_w, target_n)
    source = cloud(se3.transform_points(se3.inv(T_true), target_w)).voxel_down_sample(0.001)
    T0 = T_true @ se3.make_T(se3.axis_angle_matrix([1, 0, 0], np.radians(3)), [0.002, -0.001, 0.0015])
    T = icp(source, target, T0, 0.005, 60)
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 5e-4
    assert se3.rotation_angle_deg(T[:3, :3].T @ T_true[:3, :3]) < 0.2
    trace = []
    icp(source, target, T0, 0.005, 60, trace)
    assert len(trace) >= 2 and np.linalg.norm(trace[-1][:3, 3] - T_true[:3, 3]) < 5e-4

