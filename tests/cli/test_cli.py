import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ..conftest import SAMPLES

APOSE = [sys.executable, "-m", "apose_studio.cli.commands"]


def run(*args, cwd=None):
    return subprocess.run([*APOSE, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_console_script_installed_and_help_lists_commands():
    exe = Path(sys.executable).parent / "apose"
    assert exe.exists(), "the `apose` console script is not installed in this environment"
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True).stdout
    for cmd in ("show", "demo"):
        assert cmd in out


def test_show_json_shape(tiny_dir):
    r = run("show", tiny_dir / "assembly.yaml", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["name"] == "tiny"
    assert set(doc["parts"]) == {"plate", "peg", "cap"}
    cap = doc["parts"]["cap"]
    assert cap["root"] == "plate" and Path(cap["mesh"]).name == "cap.stl"
    np.testing.assert_allclose(np.array(cap["T_root_part"])[:3, 3], [0, 0, 0.005], atol=1e-12)
    assert cap["diameter"] == pytest.approx(np.sqrt(0.012**2 * 2 + 0.003**2))
    assert [s["step"] for s in doc["steps"]] == [1, 2]
    assert doc["steps"][1]["base"] == ["peg", "plate"] and np.array(doc["steps"][0]["T_base_part"]).shape == (4, 4)


def test_show_text(tiny_dir):
    r = run("show", tiny_dir / "assembly.yaml")
    assert r.returncode == 0, r.stderr
    assert "peg.stl" in r.stdout and "continuous symmetry" in r.stdout
    assert "1. place peg on [plate]" in r.stdout and "t = (+10.00, +0.00, +5.00) mm" in r.stdout


def test_show_invalid_file_one_line_per_problem(tiny_dir):
    bad = tiny_dir / "bad.yaml"
    bad.write_text((tiny_dir / "assembly.yaml").read_text().replace("[10, 0, 5]", "[10, 0]").replace("units: mm", "units: yd"))
    r = run("show", bad)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert lines == [f"error: {bad}: units: expected one of m, cm, mm, in, got the text 'yd'",
                     f"error: {bad}: steps[0].pose_in_base.translation: expected 3 numbers, got 2"]
    assert "Traceback" not in r.stderr


def test_show_bad_mesh_is_one_line(tiny_dir):
    (tiny_dir / "peg.stl").write_bytes(b"\x00" * 10)
    r = run("show", tiny_dir / "assembly.yaml")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.startswith("error: part 'peg': ") and "peg.stl" in r.stderr


def test_a_refusal_asked_for_json_is_json_too(tiny_dir, tmp_path):
    """`--json` (show, estimate): a refused input still prints one JSON object on stdout, ok false with the reason
    the stderr line gives, and the exit code; without --json stdout stays empty."""
    (tiny_dir / "peg.stl").write_bytes(b"\x00" * 10)
    for args in (("show", tiny_dir / "assembly.yaml", "--json"), ("estimate", tmp_path / "nothing", "--step", "1", "--json")):
        r = run(*args)
        assert r.returncode == 2 and "Traceback" not in r.stderr
        doc = json.loads(r.stdout)
        assert doc["ok"] is False and doc["refused"] is True and doc["exit_code"] == 2
        assert r.stderr.startswith("error: ") and doc["reason"].splitlines()[0] == r.stderr.splitlines()[0][len("error: "):]
    assert run("show", tiny_dir / "assembly.yaml").stdout == ""
    for args, says in ((("estimate", tmp_path, "--json"), "the following arguments are required: --step"),  # usage errors
                       (("estimate", tmp_path, "--step", "abc", "--json"), "invalid int value: 'abc'"),
                       (("show", tiny_dir / "assembly.yaml", "--json", "--bogus"), "unrecognized arguments: --bogus")):
        r = run(*args)
        doc = json.loads(r.stdout)
        assert r.returncode == 2 and doc["refused"] and says in doc["reason"] and says in r.stderr, (r.stdout, r.stderr)
    assert run("estimate", tmp_path, "--step", "abc").stdout == ""
    # --json before the command, or spelt --json=1 (an outsider's probes), still a JSON refusal
    for args in (("--json", "show", tiny_dir / "assembly.yaml"), ("show", "--json=1", tiny_dir / "assembly.yaml")):
        r = run(*args)
        assert r.returncode == 2 and json.loads(r.stdout)["refused"], (r.stdout, r.stderr)


def test_a_refused_argument_is_named_as_typed_and_said_as_a_value_or_a_path(tiny_dir, tmp_path):
    """A 5,000-digit --box is 'longer than the 4096 a value may have' (it had been told to use a shorter path); a
    positional path with ESC in it is named INPUT / ASSEMBLY, as the usage names it (it had been '--input')."""
    r = run("estimate", tmp_path, "--step", "1", "--box", "1" * 5000, "--json")
    assert r.returncode == 2 and "--box of 5000 characters: longer than the 4096 a value may have" in r.stderr, r.stderr
    r = run("estimate", str(tmp_path / "a\x1bb"), "--step", "1")
    assert r.returncode == 2 and r.stderr.startswith("error: INPUT ") and "rename the file" in r.stderr, r.stderr
    r = run("estimate", tmp_path, "--step", "1", "--param", "seed=\x1b1")
    assert r.returncode == 2 and "--param" in r.stderr and "type it again without it" in r.stderr, r.stderr
    assert "\x1b" not in r.stdout + r.stderr  # shown escaped, never raw


def test_a_failed_estimate_in_json_says_why_on_stderr_too(gearbox_dataset, engine_dataset, tmp_path):
    """Exit 1 (the estimate failed: here a mask of a dozen pixels) with --json: the reason in the JSON and, in
    words, on stderr (it had been silent there: a script's log showed nothing). A seat (a region of the head) given
    a mask or a click instead of a box is bad input, refused before any work (exit 2; it had run and failed)."""
    import cv2

    mask = np.zeros((480, 640), np.uint8)
    mask[240:243, 320:324] = 255
    cv2.imwrite(str(tmp_path / "tiny.png"), mask)
    r = run("estimate", gearbox_dataset, "--step", "1", "--frame", "0", "--mask", tmp_path / "tiny.png", "--json")
    doc = json.loads(r.stdout)
    assert r.returncode == 1 and not doc["ok"] and r.stderr == f"estimation failed: {doc['reason']}\n", (r.stdout, r.stderr)
    for how in (("--mask", "depth"), ("--point", "320,240")):
        r = run("estimate", engine_dataset, "--step", "1", "--frame", "0", *how, "--json")
        assert r.returncode == 2 and json.loads(r.stdout)["refused"] and "region of a larger part" in r.stderr, (how, r.stderr)


def test_demo_runs_on_the_sample(tmp_path):
    r = run("demo", "--out", tmp_path / "demo", "--frames", "1", "--no-studio")
    assert r.returncode == 0, r.stderr
    assert "helical_gearbox" in r.stdout and "place lid on [casing, pinion, wheel]" in r.stdout
    assert "rendering 1 RealSense-like views per step" in r.stdout
    assert "failed:" not in r.stdout, r.stdout
    assert "likely wrong" not in r.stdout  # a result that is not confident says its doubt, not a verdict (#28)
    # one line per step: the estimated position and its MSSD / ADI against the frame's truth
    import re

    from apose_studio.data.dataset import Dataset

    rows = re.findall(r"step (\d): place (\w+) +at \( *([-+\d.]+), *([-+\d.]+), *([-+\d.]+)\) mm in the world; "
                      r"error vs truth: MSSD ([\d.]+) mm, ADI ([\d.]+) mm", r.stdout)
    assert [(s, part) for s, part, *_ in rows] == [("1", "pinion"), ("2", "wheel"), ("3", "lid")], r.stdout
    ds = Dataset(tmp_path / "demo")
    for step, _, x, y, z, mssd_mm, adi_mm in rows:
        assert 0 < float(mssd_mm) < 1.0 and 0 < float(adi_mm) < 1.0, (step, mssd_mm, adi_mm)
        # the printed position against the renderer's truth (scene_gt), not the code that scored it
        truth = ds.frame(int(step), 0).T_world_part[:3, 3] * 1000
        assert np.linalg.norm(np.array([x, y, z], float) - truth) < 1.0, (step, (x, y, z), truth)
    assert (tmp_path / "demo" / "test" / "000003" / "scene_gt.json").is_file()


def test_fidget_show_json(fidget_yaml):
    r = run("show", fidget_yaml, "--json")
    assert r.returncode == 0, r.stderr
    top = json.loads(r.stdout)["steps"][2]
    np.testing.assert_allclose(np.array(top["T_base_part"])[:3, 3], [0, 0, 0.012])


def test_estimate_on_the_truths_symmetric_twin_says_it_is_the_same_assembly(fidget_yaml, tmp_path):
    """The fidget's casing is 2-fold symmetric: a gear placed on it half turned is the same assembly. On this
    frame the estimate is that twin, and the ground-truth line (raw MSSD 48 mm, 180 degrees) goes on to say so,
    with the MSSD to the truth's equivalent placement (before, the line alone read as a wrong answer)."""
    out = tmp_path / "ds"
    r = run("render", fidget_yaml, "--out", out, "--frames", "1", "--steps", "1", "--clutter", "bench", "--seed", "5", "-q")
    assert r.returncode == 0, r.stderr
    r = run("estimate", out, "--step", "1", "--mask", "gt")
    assert r.returncode == 0, r.stderr
    truth = r.stdout.split("against ground truth:")[1]
    mssd = float(truth.split("MSSD ")[1].split(" mm")[0])
    assert mssd > 10 and "the same assembly as the truth turned by the base's symmetry" in truth, r.stdout
    assert float(truth.split("MSSD ")[2].split(" mm")[0]) < 1.0


def test_estimate_says_which_reading_of_the_mask_the_pose_came_from(tmp_path):
    """A gearbox casing mostly hidden behind a box: the box prompt (drawn round what is seen of the casing, 10 px
    wider) takes in the box in front, and the pose comes from what lies wholly in the prompt's box. The text
    output says so, with the result's mask, where before it named only the prompted mask."""
    out = tmp_path / "ds"
    r = run("render", SAMPLES / "helical_gearbox" / "assembly.yaml", "--out", out, "--frames", "1", "--steps", "2",
            "--clutter", "hidden", "--noise", "kinect", "--pitch-range", "20,50", "--seed", "5", "-q")
    assert r.returncode == 0, r.stderr
    r = run("estimate", out, "--step", "2", "--box", "260,171,384,251")
    assert r.returncode == 0, r.stderr
    assert "the pose came from another reading of the mask: what lies wholly in the box" in r.stdout, r.stdout
    assert "not confident" not in r.stdout
    assert float(r.stdout.split("MSSD ")[1].split(" mm")[0]) < 5.0, r.stdout
    # the text names both masks with the counts --json gives (the prompt's and the result's, cut to the model's view)
    doc = json.loads(run("estimate", out, "--step", "2", "--box", "260,171,384,251", "--json").stdout)["mask"]
    assert f"mask: box, {doc['prompt_pixels']} pixels" in r.stdout and doc["prompt_source"] == "box"
    assert f"the result's mask: {doc['source']}, {doc['pixels']} pixels" in r.stdout, r.stdout
    assert doc["pixels"] != doc["prompt_pixels"]


def test_render_cli(tmp_path):
    out = tmp_path / "ds"
    r = run("render", SAMPLES / "helical_gearbox" / "assembly.yaml", "--out", out, "--frames", "2", "--steps", "1,3",
            "--noise", "gaussian", "--base-pose", "fixed", "--pitch-range", "30,60", "-q")
    assert r.returncode == 0, r.stderr
    assert "rendered 4 frames of helical_gearbox" in r.stdout
    assert sorted(p.name for p in (out / "test").iterdir()) == ["000001", "000003"]
    info = json.loads((out / "dataset_info.json").read_text())
    assert info["settings"]["base_pose"] == "fixed" and info["settings"]["pitch_range_deg"] == [30.0, 60.0]
    again = run("render", SAMPLES / "helical_gearbox" / "assembly.yaml", "--out", out)
    assert again.returncode == 2 and again.stderr.startswith(f"error: {out}: folder is not empty")
    bad = run("render", SAMPLES / "helical_gearbox" / "assembly.yaml", "--out", tmp_path / "x", "--steps", "0")
    assert bad.returncode == 2 and "step 0 does not exist" in bad.stderr and "Traceback" not in bad.stderr
    bad = run("render", SAMPLES / "helical_gearbox" / "assembly.yaml", "--out", tmp_path / "x", "--yaw-range", "oops")
    assert bad.returncode == 2 and "expected two numbers as min,max" in bad.stderr


def test_malformed_inputs_get_one_clear_line(tiny_dir, gearbox_dataset, tmp_path):
    """Each of these reached the catch-all ("unexpected ...") or said the wrong thing; each now names the
    thing and the fix."""
    import numpy as np
    import trimesh

    flat = trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), [[0, 1, 2]], process=False)
    (tiny_dir / "flat.stl").write_bytes(flat.export(file_type="stl"))
    (tiny_dir / "text.stl").write_text("hello, this is a note and not a mesh\n" * 5)
    (tiny_dir / "folder.stl").mkdir()
    base = (tiny_dir / "assembly.yaml").read_text()
    cases = [("flat.stl", "all triangles are degenerate (zero area)"),
             ("text.stl", "text.stl: a text file, not a STL mesh"),
             ("folder.stl", "folder.stl: a folder, not a file"),
             ("/dev/zero", "/dev/zero: not a regular file")]
    for mesh, message in cases:
        y = tiny_dir / "m.yaml"
        y.write_text(base.replace("cap: {mesh: cap.stl}", f"cap: {{mesh: {mesh}}}"))
        r = run("show", y)
        assert r.returncode == 2 and message in r.stderr and "unexpected" not in r.stderr, (mesh, r.stderr)
    for args, message in [(("eval", gearbox_dataset, "--json", tmp_path), "a folder; give a file name"),
                          (("train-seg", gearbox_dataset, "--out", tmp_path / "no" / "m.pt"), "does not exist"),
                          (("train-seg", gearbox_dataset, "--out", "m.pt", "--epochs", "0"), "at least 1, got '0'"),
                          (("train-seg", gearbox_dataset, "--out", "m.pt", "--batch", "0"), "at least 1, got '0'"),
                          (("studio", "--port", "70000"), "port number from 1 to 65535"),
                          (("estimate", gearbox_dataset, "--step", "1", "--box", "1e309,0,10,10"), "expected four pixel numbers")]:
        r = run(*args)
        assert r.returncode != 0 and message in r.stderr and "unexpected" not in r.stderr, (args, r.stderr)


