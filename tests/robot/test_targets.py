"""Pick-and-place targets (robot/targets.py, api.robot_targets) against poses worked out by hand: an
eye-to-hand and an eye-in-hand cell, a grasp with a rotation, a pre-place along the step's approach, the
alternatives of a symmetric part, and the lift after a pick."""

import numpy as np
import pytest

from apose_studio.assembly.grasps import Grasp
from apose_studio.assembly.mates import Approach
from apose_studio.assembly.model import Symmetry
from apose_studio.robot.handeye import HandEye
from apose_studio.robot.targets import add_pick, place_targets, pose_record


def T(R=None, t=(0, 0, 0)):
    out = np.eye(4)
    if R is not None:
        out[:3, :3] = R
    out[:3, 3] = t
    return out


RX180 = np.diag([1.0, -1.0, -1.0])  # a half turn about x
RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

# a camera 0.8 m above the robot's base frame at (0.5, 0, 0.8), looking straight down (optical z = robot -z)
T_ROBOT_CAMERA = T(RX180, (0.5, 0.0, 0.8))
# the part 0.7 m in front of the camera, 0.1 m along the camera's x: in the robot frame at (0.6, 0, 0.1),
# turned as the camera is (its z down)
T_CAMERA_PART = T(None, (0.1, 0.0, 0.7))
# a grasp from the part's +z side: TCP 20 mm above the part's origin, its z pointing down into the part, the
# jaws closing along the part's x (the TCP's y = part x)
GRASP = Grasp("top", T(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), (0.0, 0.0, 0.02)), 0.03)


