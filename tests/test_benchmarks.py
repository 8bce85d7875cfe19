"""benchmarks/captures.py --compare: what changed between two runs' rows, as the notes and docs/BENCHMARKS.md quote it
("outcome changed on 0 of 528")."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "benchmarks" / "captures.py"


@pytest.fixture(scope="module")
def captures():
    spec = importlib.util.spec_from_file_location("captures_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(im_id, right=True, confident=True, mssd=1.0, seconds=0.2, condition="kinect", telling_px=-1):
    return {"assembly": "fidget", "condition": condition, "step": 1, "im_id": im_id, "right": right,
            "confident": confident, "mssd_mm": mssd, "seconds": seconds, "doubts": "" if confident else "ambiguous",
            "telling_px": telling_px}


def test_compare_finds_the_frames_whose_outcome_changed(captures):
    before = [_row(0), _row(1), _row(2), _row(3), _row(4, condition="hidden", seconds=1.0)]
    same = captures.compare_rows(before, before)
    assert "outcome changed on 0 of 5" in same[0] and len([s for s in same if s.startswith("  fidget/")]) == 0
    after = [_row(0, mssd=1.0 + 0.9 * captures.COMPARE_MM),  # moved within the tolerance: the same outcome
             _row(1, confident=False),  # lost its confidence
             _row(2, right=False, mssd=30.0),  # confident and wrong now
             _row(3, mssd=None, right=False, confident=False),  # failed
             _row(4, condition="hidden", seconds=0.5),
             _row(5)]  # a frame the run before did not have
    lines = captures.compare_rows(before, after)
    assert "5 frames (1 only in this run, 0 only in the one before): outcome changed on 3 of 5" in lines[0], lines[0]
    listed = [s for s in lines if s.startswith("  fidget/")]
    assert [s.split(":")[0].strip() for s in listed] == ["fidget/kinect/1/1", "fidget/kinect/1/2", "fidget/kinect/1/3"]
    assert "error 1.0 -> failed mm" in listed[2]
    assert any(s.split()[:2] == ["hidden", "s/frame"] and "total 1.0 -> 0.5" in s for s in lines), lines
    assert lines[-2].endswith("before: confident-and-wrong 0, unconfident-and-right 0.0% and recall 1.000 where the view "
                              "can tell")
    assert "after:  confident-and-wrong 1, unconfident-and-right 20.0% and recall 0.600" in lines[-1], lines[-1]
    moved = captures.compare_rows(before, [_row(0, mssd=1.0 + 1.1 * captures.COMPARE_MM)])
    assert "outcome changed on 1 of 1" in moved[0]
    nan = captures.compare_rows(before, [_row(0, mssd=float("nan"))])  # an error that became NaN has changed
    assert "outcome changed on 1 of 1" in nan[0]
    twice = captures.compare_rows(before, [_row(0), _row(0)])
    assert "1 rows now repeat a frame" in twice[1], twice


@pytest.mark.parametrize("contents, why", [(None, "No such file"), ("not json", "Expecting value"),
                                           ('{"rows": []}', "not a list of frame rows"),
                                           ('[{"assembly": "fidget"}]', "row 0 has no condition")])
def test_compare_refuses_what_is_not_a_run_before_the_run(tmp_path, contents, why):
    """A --compare file that is missing or is not this benchmark's --json rows is refused at once, named, before minutes
    of estimates."""
    bad = tmp_path / "before.json"
    if contents is not None:
        bad.write_text(contents)
    out = subprocess.run([sys.executable, str(SCRIPT), "--compare", str(bad)], capture_output=True, text=True,
                         timeout=120, cwd=REPO)
    assert out.returncode == 2 and f"--compare {bad}: not a --json file of this benchmark" in out.stderr, out.stderr
    assert why in out.stderr and out.stdout == "", (out.stderr, out.stdout)


def test_each_real_like_row_is_held_to_the_goals_on_its_own(captures):
    """The rates over all rows let easy bench rows hide a hard row: each real-like row gets its own goal line, and a
    row that misses a goal says so even where the rows together meet it."""
    easy = [_row(i) for i in range(40)]
    hard = [_row(i, condition="hidden", confident=i >= 3, seconds=1.5) for i in range(10)]  # 3 of 10 right ones
    # unconfident, and slow
    hard += [_row(10, condition="hidden", right=False, confident=False, mssd=40.0, telling_px=5)]  # view cannot tell
    stacked = [dict(_row(i, condition="stacked"), final_iou=0.95) for i in range(5)]
    lines = captures.row_goals({"kinect": easy, "hidden": hard, "stacked": stacked})
    assert len(lines) == 2 and lines[0].startswith("goals (stacked, 5 of 5 ") and lines[1].startswith("goals (hidden, 10 of 11 ")
    assert "MISSED" not in lines[0] and "mask IoU 0.950 met" in lines[0]
    assert "unconfident-and-right 30.0% MISSED" in lines[1] and "confident-and-wrong 0 met" in lines[1]
    assert "recall 1.000 met" in lines[1]  # the frame the view cannot tell is left out of the recall
    assert "median 0.200 s/frame met" in lines[0] and "median 1.500 s/frame MISSED" in lines[1]  # each row's own time
    together = captures.goal_counts(easy + hard)
    assert together[1] <= 0.10  # ... which the rates over all rows would have let pass
    wrong = captures.row_goals({"real": [_row(0, condition="real", right=False, mssd=30.0)]})
    assert wrong == ["goals (real, 1 of 1 frames whose view can tell): confident-and-wrong 1 MISSED, "
                     "unconfident-and-right 0.0% met, recall 0.000 MISSED, median 0.200 s/frame met"]


def test_a_twin_is_fitted_where_the_view_would_place_it(captures):
    """telling_pixels tries each twin of the base also as the view would fit it (`fitted_twin`, an ICP of the
    benchmark's own): a half turn that a base's self-map shifts 3 mm along its length (the hole punch's) lies off
    what the camera sees of a box-like base, and the twin moved onto it lies on it, still turned half round."""
    import numpy as np
    import trimesh

    from apose_studio.geometry import se3

    box = trimesh.creation.box((0.12, 0.05, 0.04))
    samples = np.asarray(trimesh.sample.sample_surface_even(box, 20000, seed=1)[0])
    T_truth = se3.make_T(se3.axis_angle_matrix([0.0, 0.0, 1.0], 0.4), np.array([0.1, -0.05, 0.6]))
    seen = samples[(samples[:, 2] > 0.0199) | (samples[:, 0] > 0.0599)]  # its top and one end, as a camera sees them
    points = se3.transform_points(T_truth, seen)
    S = se3.make_T(se3.axis_angle_matrix([0.0, 0.0, 1.0], np.pi), np.array([0.003, 0.0, 0.0]))
    raw = T_truth @ S

    def off(T):  # mean distance of the seen points to the surface at T (mm)
        from scipy.spatial import cKDTree
        return 1000 * float(np.mean(cKDTree(se3.transform_points(T, samples)).query(points)[0]))

    fitted = captures.fitted_twin(raw, points, samples)
    assert off(raw) > 1.0 and off(fitted) < 0.5, (off(raw), off(fitted))
    turn = se3.inv(T_truth) @ fitted
    assert se3.rotation_angle_deg(turn[:3, :3]) > 179.0  # still the twin, not fitted back onto the truth
    assert captures.fitted_twin(raw, points[:2], samples) is raw  # too few points: the twin as it is
