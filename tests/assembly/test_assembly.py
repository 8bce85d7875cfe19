import numpy as np
import pytest
import yaml

from apose_studio.assembly.model import Assembly, assembly_from_dict, load_assembly, save_assembly
from apose_studio.errors import AssemblyError
from apose_studio.geometry import se3

from ..conftest import TINY_YAML


def Rz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_tiny_loads_in_metres(tiny_dir):
    asm = load_assembly(tiny_dir / "assembly.yaml")
    assert asm.units == "mm" and asm.roots == ("plate",)
    peg = asm.steps[0].T_base_part
    np.testing.assert_allclose(peg[:3, 3], [0.010, 0.0, 0.005])
    np.testing.assert_allclose(peg[:3, :3], Rz(90), atol=1e-12)
    assert asm.parts["peg"].symmetry.order == 0 and asm.parts["peg"].color == (1.0, 0.0, 0.0)


def test_pose_chaining_matches_hand_computation(tiny_dir):
    asm = load_assembly(tiny_dir / "assembly.yaml")
    # cap sits on the peg at (0, 10, 0) mm; the peg is at (10, 0, 5) mm turned 90 deg about z, so in
    # the plate frame the cap is at (10, 0, 5) + Rz(90) (0, 10, 0) = (10 - 10, 0, 5) = (0, 0, 5) mm.
    T = asm.T_root_part("cap")
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, 0.005], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], Rz(90), atol=1e-12)
    assert asm.root_of("cap") == "plate"
    view = asm.step_view(2)
    assert view.base == ("peg", "plate") and view.root == "plate" and view.part == "cap"
    # the plate seen from the peg: inverse of the peg's pose -> t = -Rz(-90) (10, 0, 5) = (0, 10, -5) mm
    np.testing.assert_allclose(view.T_base_members["plate"][:3, 3], [0.0, 0.010, -0.005], atol=1e-12)
    np.testing.assert_allclose(view.T_base_members["peg"], np.eye(4), atol=1e-12)
    done = asm.completed()
    assert list(done) == ["plate"] and set(done["plate"]) == {"plate", "peg", "cap"}
    with pytest.raises(IndexError, match="steps 1..2"):
        asm.step_view(3)


def test_round_trip(tiny_dir, tmp_path):
    asm = load_assembly(tiny_dir / "assembly.yaml")
    out = save_assembly(asm, tiny_dir / "saved.yaml")
    again = load_assembly(out)
    assert again == asm
    saved = yaml.safe_load(out.read_text())
    assert saved["units"] == "mm" and saved["parts"]["plate"]["mesh"] == "plate.stl"
    assert saved["steps"][0]["pose_in_base"]["translation"] == [10, 0, 5]  # written back in mm
    assert "quat_wxyz" in saved["steps"][0]["pose_in_base"]["rotation"]
    # saved elsewhere, mesh paths stay valid (absolute when outside the file's folder)
    other = tmp_path / "elsewhere"
    other.mkdir()
    assert load_assembly(save_assembly(asm, other / "a.yaml")) == asm
    changed = asm.with_steps([asm.steps[0]])
    assert changed != asm


def test_rotation_forms_agree(tiny_dir):
    base = yaml.safe_load(TINY_YAML)
    forms = [{"quat_wxyz": [float(np.cos(np.pi / 4)), 0, 0, float(np.sin(np.pi / 4))]},
             {"euler_deg": [90, 0, 0], "order": "ZYX"},
             {"matrix": Rz(90).tolist()}]
    for form in forms:
        base["steps"][0]["pose_in_base"]["rotation"] = form
        (tiny_dir / "r.yaml").write_text(yaml.safe_dump(base))
        R = load_assembly(tiny_dir / "r.yaml").steps[0].T_base_part[:3, :3]
        np.testing.assert_allclose(R, Rz(90), atol=1e-9)


def _mutate(tiny_dir, fn):
    data = yaml.safe_load(TINY_YAML)
    fn(data)
    path = tiny_dir / "bad.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(AssemblyError) as e:
        load_assembly(path)
    return e.value


def _set(path, value):
    def fn(d):
        node = d
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return fn


