"""The one parameter schema: every field is accepted in an assembly file and on the command line, values
out of range are refused at their key, the presets hold the values the paper and we chose (written out
here by hand, not read from the code), and the reference table in the docs is the schema's."""

import dataclasses
import re

import pytest
import yaml

from apose_studio.assembly.model import load_assembly, save_assembly
from apose_studio.errors import AposeError, AssemblyError
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.params import FIELDS, PRESET_PARAMS, Params, parameter_table, parse_param, resolve_params

from .cli.test_cli import run
from .conftest import REPO, TINY_YAML


def other_value(name: str):
    """A valid value of the field that differs from its default."""
    f = FIELDS[name]
    m, d = f.metadata, f.default
    if m["kind"] == "bool":
        return not d
    if m["choices"]:
        return next(c for c in m["choices"] if c != d)
    if m["kind"] == "camera":
        return {"width": 320, "height": 240, "fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0}
    lo, hi = m["lo"], m["hi"]
    v = lo if d != lo else hi
    return int(v) if m["kind"] == "int" else float(v)


def with_registration(tiny_dir, section) -> str:
    doc = yaml.safe_load(TINY_YAML)
    doc["registration"] = section
    path = tiny_dir / "reg.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize("name", [n for n in FIELDS if n != "preset"])
def test_every_field_is_accepted_in_an_assembly_file(tiny_dir, name):
    value = other_value(name)
    asm = load_assembly(with_registration(tiny_dir, {name: value}))
    got = getattr(resolve_params("default", asm.registration), name)
    want = CameraIntrinsics(**value) if isinstance(value, dict) else value
    assert got == want and got != getattr(Params(), name)


def test_the_documented_example_loads(tiny_dir):
    """The README's and the docs' examples, e.g. `registration: {second_look: true}` (a documented key that must load)."""
    texts = (REPO / "README.md").read_text() + "".join(p.read_text() for p in (REPO / "docs").glob("*.md"))
    inline = re.findall(r"registration: \{([^}]*)\}", texts)
    assert inline, "no `registration: {...}` example found in the docs"
    for body in inline:
        section = yaml.safe_load("{" + body + "}")
        asm = load_assembly(with_registration(tiny_dir, section))
        p = resolve_params("default", asm.registration)
        assert all(getattr(p, k) == v for k, v in section.items() if k != "preset"), body


def test_a_section_round_trips_through_save(tiny_dir):
    section = {"voxel_size_m": 0.004, "second_look": False, "source_camera": other_value("source_camera"), "seed": 7}
    asm = load_assembly(with_registration(tiny_dir, section))
    save_assembly(asm, tiny_dir / "again.yaml")
    again = load_assembly(tiny_dir / "again.yaml")
    assert dict(again.registration) == dict(asm.registration) and len(asm.registration) == 4


def test_unknown_and_out_of_range_keys_are_refused_at_their_key(tiny_dir):
    with pytest.raises(AssemblyError) as e:
        load_assembly(with_registration(tiny_dir, {"second_looks": True, "max_starts": 0, "global_source": "mesh",
                                                   "voxel_size_m": "4mm", "upright": 1}))
    text = str(e.value)
    known = re.search(r"registration\.second_looks: unknown parameter; known: ([\w, ]+)", text).group(1).split(", ")
    assert set(known) == set(FIELDS)
    assert "registration.max_starts: expected a whole number from 1 to 64, got 0" in text
    assert "registration.global_source: expected one of model, raycast, got 'mesh'" in text
    assert "registration.voxel_size_m: expected a length in metres from 0.0001 to 0.5 (or null), got '4mm'" in text
    assert "registration.upright: expected true or false, got 1" in text


def test_each_numeric_range_is_enforced_at_both_ends(tiny_dir):
    for name, f in FIELDS.items():
        m = f.metadata
        if m["kind"] not in ("int", "float"):
            continue
        for inside, outside in ((m["lo"], m["lo"] - 1e-9 if m["kind"] == "float" else m["lo"] - 1),
                                (m["hi"], m["hi"] + 1e-9 * max(1, m["hi"]) if m["kind"] == "float" else m["hi"] + 1)):
            assert resolve_params("default", None, **{name: inside}).__getattribute__(name) == inside
            with pytest.raises(AposeError, match=name):
                resolve_params("default", None, **{name: outside})


def test_the_presets_hold_the_published_and_our_values():
    """The paper's settings as the paper states them (../shared/docs/METHOD.md), and ours, by hand."""
    paper = PRESET_PARAMS["paper"]
    assert (paper.voxel_size_m, paper.ransac_max_iterations, paper.ransac_confidence) == (0.008, 100000, 0.899)
    assert (paper.icp_threshold_factor, paper.icp_max_iterations, paper.global_source) == (0.4, 30, "raycast")
    cam = paper.source_camera
    assert (cam.width, cam.height, cam.cx, cam.cy) == (1280, 720, 640.0, 360.0)
    assert cam.fx == pytest.approx(640 / 0.5773502692)  # 60 degrees across 1280 pixels
    assert paper.use_orientation_prior and not paper.downsample and not paper.second_look and paper.max_seconds == 0
    ours = PRESET_PARAMS["default"]
    assert ours == Params()  # the schema's defaults are ours
    assert (ours.voxel_size_m, ours.voxels_per_diameter, ours.global_source, ours.max_seconds) == (None, 50.0, "model", 0.0)
    assert ours.upright and ours.second_look and ours.use_symmetries and not ours.use_orientation_prior
    assert dataclasses.is_dataclass(Params) and Params.__dataclass_params__.frozen


def test_the_file_then_the_caller_override_the_preset(tiny_dir):
    asm = load_assembly(with_registration(tiny_dir, {"preset": "paper", "icp_max_iterations": 50, "seed": 3}))
    p = resolve_params("default", asm.registration, seed=9)
    assert (p.preset, p.icp_max_iterations, p.seed, p.voxel_size_m) == ("paper", 50, 9, 0.008)
    with pytest.raises(AposeError, match="unknown preset 'fast'; choose one of default, paper"):
        resolve_params("fast")


def test_param_flag_values():
    assert parse_param("max_seconds=0") == ("max_seconds", 0.0)
    assert parse_param("voxel_size_m=null") == ("voxel_size_m", None)
    assert parse_param("upright=false") == ("upright", False)
    for bad, why in (("max_second=0", "NAME one of preset, voxel_size_m"), ("max_seconds", "expected NAME=VALUE"),
                     ("max_seconds=abc", "max_seconds: expected seconds from 0"), ("upright=2", "expected true or false")):
        with pytest.raises(AposeError, match=why):
            parse_param(bad)


def test_param_flag_on_the_command_line(gearbox_dataset):
    """`apose estimate --param`: applied (the JSON's voxel is the one asked for) and checked (a bad one is
    refused with exit code 2 and the list of names)."""
    import json

    r = run("estimate", gearbox_dataset, "--step", "1", "--frame", "0", "--json", "--param", "voxel_size_m=0.004",
            "--param", "max_seconds=0")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["voxel_m"] == 0.004
    r = run("estimate", gearbox_dataset, "--step", "1", "--frame", "0", "--param", "voxel=0.004")
    assert r.returncode == 2 and "--param voxel=0.004: expected NAME=VALUE with NAME one of" in r.stderr


def test_the_docs_table_is_the_schema():
    text = (REPO / "docs" / "ASSEMBLY_FILES.md").read_text()
    table = text.split("<!-- parameter table -->\n", 1)[1].split("\n<!-- end of parameter table -->", 1)[0]
    assert table == parameter_table(), "regenerate the table in docs/ASSEMBLY_FILES.md from params.parameter_table()"
    assert all(f"| `{n}` |" in table for n in FIELDS if n != "preset")


def test_numbers_too_big_for_a_float_are_refused_at_their_key(tiny_dir):
    """An int of 400 digits (YAML and JSON read any size) is refused with the range, in a file, on the
    command line and in a camera section; it once reached numpy and came back as a TypeError."""
    from apose_studio.geometry.camera import is_number

    huge = int("9" * 400)
    assert not is_number(huge) and is_number(10 ** 300) and not is_number(True) and not is_number("1")
    for name in ("ransac_max_iterations", "voxel_size_m", "max_seconds"):
        with pytest.raises(AssemblyError, match=f"registration.{name}: expected"):
            load_assembly(with_registration(tiny_dir, {name: huge}))
        with pytest.raises(AposeError, match=f"--param {name}: expected"):
            parse_param(f"{name}={huge}")
    cam = {"width": 640, "height": 480, "fx": huge, "fy": 500, "cx": 320, "cy": 240}
    with pytest.raises(AssemblyError, match="registration.source_camera.fx: expected a positive number"):
        load_assembly(with_registration(tiny_dir, {"source_camera": cam}))


def test_integers_longer_than_python_converts_are_named_at_their_line(tiny_dir):
    """5000 digits: more than Python turns into an int (4300); once an "unexpected ValueError" exit 1."""
    path = tiny_dir / "long.yaml"
    path.write_text(TINY_YAML + "registration: {seed: " + "9" * 5000 + "}\n")
    with pytest.raises(AssemblyError, match=r"line \d+, column \d+: YAML error: a whole number of 5000 digits"):
        load_assembly(path)
    with pytest.raises(AposeError, match="--param seed: expected"):
        parse_param("seed=" + "9" * 5000)
