"""BOP19 results CSV: ours written, scored back with the same numbers; a malformed file named by line."""

import json
import subprocess
import sys

import numpy as np
import pytest

from apose_studio.data.bop import BopResult, read_results_csv, write_results_csv
from apose_studio.errors import DatasetError

APOSE = [sys.executable, "-m", "apose_studio.cli.commands"]


def run(*args):
    return subprocess.run([*APOSE, *map(str, args)], capture_output=True, text=True, timeout=600)


def test_results_csv_round_trip_scores_the_same(gearbox_dataset, tmp_path):
    out_json, out_csv, back_json = tmp_path / "eval.json", tmp_path / "ours.csv", tmp_path / "back.json"
    r = run("eval", gearbox_dataset, "--json", out_json, "--bop-results", out_csv)
    assert r.returncode == 0, r.stderr
    header = out_csv.read_text().splitlines()[0]
    assert header == "scene_id,im_id,obj_id,score,R,t,time"
    r = run("eval", gearbox_dataset, "--score-results", out_csv, "--json", back_json)
    assert r.returncode == 0, r.stderr
    ours, back = json.loads(out_json.read_text()), json.loads(back_json.read_text())
    for a, b in zip(ours["steps"], back["steps"]):
        assert a["recall_mssd"] == b["recall_mssd"] and a["failed"] == b["failed"]
        for key in ("adi", "mssd", "te", "re_deg"):
            assert a[key]["mean"] == pytest.approx(b[key]["mean"], abs=1e-9), key


def test_results_csv_reader_checks_every_line(tmp_path):
    good = BopResult(1, 0, 5, 0.9, np.eye(4), 0.1)
    path = tmp_path / "r.csv"
    write_results_csv(path, [good])
    assert read_results_csv(path)[0].obj_id == 5
    path.write_text(path.read_text() + "1,1,5,0.5,1 0 0 0 1 0 0 0,0 0 0,0.1\n")
    with pytest.raises(DatasetError, match="line 3"):
        read_results_csv(path)
    path.write_text("scene,im\n")
    with pytest.raises(DatasetError, match="line 1"):
        read_results_csv(path)


def test_eval_on_a_bop_split_folder(clutter_dataset, tmp_path):
    """A BOP split (our render's test/ folder read as plain BOP: scene_camera, scene_gt, mask_visib) with
    the base's parts mapped to obj_ids; writes BOP19 rows of base[0] in the camera frame."""
    info = json.loads((clutter_dataset / "dataset_info.json").read_text())
    maps = [a for part, obj in info["obj_ids"].items() for a in ("--obj-map", f"{part}={obj}")]
    out_json, out_csv = tmp_path / "e.json", tmp_path / "r.csv"
    r = run("eval", clutter_dataset / "test", "--assembly", clutter_dataset / "assembly.yaml", "--step", 2, *maps,
            "--mask", "box", "--json", out_json, "--bop-results", out_csv)
    assert r.returncode == 0, r.stderr
    st = json.loads(out_json.read_text())["steps"][0]
    assert st["n_frames"] == 3 and st["recall_mssd"] >= 2 / 3 and st["mask_iou"] > 0.6
    rows = read_results_csv(out_csv)
    base0 = json.loads((clutter_dataset / "test" / "000002" / "scene_assembly.json").read_text())["base"][0]
    assert {row.obj_id for row in rows} == {info["obj_ids"][base0]} and {row.scene_id for row in rows} == {2}
    r = run("eval", clutter_dataset / "test", "--assembly", clutter_dataset / "assembly.yaml", "--step", 2)
    assert r.returncode == 2 and "--obj-map" in r.stderr


