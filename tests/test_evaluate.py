"""The evaluation loop, its JSON document and table, and the estimate/eval commands."""

import json
import subprocess
import sys

import numpy as np
import pytest

from apose_studio.assembly.mesh import load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.data.dataset import Dataset
from apose_studio.evaluate import evaluate, format_table
from apose_studio.geometry.metrics import mssd
from apose_studio.registration import RegistrationResult, resolve_params
from apose_studio.synth.frame import RenderSettings
from apose_studio.synth.render import render_dataset

from .conftest import SAMPLES


@pytest.fixture(scope="module")
def gearbox_fixed(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "ds"
    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=2, base_pose="fixed", seed=3), steps=[2], progress=False)
    return Dataset(out)


def test_evaluate_document(gearbox_fixed):
    doc = evaluate(gearbox_fixed, resolve_params("default"), orientation_prior=True, progress=False)
    assert doc["preset"] == "default" and doc["mask"] == "gt" and len(doc["steps"]) == 1
    st = doc["steps"][0]
    assert st["step"] == 2 and st["n_frames"] == 2 and st["part"] == "wheel" and len(st["frames"]) == 2
    for key in ("fitness", "inlier_rmse", "adi", "mssd", "te", "re_deg"):
        assert set(st[key]) == {"mean", "std"}
    assert set(st["time_s"]) == {"mean", "median"} and 0 <= st["recall_mssd"] <= 1
    fr = st["frames"][0]
    assert {"scene_id", "im_id", "T_world_part_est", "T_world_part_gt", "adi", "mssd", "fitness", "time_s", "ok"} <= set(fr)
    assert np.array(fr["T_world_part_gt"]).shape == (4, 4)
    json.dumps(doc)  # plain JSON all the way down
    assert all(isinstance(f[k], bool) for f in st["frames"] for k in ("ok", "ambiguous", "confident"))
    table = format_table(doc)
    assert "MSSD mm" in table and table.splitlines()[2].split()[0] == "2"
    # the values: noise-free renders with the CAD's orientation known, both frames right to a tenth of a mm
    assert st["failed"] == 0 and st["recall_mssd"] == 1.0 and st["ar_mssd"] == 1.0
    models = load_parts(gearbox_fixed.assembly)
    wheel = models["wheel"]
    for f in st["frames"]:
        truth = gearbox_fixed.frame(2, f["im_id"]).T_world_part  # the renderer's scene_assembly.json
        est = np.array(f["T_world_part_est"])
        np.testing.assert_allclose(f["T_world_part_gt"], truth, atol=1e-12)
        assert f["ok"] and f["confident"]
        # te and the rotation error by hand; MSSD (the metric is tested in test_metrics) against the truth
        assert f["te"] == pytest.approx(np.linalg.norm(est[:3, 3] - truth[:3, 3])) and f["te"] < 1e-4
        cos = (np.trace(est[:3, :3].T @ truth[:3, :3]) - 1) / 2
        assert f["re_deg"] == pytest.approx(np.degrees(np.arccos(min(cos, 1.0))), abs=1e-6) and f["re_deg"] < 0.1
        assert f["mssd"] == pytest.approx(mssd(est, truth, wheel.samples, wheel.symmetries)) and f["mssd"] < 1e-4
    assert st["mssd"]["mean"] == pytest.approx(np.mean([f["mssd"] for f in st["frames"]]))
    assert st["te"]["mean"] == pytest.approx(np.mean([f["te"] for f in st["frames"]]))


def test_failed_frames_count_as_misses(gearbox_fixed, monkeypatch):
    import apose_studio.estimation as E

    monkeypatch.setattr(E, "estimate", lambda *a, **k: RegistrationResult(ok=False, reason="empty mask: test"))
    doc = evaluate(gearbox_fixed, resolve_params("default"), progress=False)
    st = doc["steps"][0]
    assert st["failed"] == 2 and st["recall_mssd"] == 0.0 and st["adi"]["mean"] is None
    assert st["frames"][0]["ok"] is False and st["frames"][0]["reason"] == "empty mask: test"


