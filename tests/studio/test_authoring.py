"""Authoring edits (pure): every edit is a new Assembly, validated with the loader's own rules."""

import numpy as np
import pytest
import trimesh

from apose_studio.assembly.model import load_assembly, save_assembly
from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.studio import authoring


def test_build_an_assembly_from_nothing_and_save_it(tmp_path):
    trimesh.creation.box((60, 40, 4)).export(tmp_path / "Base Plate.stl")
    trimesh.creation.cylinder(radius=4, height=20).export(tmp_path / "peg.stl")
    asm = authoring.new_assembly("rig", "mm", tmp_path)
    asm, plate = authoring.add_part(asm, tmp_path / "Base Plate.stl")
    asm, peg = authoring.add_part(asm, tmp_path / "peg.stl")
    assert (plate, peg) == ("Base_Plate", "peg")
    assert [p.key for p in authoring.problems(asm)] == ["steps"]  # valid so far, but nothing to save
    asm = authoring.add_step(asm)
    assert asm.steps[0].part == "peg" and asm.steps[0].base == ("Base_Plate",)
    T = authoring.pose_from_typed([10, -5, 12], [0, 0, 90])
    asm = authoring.edit_step(asm, 0, T_base_part=T)
    assert authoring.problems(asm) == []
    path = save_assembly(asm, tmp_path / "rig.yaml")
    back = load_assembly(path)
    np.testing.assert_allclose(back.steps[0].T_base_part[:3, 3], [0.010, -0.005, 0.012], atol=1e-12)
    np.testing.assert_allclose(back.steps[0].T_base_part[:3, :3], se3.euler_deg_to_matrix([0, 0, 90], "xyz"), atol=1e-9)
    assert (tmp_path / "rig.yaml").read_text().count("mesh: ") == 2 and "Base Plate.stl" in (tmp_path / "rig.yaml").read_text()


def test_unique_ids():
    asm = authoring.new_assembly()
    asm, a = authoring.add_part(asm, "/x/Left Gear.stl")
    asm, b = authoring.add_part(asm, "/y/left-gear.ply")
    asm, c = authoring.add_part(asm, "/z/###.stl")
    asm, d = authoring.add_part(asm, "/z/Nema17.step")
    asm, e = authoring.add_part(asm, "/z/m3-bolt.v2.stl")
    asm, f = authoring.add_part(asm, "/z/left_gear.stl")
    # the file's spelling is kept (case, '-' and '.'); what an id may not hold becomes '_'; unused whatever the case
    assert (a, b, c, d, e, f) == ("Left_Gear", "left-gear", "part", "Nema17", "m3-bolt.v2", "left_gear_2")


def test_reorder_reports_the_offending_step(tiny_dir):
    asm = load_assembly(tiny_dir / "assembly.yaml")
    moved = authoring.move_step(asm, 1, -1)  # the cap now comes before the peg it sits on
    assert [s.part for s in moved.steps] == ["cap", "peg"]
    found = authoring.problems(moved)
    assert authoring.problem_steps(found) == {0}
    assert "placed only by a later step" in found[0].what
    assert authoring.problems(authoring.move_step(moved, 0, +1)) == []
    assert authoring.move_step(asm, 0, -5).steps == asm.steps  # clamped


def test_edit_errors_are_reported_not_raised(tiny_dir):
    asm = load_assembly(tiny_dir / "assembly.yaml")
    bad = authoring.edit_step(asm, 0, base=["nope"])
    assert [p.key for p in authoring.problems(bad)] == ["steps[0].base[0]"]
    assert "unknown part 'nope'" in authoring.problems(bad)[0].what
    with pytest.raises(AposeError, match="used by step"):
        authoring.remove_part(asm, "peg")
    assert "cap" not in authoring.remove_part(authoring.delete_step(asm, 1), "cap").parts
    with pytest.raises(AposeError, match="every part is already placed"):
        authoring.add_step(asm)


