"""BOP19 results CSV: ours written, scored back with the same numbers; a malformed file named by line."""

import json
import subprocess
import sys

import numpy as np
import pytest

from apose_studio.bop import BopResult, read_results_csv, write_results_csv
from apose_studio.errors import DatasetError

APOSE = [sys.executable, "-m", "apose_studio.cli"]


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