def test_eval_counts_an_unreadable_frame_as_failed_and_names_a_missing_step(gearbox_dataset, tmp_path):
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(gearbox_dataset, ds)
    (ds / "test" / "000001" / "depth" / "000001.png").unlink()
    info = json.loads((ds / "dataset_info.json").read_text())
    info["steps_rendered"] = [1, 2]
    (ds / "dataset_info.json").write_text(json.dumps(info))
    r = run("eval", ds, "--orientation-prior", "--json", tmp_path / "e.json")
    assert r.returncode == 0, r.stderr
    assert "step 2 is listed" in r.stderr and "test/000002 is missing" in r.stderr
    assert "1 frame(s) could not be read and count as failed: step 1 frame 1" in r.stderr
    doc = json.loads((tmp_path / "e.json").read_text())
    (st,) = doc["steps"]
    assert st["n_frames"] == 2 and st["failed"] == 1 and doc["missing_steps"] == [2]
    assert "000001.png: missing" in st["frames"][1]["reason"]


def test_demo_refuses_a_folder_it_did_not_make(tmp_path):
    out = tmp_path / "work"
    (out / "models").mkdir(parents=True)
    (out / "models" / "my_model.bin").write_text("checkpoint")
    r = run("demo", "--out", out, "--frames", "1", "--no-studio")
    assert r.returncode == 2 and "holds files that no apose render wrote (models/my_model.bin)" in r.stderr
    assert (out / "models" / "my_model.bin").read_text() == "checkpoint"


