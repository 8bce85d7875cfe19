"""Robot targets end to end on rendered frames whose camera poses are known in a robot frame: the CLI
(`apose estimate --hand-eye --mcap --json`) and the API, the MCAP read back with the standard reader, and the
gripper's place error equal to the part's pose error composed with the grasp."""

import json
import subprocess
import sys

import numpy as np
import pytest

from apose_studio.estimation import truth_box
from apose_studio.geometry import se3

from ..conftest import SAMPLES, mssd_to_truth, rendered_frame, two_carriers, write_capture

APOSE = [sys.executable, "-m", "apose_studio.cli.commands"]
PLANETARY = SAMPLES / "planetary_reducer" / "assembly.yaml"
# the robot's base: 0.6 m from the world's origin along x, turned 30 deg about z (the world of the frame, on the table)
T_ROBOT_WORLD = se3.make_T(se3.axis_angle_matrix([0, 0, 1], np.radians(30)), [0.6, -0.2, 0.05])


def diameter(assembly, part: str) -> float:
    from apose_studio.assembly.mesh import load_parts
    from apose_studio.assembly.model import load_assembly

    return load_parts(load_assembly(assembly))[part].diameter


@pytest.fixture(scope="module")
def housing_capture(tmp_path_factory):
    """Planetary step 2 (the 4-fold housing onto motor and sun gear), RealSense-like, as a capture folder, with an
    eye-to-hand calibration file made from the frame's true camera pose."""
    frame = rendered_frame(PLANETARY, 2, 0, noise="realsense", seed=7)
    folder = write_capture(frame, tmp_path_factory.mktemp("robot") / "capture")
    T_robot_camera = T_ROBOT_WORLD @ frame.T_world_camera
    (folder.parent / "cell.json").write_text(json.dumps({"T_robot_camera": T_robot_camera.tolist(), "robot_frame": "ur_base",
                                                         "camera_frame": "d435_color_optical_frame"}))
    return frame, folder, folder.parent / "cell.json", T_robot_camera


