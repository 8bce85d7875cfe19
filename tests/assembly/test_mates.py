"""Mates (ASSEMBLY_FORMAT.md, "Optional step keys"): hand-solved poses, free degrees of freedom,
contradictions with their key paths, and the file round trip. Expected poses are worked out by hand
in the comments, not by the solver."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from apose_studio.assembly.model import assembly_from_dict, load_assembly, save_assembly
from apose_studio.errors import AssemblyError


@pytest.fixture()
def folder(tmp_path):
    for name in ("base", "part", "third"):
        trimesh.creation.box((10, 10, 10)).export(tmp_path / f"{name}.stl")
    return tmp_path


def _asm(folder, mates, pose=None, units="mm", symmetry=None, extra_steps=(), approach=None):
    step = {"part": "part", "base": ["base"], "mates": mates}
    if pose is not None:
        step["pose_in_base"] = pose
    if approach is not None:
        step["approach"] = approach
    part = {"mesh": "part.stl"} | ({"symmetry": symmetry} if symmetry else {})
    data = {"format": "apose-assembly/1", "name": "t", "units": units,
            "parts": {"base": {"mesh": "base.stl"}, "part": part, "third": {"mesh": "third.stl"}},
            "steps": [step, *extra_steps]}
    return assembly_from_dict(data, folder / "a.yaml")


def _problem(folder, *args, **kw):
    with pytest.raises(AssemblyError) as e:
        _asm(folder, *args, **kw)
    return e.value.problems


def coax(bp, bd, pp, pd, **kw):
    return {"type": "coaxial", "base": {"point": bp, "direction": bd}, "part": {"point": pp, "direction": pd}, **kw}


def contact(bp, bn, pp, pn, kind="contact", **kw):
    return {"type": kind, "base": {"point": bp, "normal": bn}, "part": {"point": pp, "normal": pn}, **kw}


def angle(bd, pd, deg):
    return {"type": "angle", "base": {"direction": bd}, "part": {"direction": pd}, "degrees": deg}


def Rz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_coaxial_contact_angle_hand_solved(folder):
    # The part's axis (through (1, 0, 0), +z) on the base's axis through (10, 5, 0), +z; its face at
    # z = -7 (normal -z) on the base's face z = 58.5 (normal +z); turned +30 deg about z.
    # By hand: R = Rz(30); R (1, 0, 0) + t on the line x = 10, y = 5; -7 + t_z = 58.5.
    asm = _asm(folder, [coax([10, 5, 0], [0, 0, 1], [1, 0, 0], [0, 0, 1]),
                        contact([0, 0, 58.5], [0, 0, 1], [0, 0, -7], [0, 0, -1]),
                        angle([1, 0, 0], [1, 0, 0], 30)])
    T = asm.steps[0].T_base_part
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    np.testing.assert_allclose(T[:3, :3], Rz(30), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], np.array([10 - c, 5 - s, 65.5]) / 1000, atol=1e-12)
    assert asm.steps[0].free == ()


def test_three_faces_of_a_corner(folder):
    # The part's faces with normals -y, -z, -x meet at its origin; they go on the base's faces +x, +y, +z
    # through (2, 3, 4), the first 1 mm apart. By hand R takes y -> x, z -> y, x -> z; t = (3, 3, 4).
    asm = _asm(folder, [contact([2, 3, 4], [1, 0, 0], [0, 0, 0], [0, -1, 0], offset=1),
                        contact([2, 3, 4], [0, 1, 0], [0, 0, 0], [0, 0, -1]),
                        contact([2, 3, 4], [0, 0, 1], [0, 0, 0], [-1, 0, 0])])
    T = asm.steps[0].T_base_part
    np.testing.assert_allclose(T[:3, :3], [[0, 1, 0], [0, 0, 1], [1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.003, 0.003, 0.004], atol=1e-12)
    assert asm.steps[0].free == ()


def test_flipped_coaxial(folder):
    # Axes opposed; the part's top face (z = 5, +z) then faces down onto the base face z = 10; the angle
    # mate brings the part's x back onto the base's x. By hand: R = diag(1, -1, -1), t = (0, 0, 15).
    asm = _asm(folder, [coax([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1], flip=True),
                        contact([0, 0, 10], [0, 0, 1], [0, 0, 5], [0, 0, 1]),
                        angle([1, 0, 0], [1, 0, 0], 0)])
    T = asm.steps[0].T_base_part
    np.testing.assert_allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0, 0, 0.015], atol=1e-12)


def test_under_constrained_keeps_the_given_pose_and_says_what_is_free(folder):
    pose = {"translation": [7, 8, 9], "rotation": {"euler_deg": [0, 0, 40], "order": "xyz"}}
    asm = _asm(folder, [coax([1, 2, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1])], pose=pose)
    s = asm.steps[0]
    # on the axis: x, y from the axis, z (sliding) and the 40 deg turn (rotation about it) from the pose
    np.testing.assert_allclose(s.T_base_part[:3, 3], [0.001, 0.002, 0.009], atol=1e-12)
    np.testing.assert_allclose(s.T_base_part[:3, :3], Rz(40), atol=1e-12)
    assert len(s.free) == 2
    assert "rotation about the coaxial axis" in s.free[0] and "sliding along" in s.free[1]
    # a part that is round about that axis: the free turn is not worth a word
    sym = _asm(folder, [coax([1, 2, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1])], pose=pose,
               symmetry={"axis": [0, 0, 1], "order": 0})
    assert len(sym.steps[0].free) == 1 and "sliding" in sym.steps[0].free[0]
    # a contact alone: the plane is free to slide in, and the turn about its normal
    one = _asm(folder, [contact([0, 0, 3], [0, 0, 1], [0, 0, 0], [0, 0, -1])])
    assert any("plane across [0, 0, 1]" in w for w in one.steps[0].free)


def test_two_contacts_at_different_heights_contradict(folder):
    (p,) = _problem(folder, [contact([0, 0, 10], [0, 0, 1], [0, 0, 0], [0, 0, -1]),
                             contact([0, 0, 12], [0, 0, 1], [0, 0, 0], [0, 0, -1])])
    assert p.key == "steps[0].mates[1]" and "contradicts" in p.what and "2 mm" in p.what


def test_parallel_axes_apart_contradict(folder):
    (p,) = _problem(folder, [coax([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1]),
                             coax([5, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1])])
    assert p.key == "steps[0].mates[1]" and "5 mm" in p.what


def test_normals_at_the_wrong_angle_contradict(folder):
    # the part's two normals are 90 deg apart, the base's 45 deg: no rotation takes one pair onto the other
    (p,) = _problem(folder, [contact([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, -1]),
                             contact([0, 0, 0], [0, 1, 1], [0, 0, 0], [0, -1, 0])])
    assert p.key == "steps[0].mates[1]" and "deg" in p.what


def test_angle_without_an_axis_and_angle_against_fixed_rotation(folder):
    (p,) = _problem(folder, [angle([1, 0, 0], [1, 0, 0], 10)])
    assert p.key == "steps[0].mates[0]" and "coaxial" in p.what
    corner = [contact([0, 0, 0], [1, 0, 0], [0, 0, 0], [-1, 0, 0]), contact([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, -1])]
    (p,) = _problem(folder, [angle([0, 1, 0], [0, 1, 0], 10), *corner])  # about the first normal, x
    assert p.key == "steps[0].mates[0]" and "10 deg" in p.what  # the angle is checked after the others


def test_fixed_mate_and_its_contradiction(folder):
    fixed = {"type": "fixed", "base": {"translation": [1, 2, 3], "rotation": {"euler_deg": [0, 0, 90], "order": "xyz"}},
             "part": {"translation": [0, 0, 1]}}
    T = _asm(folder, [fixed]).steps[0].T_base_part
    # base frame at (1, 2, 3) turned 90 deg about z; the part's frame 1 mm up its own z sits on it:
    # T = T_ref_base * inv(T_ref_part) -> R = Rz(90), t = (1, 2, 3) - (0, 0, 1) = (1, 2, 2)
    np.testing.assert_allclose(T[:3, :3], Rz(90), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.001, 0.002, 0.002], atol=1e-12)
    (p,) = _problem(folder, [fixed, contact([0, 0, 5], [0, 0, 1], [0, 0, 0], [0, 0, -1])])
    assert p.key == "steps[0].mates[1]" and "3 mm" in p.what


def test_pose_in_base_against_fixing_mates(folder):
    corner = [contact([0, 0, 0], [1, 0, 0], [0, 0, 0], [-1, 0, 0]), contact([0, 0, 0], [0, 1, 0], [0, 0, 0], [0, -1, 0]),
              contact([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, -1])]
    assert _asm(folder, corner, pose={"translation": [0, 0, 0]}).steps[0].free == ()
    (p,) = _problem(folder, corner, pose={"translation": [0, 0, 0.01]})
    assert p.key == "steps[0].pose_in_base" and "0.01 mm" in p.what
    # beside mates that leave freedom, the pose only supplies what is free: no error
    _asm(folder, corner[:1], pose={"translation": [0, 4, 4]})


def test_bad_mates_name_their_keys(folder):
    keys = {p.key for p in _problem(folder, [{"type": "glue"}, coax([0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 0]),
                                             {"type": "coaxial", "base": {"part": "third", "point": [0, 0, 0],
                                                                          "direction": [0, 0, 1]},
                                              "part": {"point": [0, 0, 0], "direction": [0, 0, 1]}}])}
    assert keys == {"steps[0].mates[0].type", "steps[0].mates[1].base.point", "steps[0].mates[1].part.direction",
                    "steps[0].mates[2].base.part"}
    (p,) = _problem(folder, [coax([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1])], approach={"direction": [0, 0, 1],
                                                                                         "distance": -3})
    assert p.key == "steps[0].approach.distance"


def test_base_references_in_another_base_part(folder):
    # step 2 places `third` with a mate on `part` (placed by step 1 at z = 10 mm, turned 90 deg about z);
    # the reference (x = 1 on part) is then at (0, 1, 10) in base's frame.
    step2 = {"part": "third", "base": ["base", "part"],
             "mates": [{"type": "fixed", "base": {"part": "part", "translation": [1, 0, 0]}, "part": {"translation": [0, 0, 0]}}]}
    asm = _asm(folder, [{"type": "fixed", "base": {"translation": [0, 0, 10], "rotation": {"euler_deg": [0, 0, 90],
                                                                                             "order": "xyz"}},
                         "part": {"translation": [0, 0, 0]}}], extra_steps=[step2])
    np.testing.assert_allclose(asm.steps[1].T_base_part[:3, 3], [0, 0.001, 0.01], atol=1e-12)
    np.testing.assert_allclose(asm.steps[1].T_base_part[:3, :3], Rz(90), atol=1e-12)


def test_save_writes_mates_and_solved_pose_and_round_trips(folder):
    asm = _asm(folder, [coax([10, 5, 0], [0, 0, 2], [1, 0, 0], [0, 0, 1]),
                        contact([0, 0, 58.5], [0, 0, 1], [0, 0, -7], [0, 0, -1], offset=0.5),
                        angle([1, 0, 0], [1, 0, 0], 30)], approach={"direction": [0, 0, -2], "distance": 30})
    path = save_assembly(asm, folder / "saved.yaml")
    text = path.read_text()
    assert "mates:" in text and "pose_in_base:" in text and "approach:" in text and "offset: 0.5" in text
    again = load_assembly(path)
    assert again == asm
    a = again.steps[0].approach
    np.testing.assert_allclose(a.direction, [0, 0, -1])  # normalised at load
    assert a.distance == pytest.approx(0.030)
    # the approach pose: the assembly pose moved back by 30 mm along the motion (in base[0]'s frame)
    T_world_base = np.eye(4)
    T_world_base[:3, :3] = Rz(90)
    start = a.start(T_world_base @ again.steps[0].T_base_part, T_world_base)
    np.testing.assert_allclose(start[:3, 3] - (T_world_base @ again.steps[0].T_base_part)[:3, 3], [0, 0, 0.03], atol=1e-12)


def test_apose_show_lists_mates_and_free_degrees(folder):
    import json

    from ..cli.test_cli import run
    from ..conftest import SAMPLES

    doc = json.loads(run("show", SAMPLES / "planetary_reducer" / "assembly.yaml", "--json").stdout)
    s = doc["steps"][0]
    assert s["mates"] == ["coaxial", "contact", "contact"] and s["free"] == []
    assert s["T_base_part"][2][3] == pytest.approx(0.052, abs=1e-12)  # 42 (boss) + 3 (gap) + 7 (hub below the centre)
    assert s["approach"] == {"direction": [0, 0, -1], "distance": pytest.approx(0.03)}
    path = folder / "free.yaml"
    path.write_text("format: apose-assembly/1\nname: t\nunits: mm\nparts:\n  base: {mesh: base.stl}\n  part: {mesh: part.stl}\n"
                    "steps:\n  - part: part\n    base: [base]\n    mates:\n      - type: coaxial\n"
                    "        base: {point: [0, 0, 0], direction: [0, 0, 1]}\n        part: {point: [0, 0, 0], direction: [0, 0, 1]}\n")
    text = run("show", path).stdout
    assert "from mates: coaxial; free: rotation about the coaxial axis [0, 0, 1] is free (add an angle mate); " \
           "sliding along [0, 0, 1] is free" in text


@pytest.mark.parametrize("start_deg", [0, 40, -100, 170])
def test_angle_mate_from_a_start_already_turned(folder, start_deg):
    # The guess (pose_in_base) is already turned about the coaxial axis; the angle mate alone sets the
    # turn: the part's x at +30 deg from the base's x, right-handed about +z, whatever the start. By
    # hand R = Rz(30) (a turn of 30 - start applied to the start), t from the axis through (1, 2, 0):
    # the part's origin on it, its height kept from the pose (9 mm).
    pose = {"translation": [7, 8, 9], "rotation": {"euler_deg": [0, 0, start_deg], "order": "xyz"}}
    asm = _asm(folder, [coax([1, 2, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1]), angle([1, 0, 0], [1, 0, 0], 30)], pose=pose)
    T = asm.steps[0].T_base_part
    np.testing.assert_allclose(T[:3, :3], Rz(30), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.001, 0.002, 0.009], atol=1e-12)
    # the base's reference along +y and the part's along +x: the part's x at 90 + 30 = 120 deg from the
    # base's x, so R = Rz(120); and a -45 deg mate from the same start: Rz(-45)
    asm = _asm(folder, [coax([1, 2, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1]), angle([0, 1, 0], [1, 0, 0], 30)], pose=pose)
    np.testing.assert_allclose(asm.steps[0].T_base_part[:3, :3], Rz(120), atol=1e-12)
    asm = _asm(folder, [coax([1, 2, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1]), angle([1, 0, 0], [1, 0, 0], -45)], pose=pose)
    np.testing.assert_allclose(asm.steps[0].T_base_part[:3, :3], Rz(-45), atol=1e-12)


def test_angle_mate_about_a_contact_normal_along_x(folder):
    # The part's face (normal -x) on the base's face x = 4 (normal +x): contact takes the part's -x onto
    # -(+x), so x is kept and the turn about +x is free; the angle mate sets it from the base's y to the
    # part's y: +90 deg from a start at 25. By hand R = Rx(90) (y -> z), t_x = 4 mm (the face), t_y, t_z
    # slide in the face and stay as given.
    asm = _asm(folder, [contact([4, 0, 0], [1, 0, 0], [0, 0, 0], [-1, 0, 0]), angle([0, 1, 0], [0, 1, 0], 90)],
               pose={"translation": [0, 5, 6], "rotation": {"euler_deg": [25, 0, 0], "order": "xyz"}})
    T = asm.steps[0].T_base_part
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.004, 0.005, 0.006], atol=1e-12)


def test_refs_and_approaches_compare_every_field():
    from apose_studio.assembly.mates import Approach, Ref

    z = np.array([0.0, 0, 1])
    assert Ref(direction=z) == Ref(direction=z.copy())
    assert Ref(direction=z) != Ref(point=np.zeros(3), direction=z)  # a point on one side only
    assert Ref(point=np.zeros(3), direction=z) != Ref(point=np.array([0, 0, 1e-9]), direction=z)
    assert Approach(z, 0.03) == Approach(z.copy(), 0.03)
    assert Approach(z, 0.03) != Approach(z, 0.04) and Approach(z, 0.04) != Approach(z, 0.03)  # either way round
    assert Approach(z, 0.03) != Approach(np.array([1.0, 0, 0]), 0.03) and Approach(z, 0.03) != "approach"


def test_solve_directly_and_a_reference_along_the_axis(folder):
    from apose_studio.assembly.mates import Mate, MateError, Ref, solve
    from apose_studio.errors import AposeError

    # no guess: identity supplies what is free; the part's origin onto the axis through (1, 2, 0)
    coax_m = Mate("coaxial", Ref(np.array([0.001, 0.002, 0]), np.array([0.0, 0, 1])), Ref(np.zeros(3), np.array([0.0, 0, 1])))
    s = solve([coax_m])
    np.testing.assert_allclose(s.T_base_part, [[1, 0, 0, 0.001], [0, 1, 0, 0.002], [0, 0, 1, 0], [0, 0, 0, 1]], atol=1e-12)
    assert s.n_free == 2
    # an angle mate whose part direction lies along the axis it turns about cannot say a turn
    along = Mate("angle", Ref(direction=np.array([1.0, 0, 0])), Ref(direction=np.array([0.0, 0, 1])), degrees=30)
    with pytest.raises(MateError, match="parallel to the axis"):
        solve([coax_m, along])
    with pytest.raises(AposeError, match="parallel to the axis"):
        _asm(folder, [coax([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, 1]), angle([1, 0, 0], [0, 0, 1], 30)])


def test_a_part_round_about_its_own_x_put_on_the_axis_is_not_free_to_turn(folder):
    # the part's x axis (its symmetry axis) onto the base's z axis: R takes x to z, so the free turn about z
    # is a turn about the part's own axis of symmetry: not worth a word; the sliding along z is
    one = _asm(folder, [coax([0, 0, 0], [0, 0, 1], [0, 0, 0], [1, 0, 0])], symmetry={"axis": [1, 0, 0], "order": 0})
    np.testing.assert_allclose(one.steps[0].T_base_part[:3, :3] @ [1, 0, 0], [0, 0, 1], atol=1e-12)
    assert len(one.steps[0].free) == 1 and "sliding along [0, 0, 1]" in one.steps[0].free[0]
    # round about its z instead: the turn about the base's z is a real freedom
    other = _asm(folder, [coax([0, 0, 0], [0, 0, 1], [0, 0, 0], [1, 0, 0])], symmetry={"axis": [0, 0, 1], "order": 0})
    assert any("rotation about the coaxial axis" in w for w in other.steps[0].free)


def test_mates_must_be_a_non_empty_list(folder):
    for bad in ([], {"type": "coaxial"}):
        (p,) = _problem(folder, bad)
        assert p.key == "steps[0].mates" and "expected a non-empty list of mates" in p.what, (bad, p.what)


def test_contradiction_names_what_it_contradicts(folder):
    (p,) = _problem(folder, [contact([0, 0, 10], [0, 0, 1], [0, 0, 0], [0, 0, -1]),
                             contact([0, 0, 12], [0, 0, 1], [0, 0, 0], [0, 0, -1])])
    assert "contradicts the mates before it" in p.what


def test_save_writes_a_fixed_mate_and_unit_directions(folder):
    fixed = {"type": "fixed", "base": {"translation": [1, 2, 3], "rotation": {"euler_deg": [0, 0, 90], "order": "xyz"}},
             "part": {"translation": [0, 0, 1]}}
    asm = _asm(folder, [coax([10, 5, 0], [0, 0, 2], [1, 0, 0], [0, 0, 1]), contact([0, 0, 5], [0, 0, 1], [0, 0, 0], [0, 0, -1])],
               approach={"direction": [0, 0, -2], "distance": 30},
               extra_steps=[{"part": "third", "base": ["base", "part"], "mates": [fixed]}])
    text = save_assembly(asm, folder / "saved.yaml").read_text()
    # directions and the approach as unit vectors, no offset on a coaxial mate nor a zero one on a contact, the
    # fixed frame's turn as a quaternion (a quarter about z: w = z = sqrt(1/2))
    assert "direction: [0, 0, 1]" in text and "direction: [0, 0, -1]" in text and "offset" not in text
    assert "translation: [1, 2, 3]" in text and "quat_wxyz: [0.70710678" in text
    again = load_assembly(folder / "saved.yaml")
    assert again == asm
    np.testing.assert_allclose(again.steps[1].T_base_part[:3, :3], Rz(90), atol=1e-12)


def test_bad_offsets_degrees_and_fixed_references_name_their_keys(folder):
    """Numbers of a mate are checked where they are: a gap that is text or NaN, a turn that is missing or
    text (booleans are not numbers either), a fixed reference whose rotation is bad; each problem names its
    key, nothing raises on the way."""
    good = contact([0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 0, -1])
    problems = _problem(folder, [{**good, "offset": "2mm"}, {**good, "type": "aligned", "offset": float("nan")},
                                 {**angle([0, 0, 1], [0, 0, 1], 30), "degrees": True},
                                 {"type": "angle", "base": {"direction": [1, 0, 0]}, "part": {"direction": [1, 0, 0]}},
                                 {"type": "fixed", "base": {"translation": [0, 0, 0], "rotation": {"euler_deg": "x"}},
                                  "part": {"translation": [0, 0, 0]}}])
    by_key = {p.key: p.what for p in problems}
    assert by_key["steps[0].mates[0].offset"].startswith("expected a gap in the file's units within 10 km, got")
    assert by_key["steps[0].mates[1].offset"].startswith("expected a gap in the file's units within 10 km, got")
    assert by_key["steps[0].mates[2].degrees"].startswith("expected the turn in degrees (at most 3600 either way), got")
    assert by_key["steps[0].mates[3].degrees"].startswith("expected the turn in degrees (at most 3600 either way), got")
    assert any(k.startswith("steps[0].mates[4].base.rotation") for k in by_key), by_key
    assert len(_asm(folder, [good]).steps[0].mates) == 1  # and a good one alone is accepted


def test_solve_without_mates_or_a_guess():
    from apose_studio.assembly.mates import Mate, Ref, solve

    s = solve([])
    assert np.array_equal(s.T_base_part, np.eye(4)) and s.n_free == 6
    assert s.free == ("every degree of freedom is free (no mates)",)
    up, down = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
    m = Mate("contact", Ref(point=np.zeros(3), direction=up), Ref(point=np.zeros(3), direction=down))
    s = solve([m])  # no guess: identity for what the mate leaves free
    assert s.T_base_part.shape == (4, 4) and np.allclose(s.T_base_part, np.eye(4)) and s.n_free == 3