def test_bidi_controls_are_escaped_and_long_values_shortened(tmp_path):
    """#24 minors: a right-to-left override in a path was printed raw (the terminal shows 'x\\u202elmay.yaml'
    as 'xyaml.yml'), and a 5000-character value was echoed whole in an error."""
    from apose_studio.cli.common import printable
    from apose_studio.text import shorten_values

    r = run("show", tmp_path / "x\u202elmay.yaml")
    assert r.returncode == 2 and "\u202e" not in r.stderr and "x\\u202elmay.yaml" in r.stderr, r.stderr
    for c in "\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069\u200e\u200f\u061c\u2028\u2029\x1b\x9b":
        assert c not in printable(f"a{c}b")
    assert printable("tab\tnew\nline é ü 字") == "tab\tnew\nline é ü 字"
    long_name = "d" * 300  # a name too long for the file system: the message names the path
    r = run("show", tmp_path / f"{long_name}.yaml")
    assert r.returncode == 2 and long_name not in r.stderr and "characters)" in r.stderr, r.stderr
    assert max(map(len, r.stderr.splitlines())) < 400
    text = shorten_values("score is " + "9" * 5000 + " ; write a finite number")
    assert text.startswith("score is 9999") and "(5000 characters)" in text and text.endswith(" ; write a finite number")
    assert shorten_values("a normal /path/to/file.yaml: 12 problems") == "a normal /path/to/file.yaml: 12 problems"


