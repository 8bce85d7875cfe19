"""Picking faces (#15): the ray's triangle grows into its CAD face, fitted as a plane, a cylinder or a
cone; and the authoring edits the Mates folder makes from picks. Expected values are the shapes'
own dimensions, not the fitter's."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from apose_studio.assembly.mesh import load_mesh
from apose_studio.assembly.model import Step, load_assembly
from apose_studio.studio import authoring
from apose_studio.studio.picking import FacePicker

from ..conftest import SAMPLES


def test_box_faces_are_planes_with_outward_normals():
    box = trimesh.creation.box((0.04, 0.02, 0.01))
    fp = FacePicker(box)
    f = fp.pick([0.005, 0.003, 0.1], [0, 0, -1])
    assert f.kind == "plane" and len(f.faces) == 2
    np.testing.assert_allclose(f.direction, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(f.point, [0.005, 0.003, 0.005], atol=1e-12)  # on the face, not where the ray hit in float32
    f = fp.pick([0.1, 0.0, 0.0], [-1, 0, 0])
    np.testing.assert_allclose(f.direction, [1, 0, 0], atol=1e-12)
    assert fp.pick([0.1, 0.1, 0.1], [1, 0, 0]) is None  # a miss


def test_cylinder_side_and_cap_are_different_faces():
    cyl = trimesh.creation.cylinder(radius=0.005, height=0.02, sections=48)
    cyl.apply_translation((0.01, -0.02, 0.0))
    fp = FacePicker(cyl)
    side = fp.pick([0.01, -0.1, 0.004], [0, 1, 0])
    assert side.kind == "cylinder" and len(side.faces) == 96
    assert abs(abs(side.direction[2]) - 1) < 1e-9
    assert side.radius == pytest.approx(0.005, abs=1e-9)  # through the vertices, which lie on the circle
    np.testing.assert_allclose(side.point, [0.01, -0.02, 0.004], atol=1e-9)
    cap = fp.pick([0.011, -0.02, 0.1], [0, 0, -1])
    assert cap.kind == "plane" and not set(cap.faces) & set(side.faces)


def test_cone_and_freeform():
    cone = trimesh.creation.cone(radius=0.01, height=0.02, sections=64)
    f = FacePicker(cone).pick([0.0, -0.1, 0.005], [0, 1, 0])
    assert f.kind == "cone" and abs(abs(f.direction[2]) - 1) < 1e-6
    torus = trimesh.creation.torus(major_radius=0.03, minor_radius=0.01, major_sections=64, minor_sections=32)
    assert FacePicker(torus).pick([0.03, 0.0, 0.1], [0, 0, -1]).kind == "other"


def test_d_shaft_axis_from_the_round_part_only():
    # the sample motor's 5 mm shaft has a flat at y = 2 mm; its round face's axis is x = y = 0
    fp = FacePicker(load_mesh(SAMPLES / "planetary_reducer" / "motor.ply", "mm"))
    f = fp.pick([0.0, -0.05, 0.055], [0, 1, 0])
    assert f.kind == "cylinder" and f.radius == pytest.approx(0.0025, abs=1e-8)
    np.testing.assert_allclose(f.point[:2], [0, 0], atol=1e-8)
    flat = fp.pick([0.0, 0.05, 0.055], [0, -1, 0])
    assert flat.kind == "plane" and flat.point[1] == pytest.approx(0.002, abs=1e-12)


@pytest.fixture()
def reducer(tmp_path):
    """The planetary sample's motor and sun gear, the gear's step without mates, set down beside the motor."""
    asm = load_assembly(SAMPLES / "planetary_reducer" / "assembly.yaml")
    asm = authoring.delete_step(authoring.delete_step(authoring.delete_step(asm, 3), 2), 1)
    s = asm.steps[0]
    return asm.with_steps([Step(s.part, s.base, np.array([[1, 0, 0, 0.06], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))])


def _features():
    motor = FacePicker(load_mesh(SAMPLES / "planetary_reducer" / "motor.ply", "mm"))
    gear = FacePicker(load_mesh(SAMPLES / "planetary_reducer" / "sun_gear.ply", "mm"))
    return {"shaft": motor.pick([0, -0.05, 0.05], [0, 1, 0]), "boss": motor.pick([-0.005, -0.005, 0.1], [0, 0, -1]),
            "hub": gear.pick([0, -0.05, -0.006], [0, 1, 0]), "hub_bottom": gear.pick([-0.002, -0.002, -0.05], [0, 0, 1])}


def test_mates_from_picks_place_the_sun_gear_and_undo(reducer):
    f = _features()
    asm, hist = reducer, authoring.History()
    contact = authoring.mate_from_picks(asm, 0, "contact", "motor", f["boss"], f["hub_bottom"], 0.003)
    hist.record(asm)
    asm = authoring.set_mates(asm, 0, [contact])
    assert asm.steps[0].T_base_part[2, 3] == pytest.approx(0.052, abs=1e-12) and asm.steps[0].T_base_part[0, 3] == 0.06
    coax = authoring.mate_from_picks(asm, 0, "coaxial", "motor", f["shaft"], f["hub"])
    # a fitted axis has no sign: the mate is flipped exactly when the two fitted directions disagree
    assert coax.flip == bool(f["shaft"].direction @ f["hub"].direction < 0)
    hist.record(asm)
    asm = authoring.set_mates(asm, 0, [contact, coax])
    want = np.eye(4)
    want[2, 3] = 0.052  # on the shaft's axis, 3 mm above the boss, unturned: where the sample file puts it
    np.testing.assert_allclose(asm.steps[0].T_base_part, want, atol=1e-9)
    assert "rotation about the coaxial axis" in asm.steps[0].free[0]
    locked = authoring.lock_turn(asm, 0)
    assert locked.steps[0].free == () and np.allclose(locked.steps[0].T_base_part, asm.steps[0].T_base_part, atol=1e-12)
    turned = authoring.edit_mate(locked, 0, 2, degrees=30.0)
    assert np.degrees(np.arctan2(turned.steps[0].T_base_part[1, 0], turned.steps[0].T_base_part[0, 0])) == pytest.approx(30)
    # a pose off the mates breaks them; one along what they leave free does not
    moved = asm.steps[0].T_base_part.copy()
    moved[2, 3] += 0.001
    assert authoring.broken_mates(asm, 0, moved)
    spun = asm.steps[0].T_base_part.copy()
    spun[:3, :3] = trimesh.transformations.rotation_matrix(0.3, [0, 0, 1])[:3, :3]
    assert not authoring.broken_mates(asm, 0, spun)
    with pytest.raises(authoring.AposeError, match="mate 3: contradicts"):
        authoring.set_mates(asm, 0, [contact, coax, authoring.mate_from_picks(asm, 0, "contact", "motor", f["boss"],
                                                                               f["hub_bottom"], 0.004)])
    back = hist.undo(asm)
    assert back.steps[0].mates == (contact,)
    assert hist.undo(back) is reducer and hist.redo(reducer) is back
    with pytest.raises(authoring.AposeError, match="nothing to redo"):
        hist.redo(hist.redo(back))


def test_approach_set_and_cleared(reducer):
    asm = authoring.set_approach(reducer, 0, [0, 0, -2], 0.03)
    np.testing.assert_allclose(asm.steps[0].approach.direction, [0, 0, -1])
    assert authoring.set_approach(asm, 0, None, 0).steps[0].approach is None
    with pytest.raises(authoring.AposeError, match="above 0 mm"):
        authoring.set_approach(asm, 0, [0, 0, 1], 0.0)