def test_a_hand_written_results_file_with_a_known_offset(gearbox_dataset, tmp_path):
    """Scored against truth read straight from the BOP files (not through the code under test): each
    image's base pose from scene_gt.json moved 10 mm along the camera's x gives an assembly pose 10 mm off
    (a pure translation: ADD = MSSD = te = 10 mm, re = 0); a higher-scored row wins over a lower one."""
    from apose_studio.data.dataset import Dataset
    from apose_studio.evaluate import score_results

    ds_info = json.loads((gearbox_dataset / "dataset_info.json").read_text())
    sa = json.loads((gearbox_dataset / "test" / "000001" / "scene_assembly.json").read_text())
    base_obj = ds_info["obj_ids"][sa["base"][0]]
    gt = json.loads((gearbox_dataset / "test" / "000001" / "scene_gt.json").read_text())
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    for im, objs in gt.items():
        g = next(o for o in objs if o["obj_id"] == base_obj)
        R = " ".join(repr(float(v)) for v in g["cam_R_m2c"])
        t = np.asarray(g["cam_t_m2c"], float)
        lines.append(f"1,{im},{base_obj},0.9,{R},{' '.join(repr(float(v)) for v in t + [10.0, 0, 0])},0.5")
        lines.append(f"1,{im},{base_obj},0.2,{R},{' '.join(repr(float(v)) for v in t + [500.0, 0, 0])},0.5")  # loses
    (tmp_path / "hand.csv").write_text("\n".join(lines) + "\n")
    doc = score_results(Dataset(gearbox_dataset), read_results_csv(tmp_path / "hand.csv"))
    frames = doc["steps"][0]["frames"]
    assert len(frames) == len(gt) == 2
    for f in frames:
        assert f["ok"] and abs(f["mssd"] - 0.010) < 1e-6 and abs(f["te"] - 0.010) < 1e-6 and f["re_deg"] < 1e-4, f
    d = doc["steps"][0]["part_diameter"]
    assert doc["steps"][0]["recall_mssd"] == (1.0 if 0.010 < 0.1 * d else 0.0)  # recall at 0.1 x diameter


def test_obj_map_items_are_checked_and_a_scene_checks_what_it_shows(gearbox_dataset, tmp_path):
    """--obj-map / 'BOP object ids': PART=OBJ_ID with ASCII digits (a superscript two was an internal error);
    a scene refuses a base mapped to an obj_id none of its images shows, and a map with no id it shows,
    but takes a dataset-wide map that names objects it lacks."""
    import pytest

    from apose_studio.data.bop import BopScene, parse_obj_map
    from apose_studio.errors import DatasetError

    from ..conftest import plain_bop_scene

    parts = {"casing": None, "pinion": None}
    assert parse_obj_map(["casing=1", "pinion=2"], parts) == {"casing": 1, "pinion": 2}
    for bad in ("casing=\u00b2", "casing=", "casing=1.5", "casing=-1", "casing=1234567890"):
        with pytest.raises(DatasetError, match="expected PART=OBJ_ID"):
            parse_obj_map([bad], parts)
    scene = BopScene(plain_bop_scene(gearbox_dataset / "test" / "000001", tmp_path / "000001"))
    shown = scene.obj_ids()
    assert shown and all(scene.images_with(o) == 2 for o in shown)
    scene.check_obj_map({"casing": shown[0], "pinion": 99}, "casing")  # pinion absent here: fine
    with pytest.raises(DatasetError, match="obj_id 99 is in none of this scene's 2 images"):
        scene.check_obj_map({"casing": 99}, "casing")
    with pytest.raises(DatasetError, match="names no obj_id for the step's base 'casing'"):
        scene.check_obj_map({"pinion": shown[0]}, "casing")
    with pytest.raises(DatasetError, match="none of these obj_ids"):
        scene.check_obj_map({"casing": 98, "pinion": 99})


def test_a_scene_gt_with_an_absurd_number_of_objects_in_an_image_is_refused(gearbox_dataset, tmp_path):
    """400,000 objects in one image of a scene_gt.json (36 MB, under the JSON size limit) held the studio's
    lock for over 10 s while each entry was checked; more than MAX_OBJECTS_PER_IMAGE is refused, naming the
    file and the image."""
    import pytest

    from apose_studio.data.bop import BopScene
    from apose_studio.data.dataset import MAX_OBJECTS_PER_IMAGE
    from apose_studio.errors import DatasetError

    from ..conftest import plain_bop_scene

    scene = plain_bop_scene(gearbox_dataset / "test" / "000001", tmp_path / "000001")
    entry = {"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 500]}
    (scene / "scene_gt.json").write_text(json.dumps({"0": [entry] * (MAX_OBJECTS_PER_IMAGE + 1)}))
    with pytest.raises(DatasetError, match=r"scene_gt.json: 0: lists 1001 objects"):
        BopScene(scene, {"casing": 1}).frame(0)