def test_estimate_and_eval_commands(gearbox_fixed, tmp_path):
    cli = [sys.executable, "-m", "apose_studio.cli.commands"]
    r = subprocess.run(cli + ["estimate", str(gearbox_fixed.root), "--step", "2", "--frame", "1", "--json",
                              "--orientation-prior"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["ok"] and np.array(doc["T_world_part_est"]).shape == (4, 4) and doc["stages"][-1]["name"] == "final"
    # the pose against the frame's truth (scene_assembly.json), not the numbers the command printed beside it
    truth = gearbox_fixed.frame(2, 1).T_world_part
    wheel = load_parts(gearbox_fixed.assembly)["wheel"]
    est = np.array(doc["T_world_part_est"])
    assert doc["confident"] and np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 1e-4
    assert mssd(est, truth, wheel.samples, wheel.symmetries) < 1e-4
    np.testing.assert_allclose(doc["T_world_part"], est)
    r = subprocess.run(cli + ["estimate", str(gearbox_fixed.root), "--step", "2", "--frame", "1"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "T_world_part (estimated assembly pose; world: the dataset's world frame):" in r.stdout \
        and "q (w,x,y,z)" in r.stdout
    r = subprocess.run(cli + ["estimate", str(gearbox_fixed.root), "--step", "3"], capture_output=True, text=True)
    assert r.returncode == 2 and "step 3 was not rendered; rendered steps: 2" in r.stderr
    out = tmp_path / "eval.json"
    r = subprocess.run(cli + ["eval", str(gearbox_fixed.root), "--preset", "paper", "--frames", "1", "--json", str(out),
                              "--orientation-prior"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "preset paper" in r.stdout and json.loads(out.read_text())["steps"][0]["n_frames"] == 1
    r = subprocess.run(cli + ["eval", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "not an apose dataset" in r.stderr and "Traceback" not in r.stderr


def test_confidence_flag_follows_coverage():
    ok = RegistrationResult(ok=True, fitness=0.7, coverage=0.95)
    poor = RegistrationResult(ok=True, fitness=0.9, coverage=0.5)
    assert ok.confident and not poor.confident and not RegistrationResult(ok=False).confident


# ---------------------------------------------------------- results files: every column checked (#24 M-f)


def test_results_rows_that_cannot_be_scored_are_refused_with_the_row_and_the_fix(gearbox_fixed):
    """Only `score` was checked: a NaN, infinite or negative time printed nan with exit 0, t = 1e308 gave
    overflow warnings and inf, and a reflected or scaled R was scored silently as a miss."""
    from apose_studio.data.bop import BopResult
    from apose_studio.errors import DatasetError
    from apose_studio.evaluate import check_results, score_results

    def row(R=np.eye(3), t_mm=(0.0, 0.0, 500.0), time=0.25, score=1.0):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, np.asarray(t_mm) / 1000.0
        return BopResult(2, 0, 1, score, T, time)

    good = row()
    check_results([good, row(time=-1.0), row(time=0.0)])  # -1: BOP's "not measured"
    cases = [(row(time=float("nan")), "time is nan"), (row(time=float("inf")), "time is inf"),
             (row(time=-5.0), "time is -5"), (row(time=1e9), "time is 1e+09"),
             (row(t_mm=(1e308, 0.0, 0.0)), "t is 1e+308 mm away"),
             (row(R=np.diag([1.0, 1.0, -1.0])), "R is a reflection"), (row(R=2 * np.eye(3)), "R is not a rotation"),
             (row(score=float("nan")), "score is nan")]
    for bad, message in cases:
        with pytest.raises(DatasetError) as e:
            check_results([good, good, bad])
        text = str(e.value)
        assert "row 3 after the header (scene_id 2, im_id 0, obj_id 1)" in text and message in text, text
    assert "-1 when it was not measured" in str(pytest.raises(DatasetError, check_results, [row(time=-5.0)]).value)
    with pytest.raises(DatasetError, match="R is a reflection"):  # scoring refuses, never scores it as a miss
        score_results(gearbox_fixed, [row(R=np.diag([1.0, 1.0, -1.0]))])


def test_score_results_command_refuses_a_bad_column_with_exit_2(gearbox_fixed, tmp_path):
    header = "scene_id,im_id,obj_id,score,R,t,time\n"
    cli = [sys.executable, "-m", "apose_studio.cli.commands", "eval", str(gearbox_fixed.root), "--score-results"]
    for name, line, message in (("huge_t", "2,0,1,1.0,1 0 0 0 1 0 0 0 1,1e308 0 0,0.1\n", "t is 1e+308 mm away"),
                                ("nan_time", "2,0,1,1.0,1 0 0 0 1 0 0 0 1,0 0 500,nan\n", "time is nan"),
                                ("mirror", "2,0,1,1.0,1 0 0 0 1 0 0 0 -1,0 0 500,0.1\n", "R is a reflection")):
        path = tmp_path / f"{name}.csv"
        path.write_text(header + line)
        r = subprocess.run(cli + [str(path)], capture_output=True, text=True, timeout=300)
        assert r.returncode == 2 and message in r.stderr and "row 1 after the header" in r.stderr, r.stderr
        assert "RuntimeWarning" not in r.stderr and "nan" not in r.stdout


def test_results_ids_and_numbers_are_ascii_and_rows_must_name_the_dataset(gearbox_fixed, tmp_path):
    """int() read '１' (full-width) as 1 and '1_0' as 10; rows naming no image of the dataset were dropped
    silently and everything scored as failed (#24, third attack)."""
    from apose_studio.data.bop import read_results_csv
    from apose_studio.errors import DatasetError
    from apose_studio.evaluate import score_results

    header = "scene_id,im_id,obj_id,score,R,t,time\n"
    for i, line in enumerate(("\uff12,0,1,1.0,1 0 0 0 1 0 0 0 1,0 0 500,0.1", "2,0,1_0,1.0,1 0 0 0 1 0 0 0 1,0 0 500,0.1",
                              "2,0,1,1.0,1 0 0 0 1 0 0 0 1,0 0 5_00,0.1", "2," + "9" * 400 + ",1,1,1 0 0 0 1 0 0 0 1,0 0 1,0.1")):
        path = tmp_path / f"bad{i}.csv"
        path.write_text(header + line + "\n")
        with pytest.raises(DatasetError, match="line 2: expected scene_id,im_id,obj_id"):
            read_results_csv(path)
    path = tmp_path / "elsewhere.csv"
    path.write_text(header + "77,0,1,1.0,1 0 0 0 1 0 0 0 1,0 0 500,0.1\n")
    with pytest.raises(DatasetError, match="none of its 1 rows names an image of this dataset.*scene_id 77"):
        score_results(gearbox_fixed, read_results_csv(path))