def test_export_html_writes_a_standalone_replay_and_refuses_what_is_not_there(gearbox_dataset, tmp_path):
    """`apose export-html DATASET --step K --frame I --out OUT.html`: the page holds viser's client, the
    scene (embedded, base64) and the caption; a step or frame the dataset lacks is refused with exit code 2
    and the choices, and no file is written. (tests/e2e opens such a page in Chromium from disk.)"""
    out = tmp_path / "replay.html"
    r = run("export-html", gearbox_dataset, "--step", 1, "--frame", 1, "--orientation-prior", "--out", out)
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    assert "__VISER_EMBED_DATA__" in page and "id='apose-caption'" in page and "step 1: pinion on casing" in page
    assert "frame 1 &middot;" in page
    assert "wrote" in r.stdout and "Server stopped" not in r.stdout
    for args, said in ((("--step", 4, "--frame", 0), "has steps 1"), (("--step", 1, "--frame", 7), "has frames 0, 1")):
        bad = tmp_path / "bad.html"
        r = run("export-html", gearbox_dataset, *args, "--out", bad)
        assert r.returncode == 2 and said in r.stderr and not bad.exists(), r.stderr


def test_export_html_of_a_capture_needs_its_assembly(gearbox_dataset, tmp_path):
    """A capture folder has no assembly: the CLI says so in its own words (not the studio's), exit code 2."""
    from apose_studio.data.dataset import Dataset

    from ..conftest import write_capture

    cap = write_capture(Dataset(gearbox_dataset).frame(1, 0), tmp_path / "capture")
    r = run("export-html", cap, "--step", 1, "--out", tmp_path / "x.html")
    assert r.returncode == 2 and "give --assembly" in r.stderr and "Assembly tab" not in r.stderr, r.stderr
    assert r.stdout == "" and not (tmp_path / "x.html").exists()