def test_cli_place_targets_json_and_mcap_agree_with_the_truth(housing_capture, tmp_path):
    from apose_studio.assembly.model import load_assembly
    from apose_studio.robot.ros2 import read_mcap

    frame, folder, cell, T_robot_camera = housing_capture
    box = ",".join(map(str, truth_box(frame.base_mask())))
    out = tmp_path / "targets.mcap"
    p = subprocess.run([*APOSE, "estimate", str(folder), "--assembly", str(PLANETARY), "--step", "2", "--box", box,
                        "--hand-eye", str(cell), "--mcap", str(out), "--json"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    G = load_assembly(PLANETARY).parts["housing"].grasps[0].T_part_gripper
    T_robot_part_true = T_robot_camera @ se3.inv(frame.T_world_camera) @ frame.T_world_part
    T_est = np.asarray(doc["T_robot_part"])
    assert mssd_to_truth(T_est, T_robot_part_true, PLANETARY, "housing") < 0.1 * diameter(PLANETARY, "housing")
    # the gripper's error is the part's error seen from the grasp: (T_true G)^-1 (T_est G) = G^-1 (T_true^-1 T_est) G
    grip_err = se3.inv(T_robot_part_true @ G) @ np.asarray(doc["T_robot_gripper_place"])
    np.testing.assert_allclose(grip_err, se3.inv(G) @ se3.inv(T_robot_part_true) @ T_est @ G, atol=1e-9)
    assert doc["grasp"] == "ring" and len(doc["gripper_alternatives"]) == 3  # the housing is 4-fold
    # pre-place: 40 mm up the base's z (the step's approach), the gripper held as at the place
    shift = np.asarray(doc["T_robot_gripper_preplace"])[:3, 3] - np.asarray(doc["T_robot_gripper_place"])[:3, 3]
    np.testing.assert_allclose(shift, 0.040 * np.asarray(doc["T_robot_base"])[:3, 2], atol=1e-9)
    assert doc["conventions"]["robot_frame"] == "ur_base"
    # the MCAP, read back with the standard reader: every PoseStamped is the JSON's pose, quaternions x, y, z, w
    messages = read_mcap(out)
    topics = {t: m for t, m in messages}
    for topic, key in (("/apose/place/gripper", "T_robot_gripper_place"), ("/apose/place/preplace", "T_robot_gripper_preplace"),
                       ("/apose/place/part", "T_robot_part")):
        pose = topics[topic].pose
        assert topics[topic].header.frame_id == "ur_base"
        T = np.asarray(doc[key])
        np.testing.assert_allclose([pose.position.x, pose.position.y, pose.position.z], T[:3, 3], atol=1e-12)
        q = pose.orientation
        np.testing.assert_allclose(se3.quat_wxyz_to_matrix([q.w, q.x, q.y, q.z]), T[:3, :3], atol=1e-9)
    tf = {t.child_frame_id: t for t in topics["/tf_static"].transforms}
    assert set(tf) >= {"d435_color_optical_frame", "apose_base", "apose_gripper_place", "apose_gripper_preplace"}
    np.testing.assert_allclose([tf["d435_color_optical_frame"].transform.translation.x], [T_robot_camera[0, 3]], atol=1e-12)
    assert len(topics["/apose/place/approach"].poses) == 2 and len(topics["/apose/place/alternatives"].poses) == 3


def test_cli_refuses_robot_flags_without_a_calibration_and_unknown_grasps(housing_capture, tmp_path):
    frame, folder, cell, _ = housing_capture
    p = subprocess.run([*APOSE, "estimate", str(folder), "--assembly", str(PLANETARY), "--step", "2", "--mcap",
                        str(tmp_path / "x.mcap")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "--mcap needs --hand-eye" in p.stderr and "Traceback" not in p.stderr
    p = subprocess.run([*APOSE, "estimate", str(folder), "--assembly", str(PLANETARY), "--step", "2", "--hand-eye",
                        str(cell), "--grasp", "handle"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "its grasps: ring" in p.stderr and "Traceback" not in p.stderr


def test_api_pick_finds_the_loose_part_where_it_lies(tmp_path):
    """A loose part is found by the same registration with its own CAD as the base: here the step's part has the
    base's shape (two carriers), so where it lies is the base's true pose."""
    from apose_studio.api import estimate_pose
    from apose_studio.robot.handeye import HandEye

    two_carriers(tmp_path)
    frame = rendered_frame(tmp_path / "two.yaml", 1, 0, noise="realsense", seed=3)
    T_robot_camera = T_ROBOT_WORLD @ frame.T_world_camera
    box = truth_box(frame.base_mask())
    est = estimate_pose(frame.rgb, frame.depth, frame.K, tmp_path / "two.yaml", 1, box=box,
                        T_world_camera=frame.T_world_camera, hand_eye=HandEye("eye_to_hand", T_robot_camera),
                        pick_box=box)
    t = est.targets
    assert t.pick["ok"], t.pick
    assert est.timings["pick"] > 0 and "pick" in est.to_json()["timings_s"]  # its time said apart from the place's
    truth = T_robot_camera @ se3.inv(frame.T_world_camera) @ frame.T_world_base
    assert mssd_to_truth(t.T_robot_part_pick, truth, tmp_path / "two.yaml", "twin") < 0.1 * diameter(tmp_path / "two.yaml", "twin")
    # the gripper at the pick, seen from the part, is the grasp
    np.testing.assert_allclose(se3.inv(t.T_robot_part_pick) @ t.T_robot_gripper_pick,
                               se3.make_T(np.diag([1.0, -1.0, -1.0]), [0, 0, 0.016]), atol=1e-9)
    lift = t.T_robot_gripper_lift[:3, 3] - t.T_robot_gripper_pick[:3, 3]
    np.testing.assert_allclose(lift, -0.05 * t.T_robot_gripper_pick[:3, 2], atol=1e-12)