def test_eye_to_hand_place_preplace_by_hand():
    # the base 5 cm below the part in the camera frame (further along the optical axis), same orientation
    T_camera_base = T(None, (0.1, 0.0, 0.75))
    approach = Approach(np.array([0.0, 0.0, -1.0]), 0.04)  # the part comes down its base's -z, from 40 mm
    t = place_targets(T_ROBOT_CAMERA, T_camera_base, T_CAMERA_PART, GRASP, approach, None)
    # the part: robot = camera's (0.5, 0, 0.8) + RX180 (0.1, 0, 0.7) = (0.6, 0, 0.1), rotation RX180
    np.testing.assert_allclose(t.T_robot_part, T(RX180, (0.6, 0.0, 0.1)), atol=1e-12)
    np.testing.assert_allclose(t.T_robot_base, T(RX180, (0.6, 0.0, 0.05)), atol=1e-12)
    # the gripper: the part's pose times the grasp; the TCP 20 mm along the part's +z = robot -z: z = 0.08;
    # its axes: x = RX180 (part y) = -y_robot, y = RX180 (part x) = +x_robot, z = RX180 (-part z) = +z_robot
    expected_R = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(t.T_robot_gripper_place, T(expected_R, (0.6, 0.0, 0.08)), atol=1e-12)
    # pre-place: the part 40 mm back along -(base -z) = base +z = robot -z; the gripper with it
    np.testing.assert_allclose(t.T_robot_part_preplace, T(RX180, (0.6, 0.0, 0.06)), atol=1e-12)
    np.testing.assert_allclose(t.T_robot_gripper_preplace, T(expected_R, (0.6, 0.0, 0.04)), atol=1e-12)
    assert t.grasp == "top" and t.width == 0.03 and t.gripper_alternatives == []
    rec = pose_record(t.T_robot_gripper_place)  # Rz(-90 deg): w = cos 45, z = -sin 45
    np.testing.assert_allclose(rec["quat_wxyz"], [np.sqrt(0.5), 0, 0, -np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(rec["quat_xyzw"], [0, 0, -np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_eye_in_hand_composes_the_flange_and_the_calibration():
    # the flange at (0.4, 0.2, 0.5) turned 90 deg about z; the camera 0.1 m along the flange's x, same axes
    he = HandEye("eye_in_hand", T(None, (0.1, 0.0, 0.0)), source="calib")
    T_robot_flange = T(RZ90, (0.4, 0.2, 0.5))
    # the flange's x is the robot's y: the camera at (0.4, 0.3, 0.5), turned as the flange
    np.testing.assert_allclose(he.T_robot_camera(T_robot_flange), T(RZ90, (0.4, 0.3, 0.5)), atol=1e-12)
    with pytest.raises(Exception, match="T_robot_flange"):
        he.T_robot_camera()  # eye-in-hand without the arm's pose: said, not guessed


def test_a_four_fold_part_lists_its_three_other_grasps():
    sym = Symmetry((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), 4)
    t = place_targets(T_ROBOT_CAMERA, T_CAMERA_PART, T_CAMERA_PART, GRASP, None, sym)
    assert len(t.gripper_alternatives) == 3
    # the part a quarter turn about its z: the TCP at the same point (it lies on the axis), turned about robot z
    # by -90 deg (the part's z points down in the robot frame)
    q = t.gripper_alternatives[0]
    np.testing.assert_allclose(q[:3, 3], (0.6, 0.0, 0.08), atol=1e-12)
    np.testing.assert_allclose(q[:3, :3], t.T_robot_gripper_place[:3, :3] @ GRASP.T_part_gripper[:3, :3].T @ RZ90
                               @ GRASP.T_part_gripper[:3, :3], atol=1e-12)
    assert "90 deg" in t.alternatives_why[0]
    # without an approach the pre-place backs off along the gripper's own -z (up, here), and says so
    np.testing.assert_allclose(t.T_robot_gripper_preplace[:3, 3], (0.6, 0.0, 0.03), atol=1e-12)
    assert any("no approach" in n for n in t.notes)


def test_a_continuous_symmetry_gives_samples_and_its_axis():
    sym = Symmetry((0.0, 0.0, 1.0), (0.01, 0.0, 0.0), 0)
    t = place_targets(T_ROBOT_CAMERA, T_CAMERA_PART, T_CAMERA_PART, GRASP, None, sym)
    assert len(t.gripper_alternatives) == 7  # 8 samples, identity being the estimate itself
    np.testing.assert_allclose(t.symmetry_axis["point"], (0.61, 0.0, 0.1), atol=1e-12)
    np.testing.assert_allclose(t.symmetry_axis["direction"], (0.0, 0.0, -1.0), atol=1e-12)
    # a half turn about an axis 10 mm off the part's origin: the TCP (on the part's origin axis) moves 20 mm
    half = t.gripper_alternatives[3]
    assert np.linalg.norm(half[:3, 3] - t.T_robot_gripper_place[:3, 3]) == pytest.approx(0.02, abs=1e-12)


def test_the_lift_backs_off_along_the_gripper():
    t = place_targets(T_ROBOT_CAMERA, T_CAMERA_PART, T_CAMERA_PART, GRASP, None, None)
    add_pick(t, T(RX180, (0.3, -0.2, 0.0)), GRASP, lift=0.05)  # the loose part on the table, upside down as placed
    np.testing.assert_allclose(t.T_robot_gripper_pick[:3, 3], (0.3, -0.2, -0.02), atol=1e-12)
    np.testing.assert_allclose(t.T_robot_gripper_lift[:3, 3], (0.3, -0.2, -0.07), atol=1e-12)  # gripper z is up here
    doc = t.to_json()
    for key in ("T_robot_part", "T_robot_gripper_place", "T_robot_gripper_preplace", "T_robot_part_pick",
                "T_robot_gripper_pick", "T_robot_gripper_lift"):
        assert np.asarray(doc[key]).shape == (4, 4), key
    assert doc["conventions"]["units"] == "metres"


def test_no_grasp_gives_the_part_poses_and_says_why():
    t = place_targets(T_ROBOT_CAMERA, T_CAMERA_PART, T_CAMERA_PART, None, None, None)
    assert t.T_robot_gripper_place is None and t.T_robot_part is not None
    assert any("grasps" in n for n in t.notes)


def test_two_writers_of_one_mcap_never_share_a_temporary_file(tmp_path):
    """Two programs writing the same --mcap at once: each write is whole (its own temporary file, renamed into
    place), the file is always one of them, and no temporary file is left behind."""
    import threading

    from apose_studio.robot.ros2 import read_mcap, write_mcap

    approach = Approach(np.array([0.0, 0.0, -1.0]), 0.04)
    t = place_targets(T_ROBOT_CAMERA, T(None, (0.1, 0.0, 0.75)), T_CAMERA_PART, GRASP, approach, None)
    out, errors = tmp_path / "targets.mcap", []

    def write() -> None:
        try:
            for _ in range(30):
                write_mcap(out, t)
        except Exception as e:  # noqa: BLE001 - the test reports it
            errors.append(e)

    threads = [threading.Thread(target=write) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert errors == []
    topics = dict(read_mcap(out))
    assert topics["/apose/place/gripper"].pose.position.z == pytest.approx(t.T_robot_gripper_place[2, 3])
    assert [p.name for p in tmp_path.iterdir()] == ["targets.mcap"]
