"""The Inspect tab's Robot folder: a hand-eye file draws the robot base where the calibration puts it, the
estimate's targets are listed in the robot's frame, and 'Estimate pick' finds the loose part and draws the
gripper where it picks it. Checked against the frame's own truth (the renderer's poses), not the code's."""

import json

import numpy as np

from apose_studio.estimation import truth_box
from apose_studio.geometry import se3

from ..conftest import rendered_frame, two_carriers, write_capture
from .conftest import act, errors

# the robot's base in the rendered world: 0.6 m along x, turned 30 deg about z
T_ROBOT_WORLD = se3.make_T(se3.axis_angle_matrix([0, 0, 1], np.radians(30)), [0.6, -0.2, 0.05])
GRASP = se3.make_T(np.diag([1.0, -1.0, -1.0]), [0, 0, 0.016])  # the twin's grasp below: 16 mm up, fingers down


def node_T(node) -> np.ndarray:
    return se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(node.wxyz)), np.asarray(node.position))


def test_robot_folder_draws_the_cell_and_the_gripper_at_place_preplace_and_pick(studio, tmp_path):
    asm = two_carriers(tmp_path)
    frame = rendered_frame(asm, 1, 0, noise="realsense", seed=3)
    cap = write_capture(frame, tmp_path / "capture")
    T_robot_camera = T_ROBOT_WORLD @ frame.T_world_camera
    (tmp_path / "cell.json").write_text(json.dumps({"T_robot_camera": T_robot_camera.tolist(), "robot_frame": "ur_base"}))
    st = studio(asm)
    st.inspect.i_path.value = str(cap)
    act(st, st.inspect.on_open_data)
    box = ",".join(map(str, truth_box(frame.base_mask())))
    st.prompt.i_prompt.value = box
    st.robot.i_hand_eye.value = str(tmp_path / "cell.json")
    act(st, st.robot.on_use_hand_eye)
    assert errors(st) == []
    # the robot base where the calibration puts it, before any estimate (the studio's world of a capture is its
    # own choice: the table level, seen from the camera)
    Tc = st.state.inspect.frame.T_world_camera
    np.testing.assert_allclose(node_T(st.nodes["/inspect/robot"]), Tc @ se3.inv(T_robot_camera), atol=1e-6)
    assert "ur_base" in st.robot.i_targets.content and "Estimate frame gives the place targets" in st.robot.i_targets.content

    act(st, lambda c: st.inspect.run_estimation(False, c))
    assert st.state.inspect.result is not None and st.state.inspect.result.ok
    md = st.robot.i_targets.content
    assert "| place |" in md and "| pre-place |" in md and "| pick |" not in md
    # the listed place is the truth's (mm): the part's true pose in the robot frame composed with the grasp
    T_camera_part_true = se3.inv(frame.T_world_camera) @ frame.T_world_part
    true_place = T_robot_camera @ T_camera_part_true @ GRASP
    row = next(line for line in md.splitlines() if line.startswith("| place |"))
    listed = np.array([float(v) for v in row.split("|")[2].split(",")])
    assert np.linalg.norm(listed - true_place[:3, 3] * 1000) < 5.0, (listed, true_place[:3, 3] * 1000)
    # the gripper drawn at the pre-place: 40 mm back along the approach from the place, fainter
    pre = node_T(st.nodes["/inspect/gripper_preplace"])
    place = node_T(st.nodes["/inspect/gripper"])
    np.testing.assert_allclose(pre[:3, :3], place[:3, :3], atol=1e-5)
    assert abs(np.linalg.norm(pre[:3, 3] - place[:3, 3]) - 0.040) < 1e-4

    # the pick: the loose part (here the base's twin) found where it lies, the gripper drawn by its grasp
    st.robot.i_pick.value = box
    act(st, st.robot.on_estimate_pick)
    assert [n for n in errors(st) if "Pick" in n[0] and "not confident" not in n[0]] == []
    picked = node_T(st.nodes["/inspect/gripper_pick"])
    truth = Tc @ se3.inv(frame.T_world_camera) @ frame.T_world_base @ GRASP
    assert np.linalg.norm(picked[:3, 3] - truth[:3, 3]) < 0.005
    md = st.robot.i_targets.content
    assert "| pick |" in md and "| lift |" in md
    assert "gripper" in st.results.i_legend.content
    # the download says where every number came from: the calibration file, the pick's prompt, the place's verdict
    sent = {}

    class Tab:
        def send_file_download(self, name, data, save_immediately=False):
            assert save_immediately  # saved on the button's click, not offered as a link to click again
            sent[name] = json.loads(data)

    st.robot.on_download(Tab())
    (doc,) = sent.values()
    assert doc["hand_eye_file"].endswith("cell.json") and doc["pick_prompt"] == box and doc["place"]["ok"]
    np.testing.assert_allclose(np.asarray(doc["T_robot_gripper_pick"]), T_robot_camera @ se3.inv(Tc) @ picked, atol=1e-9)
    # Pick at click: the ray through the loose part's middle pixel from the frame's camera gives the prompt and the pick
    vs, us = np.nonzero(frame.base_mask())
    k = np.argmin((us - us.mean()) ** 2 + (vs - vs.mean()) ** 2)
    ray = Tc[:3, :3] @ np.array([(us[k] - frame.camera.cx) / frame.camera.fx, (vs[k] - frame.camera.cy) / frame.camera.fy, 1])
    act(st, lambda c: st.robot.pick_at_ray(Tc[:3, 3], ray, c))
    u, v = map(int, st.robot.i_pick.value.split(","))
    assert frame.base_mask()[v, u] and "/inspect/gripper_pick" in st.nodes
    assert np.linalg.norm(node_T(st.nodes["/inspect/gripper_pick"])[:3, 3] - truth[:3, 3]) < 0.005
    assert st.state.inspect.pick()[0] == f"{u},{v}"
    # Drag a pick box: a rectangle around the loose part in a view from the frame's own camera gives its box
    from types import SimpleNamespace

    cam, (x0, y0, x1, y1) = frame.camera, truth_box(frame.base_mask())
    view = SimpleNamespace(wxyz=se3.matrix_to_quat_wxyz(Tc[:3, :3]), position=Tc[:3, 3],
                           fov=2 * np.arctan2(cam.height / 2, cam.fy), aspect=cam.width / cam.height)
    drag = SimpleNamespace(client=SimpleNamespace(camera=view), screen_min=(x0 / cam.width, y0 / cam.height),
                           screen_max=(x1 / cam.width, y1 / cam.height))
    act(st, lambda c: st.robot.pick_from_drag(drag, c))
    got = np.array(list(map(int, st.robot.i_pick.value.split(","))))
    assert np.abs(got - np.array([x0, y0, x1, y1])).max() <= 3, (got, (x0, y0, x1, y1))
    assert np.linalg.norm(node_T(st.nodes["/inspect/gripper_pick"])[:3, 3] - truth[:3, 3]) < 0.005
    # a pick prompt that fails takes the old pick away: nothing on screen answers a prompt it did not come from
    st.robot.i_pick.value = "abc"
    act(st, st.robot.on_estimate_pick)
    assert "Pick prompt 'abc'" in errors(st)[-1][1] and "Prompt at click" not in errors(st)[-1][1]
    assert "/inspect/gripper_pick" not in st.nodes and "| pick |" not in st.robot.i_targets.content
    # a refused calibration keeps the one in use, and says which
    (tmp_path / "mm.json").write_text(json.dumps({"T_robot_camera": se3.make_T(np.eye(3), [600.0, 0, 50.0]).tolist()}))
    st.robot.i_hand_eye.value = str(tmp_path / "mm.json")
    act(st, st.robot.on_use_hand_eye)
    assert "the calibration in use stays" in errors(st)[-1][1] and "cell.json" in errors(st)[-1][1]
    assert st.state.inspect.hand_eye.source.endswith("cell.json") and "/inspect/robot" in st.nodes
    # Use hand-eye frames the view on the robot base and the object together: both in front of the camera
    st.robot.i_hand_eye.value = str(tmp_path / "cell.json")
    act(st, st.robot.on_use_hand_eye)
    cam = st.server.initial_camera
    look = np.asarray(cam.look_at) - np.asarray(cam.position)
    for p in (node_T(st.nodes["/inspect/robot"])[:3, 3], st.state.inspect.result.T_world_part[:3, 3]):
        v = p - np.asarray(cam.position)
        assert v @ look / np.linalg.norm(v) / np.linalg.norm(look) > np.cos(np.radians(30))
    # the Layers checkbox hides the robot base
    st.results.layers["robot base"].value = False
    st.results.apply_layers()
    assert st.nodes["/inspect/robot"]._apose_visible is False


