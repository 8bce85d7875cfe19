"""A grasp from one picked face (robot/grasping.py), against a box and a cylinder worked out by hand."""

import numpy as np
import pytest
import trimesh

from apose_studio.errors import AposeError
from apose_studio.robot.grasping import APPROACHES, grasp_at_face, gripper_mesh


def test_a_flat_face_grasps_across_to_the_face_opposite():
    box = trimesh.creation.box((0.04, 0.02, 0.01))  # x 40 mm, y 20 mm, z 10 mm, centred
    g = grasp_at_face(box, "plane", (0.02, 0.003, 0.001), (1, 0, 0), 0.0, APPROACHES["from +z"], "g")
    np.testing.assert_allclose(g.T_part_gripper[:3, 3], (0.0, 0.003, 0.001), atol=1e-7)  # midway between x = +-20 mm
    assert g.width == pytest.approx(0.04, abs=1e-7)
    R = g.T_part_gripper[:3, :3]
    np.testing.assert_allclose(R[:, 1], (1, 0, 0), atol=1e-12)  # the jaws close along the face's normal
    np.testing.assert_allclose(R[:, 2], (0, 0, -1), atol=1e-12)  # coming down from +z
    np.testing.assert_allclose(R[:, 0], np.cross(R[:, 1], R[:, 2]), atol=1e-12)
    # across the narrow side, from -y
    g = grasp_at_face(box, "plane", (0.01, -0.01, 0.0), (0, -1, 0), 0.0, APPROACHES["from +x"], "g")
    assert g.width == pytest.approx(0.02, abs=1e-7)  # the ray cast is in float32
    np.testing.assert_allclose(g.T_part_gripper[:3, 3], (0.01, 0.0, 0.0), atol=1e-7)
    with pytest.raises(AposeError, match="closing direction"):  # coming in along the jaws' own direction
        grasp_at_face(box, "plane", (0.02, 0, 0), (1, 0, 0), 0.0, APPROACHES["from -x"], "g")


def test_a_round_face_grasps_across_its_axis():
    cyl = trimesh.creation.cylinder(radius=0.004, height=0.02)
    g = grasp_at_face(cyl, "cylinder", (0.0, 0.0, 0.005), (0, 0, 1), 0.004, APPROACHES["from +x"], "pin")
    assert g.width == pytest.approx(0.008)
    np.testing.assert_allclose(g.T_part_gripper[:3, 3], (0.0, 0.0, 0.005))
    R = g.T_part_gripper[:3, :3]
    assert abs(R[:, 1] @ (0, 0, 1)) < 1e-12 and abs(R[:, 1] @ R[:, 2]) < 1e-12  # across the axis, square to z
    np.testing.assert_allclose(R[:, 2], (-1, 0, 0), atol=1e-12)
    # down the axis: the jaws still close across it
    g = grasp_at_face(cyl, "cylinder", (0.0, 0.0, 0.0), (0, 0, 1), 0.004, APPROACHES["from +z"], "pin")
    assert abs(g.T_part_gripper[:3, 1] @ (0, 0, 1)) < 1e-12


def test_a_face_with_nothing_opposite_and_other_faces_are_refused():
    plate = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])  # one triangle: no face across
    with pytest.raises(AposeError, match="no face opposite"):
        grasp_at_face(plate, "plane", (0.2, 0.2, 0.0), (0, 0, 1), 0.0, APPROACHES["from +x"], "g")
    with pytest.raises(AposeError, match="flat face"):
        grasp_at_face(plate, "other", (0, 0, 0), (0, 0, 1), 0.0, APPROACHES["from +x"], "g")


def test_the_drawn_gripper_opens_to_the_grasp_width():
    m = gripper_mesh(0.03)
    fingers = m.vertices[m.vertices[:, 2] > -0.045 + 1e-9]  # the fingers end at the TCP plane z = 0
    assert m.vertices[:, 2].max() == pytest.approx(0.0, abs=1e-12)
    inner = np.abs(fingers[:, 1]).min()
    assert inner == pytest.approx(0.015, abs=1e-9)  # each finger's inner face half the opening from the TCP
