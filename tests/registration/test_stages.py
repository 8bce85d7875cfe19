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



def test_icps_side_by_side_give_each_start_the_pose_and_trace_it_gets_alone():
    """icp_point_to_plane_many answers every source's ICP as icp_point_to_plane does on its own, to the last bit,
    iteration by iteration (the searches run their starts side by side to share the k-d tree queries): sources
    that converge early, late or never, one too small to step, one empty, one that never comes near the target."""
    from apose_studio.geometry.nn import NearestTree, local_normals
    from apose_studio.registration.solvers import icp_point_to_plane, icp_point_to_plane_many

    rng = np.random.default_rng(7)
    u, v = np.meshgrid(np.linspace(-0.04, 0.04, 40), np.linspace(-0.03, 0.03, 30))
    tgt = np.stack([u.ravel(), v.ravel(), 0.01 * np.sin(60 * u.ravel()) + 0.008 * np.cos(80 * v.ravel())], axis=1)
    tgt = np.concatenate([tgt, tgt[::3] * [1, 1, 0] + [0.0, 0.0, -0.02]])  # a second sheet below: another basin
    nrm = local_normals(tgt, 12)
    srcs = [tgt[rng.choice(len(tgt), n, replace=False)] + rng.normal(0, 0.0005, (n, 3)) for n in (400, 250, 700)]
    srcs += [tgt[600:605] + [0.0, 0.0, 0.001], np.zeros((0, 3)), tgt[:300] + [0.5, 0.0, 0.0]]
    starts = [se3.make_T(se3.axis_angle_matrix(rng.normal(size=3), rng.normal(0, 0.08)), rng.normal(0, 0.004, 3)) for _ in srcs]
    starts[3] = np.eye(4)  # five points 1 mm off the target: matched, too few to step
    tree = NearestTree(tgt)
    alone, alone_traces = [], []
    for src, T0 in zip(srcs, starts):
        trace: list = []
        alone.append(icp_point_to_plane(src, tgt, nrm, T0, 0.006, 12, trace, tree))
        alone_traces.append(trace)
    traces: list = [[] for _ in srcs]
    together = icp_point_to_plane_many(srcs, tgt, nrm, starts, 0.006, 12, tree, traces)
    for k in range(len(srcs)):
        assert np.array_equal(together[k], alone[k]), k
        assert len(traces[k]) == len(alone_traces[k]) and all(np.array_equal(a, b) for a, b in zip(traces[k], alone_traces[k]))
    lengths = {len(t) for t in alone_traces[:3]}
    assert [len(t) for t in alone_traces[3:]] == [0, 0, 0] and len(lengths | {12}) > 1  # the cases differ, as meant
    assert not np.array_equal(alone[0], starts[0])  # and the ICP moved


def test_icp_many_runs_each_start_through_the_solver_the_setting_names():
    """stages.icp_many: with `deterministic` the starts go side by side through numpy's solver (each pose as `icp`
    gives it, to the bit); without, one at a time through Open3D's, which lands on the same poses to within a
    hundredth of a millimetre here (its sums run across threads: not to the bit)."""
    from apose_studio.geometry.nn import NearestTree, local_normals
    from apose_studio.registration.stages import icp_many

    rng = np.random.default_rng(3)
    u, v = np.meshgrid(np.linspace(-0.04, 0.04, 40), np.linspace(-0.03, 0.03, 30))
    tgt = np.stack([u.ravel(), v.ravel(), 0.01 * np.sin(60 * u.ravel()) + 0.008 * np.cos(80 * v.ravel())], axis=1)
    target = cloud(tgt, local_normals(tgt, 12))
    srcs = [tgt[rng.choice(len(tgt), 500, replace=False)] for _ in range(3)]
    starts = [se3.make_T(se3.axis_angle_matrix(rng.normal(size=3), 0.03), rng.normal(0, 0.002, 3)) for _ in srcs]
    mine = icp_many(srcs, target, starts, 0.006, 30, None, True, NearestTree(tgt))
    assert all(np.array_equal(T, icp(cloud(s), target, T0, 0.006, 30, None, True)) for s, T0, T in zip(srcs, starts, mine))
    theirs = icp_many(srcs, target, starts, 0.006, 30, None, False)
    for T, U, T0 in zip(mine, theirs, starts):
        assert np.linalg.norm(T[:3, 3] - U[:3, 3]) < 1e-5 and np.linalg.norm(T[:3, 3] - T0[:3, 3]) > 1e-4


def test_a_pose_at_the_camera_sees_nothing(gearbox_step2):
    """A candidate pose that puts the base's face through the camera (a free search's start did, on a 1280 x 960
    capture) cast every ray of the image onto it: no depth camera sees a base from there, so nothing is seen."""
    from apose_studio.registration.base import NEAREST_M

    _, base, _ = gearbox_step2
    T_world_camera = se3.look_at([0.25, -0.2, 0.3], [0, 0, 0.01])
    lo, hi = base.mesh.bounds
    eye_in_base = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] - 0.5 * NEAREST_M])  # just under its bottom
    R = T_world_camera[:3, :3]  # the base's +z along the camera's view: its bottom face fills the view from 2 cm
    T_world_base = se3.make_T(R, T_world_camera[:3, 3] - R @ eye_in_base)
    assert np.allclose(se3.transform_points(se3.inv(T_world_base), T_world_camera[:3, 3][None])[0], eye_in_base)
    seen, normals = raycast_source(base, T_world_base, T_world_camera, CAM)
    assert seen.shape == (0, 3) and normals.shape == (0, 3)
    T_away = se3.make_T(R, T_world_base[:3, 3] + 0.3 * R[:, 2])  # 30 cm farther along the view: seen
    assert 100 < len(raycast_source(base, T_away, T_world_camera, CAM)[0]) < 0.5 * CAM.width * CAM.height