def test_typed_pose_round_trip_and_snapping():
    T = authoring.pose_from_typed([1.234, -20.06, 3.0], [10.0, -33.0, 170.0])
    t, e = authoring.typed_pose(T)
    np.testing.assert_allclose(t, [1.234, -20.06, 3.0], atol=1e-9)
    np.testing.assert_allclose(e, [10.0, -33.0, 170.0], atol=1e-9)
    t, e = authoring.typed_pose(authoring.snap_pose(T, 0.5, 5.0))
    np.testing.assert_allclose(t, [1.0, -20.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(e, [10.0, -35.0, 170.0], atol=1e-9)
    with pytest.raises(AposeError, match="finite"):
        authoring.pose_from_typed([0, np.nan, 0], [0, 0, 0])


def test_preview_places_parts_up_to_a_step(tiny_dir):
    asm = load_assembly(tiny_dir / "assembly.yaml")
    d = {"plate": 0.07, "peg": 0.02, "cap": 0.017}
    assert set(authoring.preview_poses(asm, 0, d)) == {"plate"}
    assert set(authoring.preview_poses(asm, 1, d)) == {"plate", "peg"}
    full = authoring.preview_poses(asm, 2, d)
    np.testing.assert_allclose(full["cap"], asm.T_root_part("cap"))
    exploded = authoring.preview_poses(asm, 2, d, explode=1.0)
    # each placed part moves out along its step's insertion direction (the axis of base[0]'s frame nearest
    # to base centre -> part centre), a part placed on a moved part moves with it; the root stays
    np.testing.assert_allclose(exploded["plate"], full["plate"])
    peg_up = exploded["peg"][:3, 3] - full["peg"][:3, 3]  # peg at (10, 0, 5) mm on the plate: along +x
    np.testing.assert_allclose(peg_up / np.linalg.norm(peg_up), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(peg_up), 0.07 * 1 / 2)
    cap_move = exploded["cap"][:3, 3] - full["cap"][:3, 3]  # cap at (0, 10, 0) in the peg's frame, turned 90° about z
    np.testing.assert_allclose(cap_move - peg_up, asm.T_root_part("peg")[:3, :3] @ [0, 0.07 * 2 / 2, 0], atol=1e-12)
    np.testing.assert_allclose(authoring.insertion_direction(asm, 0), [1, 0, 0])


def test_region_handles_stand_at_the_centre_and_a_corner_and_give_the_size_back():
    """Drag region's handles: a box's +x+y+z corner, a sphere's point along x; the size read back from where they
    are dragged (a box's sides about its centre, a sphere's diameter), never under the least size."""
    c, corner = authoring.roi_handles("box", (0.01, 0.0, 0.02), (0.04, 0.02, 0.006))
    assert np.allclose(corner, (0.03, 0.01, 0.023))
    assert np.allclose(authoring.roi_from_handles("box", c, corner + (0.005, 0, -0.002), 0.001), (0.05, 0.02, 0.002))
    assert np.allclose(authoring.roi_from_handles("box", c, c, 0.001), (0.001,) * 3)  # dragged onto the centre
    c, corner = authoring.roi_handles("sphere", (0.0, 0.0, 0.0), (0.02, 0.02, 0.02))
    assert np.allclose(corner, (0.01, 0.0, 0.0))
    assert np.allclose(authoring.roi_from_handles("sphere", c, corner + (0, 0.01, 0), 0.001), (2 * np.sqrt(2e-4),) * 3)


def test_the_corner_handle_stays_on_the_side_it_was_dragged_to():
    """A corner dragged past the centre (the box mirrored): the handle is placed back on that side, not on +x+y+z."""
    c, corner = authoring.roi_handles("box", (0.0, 0.0, 0.0), (0.04, 0.02, 0.006), side=(-0.01, 0.003, -0.001))
    assert np.allclose(corner, (-0.02, 0.01, -0.003))
    _, point = authoring.roi_handles("sphere", (0.0, 0.0, 0.0), (0.02, 0.02, 0.02), side=(-1.0, 0.0, 0.0))
    assert np.allclose(point, (-0.01, 0.0, 0.0))