def test_export_html_of_a_bop_scene_with_its_obj_ids(gearbox_dataset, tmp_path):
    """A BOP scene folder with --assembly and --obj-map: the page of its image --frame, scored against its
    scene_gt.json; a part the assembly lacks is refused in the CLI's words (exit code 2, nothing written)."""
    from ..conftest import plain_bop_scene

    scene = plain_bop_scene(gearbox_dataset / "test" / "000001", tmp_path / "000003")
    asm = SAMPLES / "helical_gearbox" / "assembly.yaml"
    obj_ids = json.loads((gearbox_dataset / "dataset_info.json").read_text())["obj_ids"]
    out = tmp_path / "bop.html"
    r = run("export-html", scene, "--assembly", asm, "--step", 1, "--frame", 1, "--obj-map", f"casing={obj_ids['casing']}",
            "--out", out)
    assert r.returncode == 0, r.stderr
    page = out.read_text()
    assert "frame 1 &middot;" in page and "MSSD" in page
    bad = tmp_path / "bad.html"
    for obj_map, said in (("nopart=3", "--obj-map nopart=3"), ("casing=99", "obj_id 99 is in none of this scene's"),
                          (f"pinion={obj_ids['pinion']}", "names no obj_id for the step's base 'casing'")):
        r = run("export-html", scene, "--assembly", asm, "--step", 1, "--obj-map", obj_map, "--out", bad)
        assert r.returncode == 2 and said in r.stderr and not bad.exists(), r.stderr
    r = run("export-html", gearbox_dataset, "--step", 1, "--obj-map", "casing=1", "--out", bad)  # not a BOP scene
    assert r.returncode == 2 and "is not a BOP scene folder" in r.stderr and not bad.exists(), r.stderr