def test_robot_folder_refusals_name_the_fix(studio, tmp_path):
    asm = two_carriers(tmp_path)
    frame = rendered_frame(asm, 1, 0, noise="realsense", seed=3)
    cap = write_capture(frame, tmp_path / "capture")
    st = studio(asm)
    act(st, st.robot.on_estimate_pick)
    assert "open a capture" in errors(st)[-1][1]
    st.inspect.i_path.value = str(cap)
    act(st, st.inspect.on_open_data)
    act(st, st.robot.on_estimate_pick)
    assert "Pick prompt (px)" in errors(st)[-1][1]
    # eye-in-hand without the arm's pose at the capture: says where to put it
    (tmp_path / "hand.json").write_text(json.dumps({"T_flange_camera": np.eye(4).tolist()}))
    st.robot.i_hand_eye.value = str(tmp_path / "hand.json")
    act(st, st.robot.on_use_hand_eye)
    assert "T_robot_flange" in errors(st)[-1][1] and "camera.json" in errors(st)[-1][1]
    assert st.state.inspect.hand_eye is None and "/inspect/robot" not in st.nodes
    # a millimetre calibration: refused by the reader, naming the key
    bad = se3.make_T(np.eye(3), [600.0, 0, 50.0])
    (tmp_path / "mm.json").write_text(json.dumps({"T_robot_camera": bad.tolist()}))
    st.robot.i_hand_eye.value = str(tmp_path / "mm.json")
    act(st, st.robot.on_use_hand_eye)
    assert "T_robot_camera" in errors(st)[-1][1]
    act(st, st.robot.on_download)
    assert "hand-eye" in errors(st)[-1][1]