CASES = [
    (_set(["steps", 0, "pose_in_base", "translation"], [1, 2]),
     "steps[0].pose_in_base.translation: expected 3 numbers, got 2"),
    (_set(["steps", 0, "pose_in_base", "translation"], [1, "x", 2]),
     "steps[0].pose_in_base.translation[1]: expected a finite number, got 'x'"),
    (_set(["colour"], "red"), "colour: unknown key; expected one of format, name, units"),
    (_set(["format"], "apose-assembly/2"), "format: expected 'apose-assembly/1', got the text 'apose-assembly/2'"),
    (_set(["units"], "furlong"), "units: expected one of m, cm, mm, in, got the text 'furlong'"),
    (_set(["steps", 0, "part"], "nope"), "steps[0].part: unknown part 'nope'; parts are plate, peg, cap"),
    (_set(["steps", 1, "part"], "peg"), "steps[1].part: 'peg' is already placed by steps[0]"),
    (_set(["steps", 0, "base"], ["plate", "cap"]), "steps[0].base[1]: 'cap' is placed only by a later step (steps[1])"),
    (_set(["steps", 0, "base"], []), "steps[0].base: expected a non-empty list of part ids, got a list"),
    (_set(["steps", 0, "base"], ["peg"]), "steps[0].base[0]: 'peg' cannot be part of its own base"),
    (_set(["parts", "plate", "mesh"], "missing.stl"), "missing.stl: file not found"),
    (_set(["parts", "plate", "size"], 3), "parts.plate.size: unknown key; expected one of mesh, solid, color, symmetry"),
    (_set(["parts", "peg", "color"], [2, 0, 0]), "parts.peg.color: expected 3 numbers in 0..1"),
    (_set(["parts", "peg", "symmetry"], {"axis": [0, 0, 1], "order": 1}),
     "parts.peg.symmetry.order: expected 0 (continuous) or a whole number n from 2 to 360"),
    (_set(["parts", "peg", "symmetry"], {"axis": [0, 0, 0], "order": 2}), "parts.peg.symmetry.axis: expected a non-zero direction"),
    (_set(["steps", 0, "pose_in_base", "rotation"], {"quat_wxyz": [0, 0, 0, 0]}),
     "steps[0].pose_in_base.rotation.quat_wxyz: expected a non-zero quaternion"),
    (_set(["steps", 0, "pose_in_base", "rotation"], {"quat_wxyz": [1, 0, 0, 0], "matrix": np.eye(3).tolist()}),
     "steps[0].pose_in_base.rotation: expected one of {quat_wxyz"),
    (_set(["steps", 0, "pose_in_base", "rotation"], {"euler_deg": [0, 0, 90], "order": "xyq"}),
     "steps[0].pose_in_base.rotation.order: expected a scipy axis order"),
    (_set(["steps", 0, "pose_in_base", "rotation"], {"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}),
     "steps[0].pose_in_base.rotation.matrix: expected a rotation matrix"),
    (_set(["registration"], {"voxel": 0.01}), "registration.voxel: unknown parameter; known: preset, voxel_size_m"),
    (_set(["registration"], {"voxel_size_m": -1}), "registration.voxel_size_m: expected a length in metres from 0.0001 to 0.5 (or null), got -1"),
    (_set(["registration"], {"ransac_max_iterations": 1.5}), "registration.ransac_max_iterations: expected a whole number from 1 to 1000000, got 1.5"),
    (_set(["camera"], {"width": 640, "height": 480, "fx": 600, "fy": 600, "cx": 320}), "camera.cy: missing"),
    (_set(["camera"], {"width": 640.5, "height": 480, "fx": 600, "fy": 600, "cx": 320, "cy": 240}),
     "camera.width: expected a positive whole number of pixels, got 640.5"),
    (_set(["steps"], "all of them"), "steps: expected a list of steps, got the text 'all of them'"),
]


@pytest.mark.parametrize("mutate,message", CASES, ids=[c[1][:40] for c in CASES])
def test_error_messages(tiny_dir, mutate, message):
    err = _mutate(tiny_dir, mutate)
    text = str(err)
    assert str(tiny_dir / "bad.yaml") in text
    assert message in text, text


def test_different_roots_in_one_base(tiny_dir):
    import trimesh

    trimesh.creation.box((5, 5, 5)).export(tiny_dir / "other.stl")

    def fn(d):
        d["parts"]["other"] = {"mesh": "other.stl"}
        d["steps"][1]["base"] = ["peg", "other"]
    assert "steps[1].base: base parts hang off different roots (other, plate)" in str(_mutate(tiny_dir, fn))


def test_every_problem_reported_at_once(tiny_dir):
    def fn(d):
        d["units"] = "yards"
        d["steps"][0]["pose_in_base"]["translation"] = [1]
        d["registration"] = {"bogus": 1}
    err = _mutate(tiny_dir, fn)
    keys = [p.key for p in err.problems]
    assert keys == ["units", "steps[0].pose_in_base.translation", "registration.bogus"]
    assert len(str(err).splitlines()) == 3


def test_yaml_syntax_and_missing_file(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("format: apose-assembly/1\nparts: [a, b\nsteps: []\n")
    with pytest.raises(AssemblyError, match=r"broken.yaml: line \d+, column \d+: YAML syntax error"):
        load_assembly(p)
    with pytest.raises(AssemblyError, match="nothere.yaml: file not found"):
        load_assembly(tmp_path / "nothere.yaml")
    p.write_text("- just\n- a list\n")
    with pytest.raises(AssemblyError, match="expected a mapping with format, name, units, parts, steps, got a list"):
        load_assembly(p)


def test_save_is_atomic(tiny_dir, monkeypatch):
    import apose_studio.assembly.model as A

    asm = load_assembly(tiny_dir / "assembly.yaml")
    target = tiny_dir / "assembly.yaml"
    before = target.read_text()

    def boom(*a, **k):
        raise RuntimeError("disk full")
    monkeypatch.setattr(A.os, "fsync", boom)
    with pytest.raises(RuntimeError):
        save_assembly(asm, target)
    assert target.read_text() == before
    assert not [p for p in tiny_dir.iterdir() if p.name.endswith(".tmp")]


def test_fidget_top_casing_pose(fidget_yaml):
    asm = load_assembly(fidget_yaml)
    view = asm.step_view(3)
    assert view.part == "top_casing" and view.base[0] == "bottom_casing"
    np.testing.assert_allclose(view.T_base_part[:3, 3], [0, 0, 0.012], atol=1e-12)
    R = view.T_base_part[:3, :3]
    assert abs(se3.rotation_angle_deg(R) - 179.9087) < 1e-6
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    # near 180 deg the skew part is tiny; the axis is the eigenvector with eigenvalue 1
    w, v = np.linalg.eig(R)
    axis = np.real(v[:, np.argmin(abs(w - 1))])
    assert abs(abs(axis[0]) - 1) < 1e-6
    assert isinstance(asm, Assembly) and asm.roots == ("bottom_casing",)
    np.testing.assert_allclose(asm.T_root_part("right_gear")[:3, 3], [-0.0115, 0, 0.005])


# ------------------------------------------------------------------- hostile and malformed files


def test_yaml_aliases_are_refused_before_they_expand(tmp_path):
    """Billion laughs: nine lines that expand to 10^9 items. Refused at the first alias, not after minutes."""
    lines = ["format: apose-assembly/1", "a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 9)]
    p = tmp_path / "laughs.yaml"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(AssemblyError, match=r"line 3, column \d+: YAML error: aliases \(\*name\) are not allowed"):
        load_assembly(p)


def _edited(tiny_dir, name: str, old: str, new: str):
    """A copy of the tiny assembly with one piece of text replaced."""
    path = tiny_dir / name
    path.write_text((tiny_dir / "assembly.yaml").read_text().replace(old, new))
    return path


def test_duplicate_keys_and_deep_nesting_are_errors(tiny_dir):
    dup = _edited(tiny_dir, "dup.yaml", "  cap: {mesh: cap.stl}\n", "  cap: {mesh: cap.stl}\n  peg: {mesh: cap.stl}\n")
    with pytest.raises(AssemblyError, match=r"duplicate key 'peg' \(first at line 6\)"):
        load_assembly(dup)
    deep = tiny_dir / "deep.yaml"
    deep.write_text("format: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(AssemblyError, match="nested far too deeply"):
        load_assembly(deep)


def test_part_ids_are_plain_names(tiny_dir):
    bad = _edited(tiny_dir, "bad.yaml", "  cap: {mesh: cap.stl}", '  "<img src=x onerror=alert(1)>": {mesh: cap.stl}')
    with pytest.raises(AssemblyError, match=r"a part id is 1 to 64 letters, digits, '_', '-' or '\.'"):
        load_assembly(bad)


def test_errors_never_echo_a_files_contents(tmp_path):
    secret = tmp_path / "passwd"
    secret.write_text("root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1:daemon:/usr/sbin:/usr/sbin/nologin\n")
    with pytest.raises(AssemblyError) as e:
        load_assembly(secret)
    assert "root:x" not in str(e.value) and "a text of" in str(e.value)


def test_limits_on_counts_and_symmetry_order(tiny_dir):
    import yaml

    data = yaml.safe_load((tiny_dir / "assembly.yaml").read_text())
    data["parts"]["peg"]["symmetry"]["order"] = 10_000_000
    with pytest.raises(AssemblyError, match="whole number n from 2 to 360"):
        assembly_from_dict(data, tiny_dir / "a.yaml")
    data = yaml.safe_load((tiny_dir / "assembly.yaml").read_text())
    data["steps"] = data["steps"] * 1500
    with pytest.raises(AssemblyError, match="3000 steps; at most 2000"):
        assembly_from_dict(data, tiny_dir / "a.yaml")


def test_chaining_a_long_sequence_is_exact(tmp_path):
    """A 1500-step chain (each part 1 mm along x and turned 1 degree on the one before): poses by chaining
    once through the steps, checked against products computed here."""
    import trimesh

    from apose_studio.geometry import se3

    trimesh.creation.box((1, 1, 1)).export(tmp_path / "b.stl")
    n = 1500
    parts = {f"p{i}": {"mesh": "b.stl"} for i in range(n + 1)}
    steps = [{"part": f"p{i + 1}", "base": [f"p{i}"],
              "pose_in_base": {"translation": [1, 0, 0], "rotation": {"euler_deg": [0, 0, 1]}}} for i in range(n)]
    asm = assembly_from_dict({"format": "apose-assembly/1", "name": "chain", "units": "mm", "parts": parts,
                              "steps": steps}, tmp_path / "chain.yaml")
    step = se3.make_T(se3.euler_deg_to_matrix([0, 0, 1], "xyz"), [0.001, 0, 0])
    want = np.eye(4)
    for _ in range(n):
        want = want @ step
    np.testing.assert_allclose(asm.T_root_part(f"p{n}"), want, atol=1e-12)
    assert asm.root_of(f"p{n}") == "p0" and len(asm.completed()["p0"]) == n + 1
