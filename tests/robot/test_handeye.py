"""Hand-eye calibration files (robot/handeye.py): our 4x4 forms, a bare matrix, easy_handeye2's and
easy_handeye's files (quaternions x, y, z, w), and bad files refused with the key and the fix."""

import json

import numpy as np
import pytest

from apose_studio.errors import AposeError
from apose_studio.robot.handeye import read_hand_eye

S = np.sqrt(0.5)
RZ90 = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]

EASY_HANDEYE2 = """\
parameters:
  name: cell_a
  calibration_type: {kind}
  robot_base_frame: ur_base_link
  robot_effector_frame: tool0
  tracking_base_frame: camera_color_optical_frame
  tracking_marker_frame: aruco_marker
  freehand_robot_movement: false
transform:
  translation: {{x: 0.9, y: -0.1, z: 0.5}}
  rotation: {{x: 0.0, y: 0.0, z: {s}, w: {s}}}
"""


def test_easy_handeye2_eye_on_base_is_T_robot_camera_with_xyzw(tmp_path):
    f = tmp_path / "cell.calib"
    f.write_text(EASY_HANDEYE2.format(kind="eye_on_base", s=S))
    he = read_hand_eye(f)
    assert he.kind == "eye_to_hand" and he.robot_frame == "ur_base_link" and he.camera_frame == "camera_color_optical_frame"
    # x, y, z, w = (0, 0, sin 45, cos 45): a quarter turn about z (read as w, x, y, z it would be another rotation)
    np.testing.assert_allclose(he.T_robot_camera()[:3, :3], RZ90, atol=1e-12)
    np.testing.assert_allclose(he.T_robot_camera()[:3, 3], (0.9, -0.1, 0.5), atol=1e-12)
    assert he.notes == ()


def test_easy_handeye2_eye_in_hand_and_the_older_format(tmp_path):
    f = tmp_path / "hand.calib"
    f.write_text(EASY_HANDEYE2.format(kind="eye_in_hand", s=S).replace("camera_color_optical_frame", "camera_link"))
    he = read_hand_eye(f)
    assert he.kind == "eye_in_hand" and he.flange_frame == "tool0"
    assert any("not an optical frame" in n for n in he.notes)  # camera_link's axes differ from the optical frame's
    old = tmp_path / "old.yaml"
    old.write_text(f"eye_on_hand: true\nrobot_effector_frame: flange\ntracking_base_frame: cam_optical_frame\n"
                   f"transformation: {{x: 0.01, y: 0.02, z: 0.03, qx: 0, qy: 0, qz: {S}, qw: {S}}}\n")
    he = read_hand_eye(old)
    assert he.kind == "eye_in_hand"
    np.testing.assert_allclose(he.T[:3, :3], RZ90, atol=1e-12)
    np.testing.assert_allclose(he.T_robot_camera(np.eye(4))[:3, 3], (0.01, 0.02, 0.03), atol=1e-12)


def test_our_forms_and_a_bare_matrix(tmp_path):
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = RZ90, (0.2, 0.3, 0.4)
    (tmp_path / "a.json").write_text(json.dumps({"T_robot_camera": M.tolist(), "robot_frame": "world"}))
    (tmp_path / "b.yaml").write_text(f"T_flange_camera: {M.tolist()}\nT_robot_flange: {np.eye(4).tolist()}\n")
    (tmp_path / "c.txt").write_text("\n".join(" ".join(map(str, r)) for r in M.tolist()))
    (tmp_path / "d.json").write_text(json.dumps(M.tolist()))
    a, b, c, d = (read_hand_eye(tmp_path / n) for n in ("a.json", "b.yaml", "c.txt", "d.json"))
    assert a.robot_frame == "world" and b.kind == "eye_in_hand" and c.kind == d.kind == "eye_to_hand"
    for he in (a, b, c, d):
        np.testing.assert_allclose(he.T_robot_camera(), M, atol=1e-12)


@pytest.mark.parametrize("text, words", [
    ("T_robot_camera: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]", "4x4"),
    ("T_robot_camera: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]", "not orthonormal"),
    ("T_robot_camera: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]]", "reflection"),
    ("T_robot_camera: [[1, 0, 0, 900], [0, 1, 0, 0], [0, 0, 1, 400], [0, 0, 0, 1]]", "millimetres"),
    ("T_robot_camera: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.5, 0, 0, 1]]", "transposed"),
    ("T_robot_camera: [[1, 0, 0, .nan], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]", "NaN"),
    ("camera: {x: 1}", "missing T_robot_camera"),
    ("T_robot_camera: [[true, false, false, false], [false, true, false, false], [false, false, true, false], "
     "[false, false, false, true]]", "matrix of numbers"),
    ("T_robot_camera: [['1', 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]", "matrix of numbers"),
    ("parameters: {calibration_type: eye_on_base}\ntransform: {translation: {x: 0, y: 0}, rotation: {x: 0, y: 0, z: 0, "
     "w: 1}}", "transform.translation.z"),
    ("parameters: {calibration_type: eye_on_base}\ntransform: {translation: {x: 0, y: 0, z: 0}, rotation: {x: 0, y: 0, "
     "z: 0, w: 2}}", "not a rotation quaternion"),
    ("parameters: {calibration_type: sideways}\ntransform: {}", "eye_on_base or eye_in_hand"),
    ("a: &x [1]\nb: *x", "YAML"),
    ("T_robot_camera: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\nT_flange_camera: []", "both"),
])
def test_bad_calibration_files_name_the_key_and_the_fix(tmp_path, text, words):
    f = tmp_path / "calib.yaml"
    f.write_text(text)
    with pytest.raises(AposeError, match=words) as e:
        read_hand_eye(f)
    assert str(f) in str(e.value)


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(AposeError, match="missing|not found|No such"):
        read_hand_eye(tmp_path / "nope.yaml")
    (tmp_path / "m.txt").write_text("1 0 0\nx y z\n")
    with pytest.raises(AposeError, match="4 rows of 4 numbers"):
        read_hand_eye(tmp_path / "m.txt")
