"""What a result says about itself, worked out by hand: `fits`, `confident` and `doubts` at their
thresholds (coverage 80 %, contradiction 5 %, a search cut short, ambiguity), `seconds`, `failed`,
the frozen result, and View.of."""

import dataclasses

import numpy as np
import pytest

from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.registration.types import (
    CONFIDENT_CONTRADICTION,
    CONFIDENT_COVERAGE,
    Candidate,
    RegistrationResult,
    View,
    doubts,
    failed,
)


def result(**kw) -> RegistrationResult:
    base = dict(ok=True, T_world_base=np.eye(4), T_world_part=np.eye(4), coverage=0.9, contradiction=0.0)
    return RegistrationResult(**{**base, **kw})


def test_the_thresholds_are_the_documented_ones():
    assert (CONFIDENT_COVERAGE, CONFIDENT_CONTRADICTION) == (0.80, 0.05)


def test_confident_at_and_around_each_threshold():
    assert result().fits and result().confident and doubts(result()) == ""
    assert result(coverage=0.80).confident  # at the floor: enough
    assert not result(coverage=0.7999).confident
    assert result(contradiction=0.05).confident  # at the ceiling: still little
    assert not result(contradiction=0.0501).confident
    assert result(contradiction=float("nan")).confident  # no model view to contradict: not held against it
    assert not result(coverage=float("nan")).confident  # unknown coverage never is
    assert not result(out_of_time="the upright search").confident
    amb = result(ambiguous=True)
    assert amb.fits and not amb.confident  # every placement of an ambiguous result may fit
    assert not result(ok=False).fits and not result(ok=False).confident


def test_doubts_say_every_reason_in_words():
    assert doubts(result(coverage=0.5)) == "only 50% of the target lies near the model"
    assert doubts(result(coverage=float("nan"))) == "how much of the target the model explains is unknown"
    assert doubts(result(contradiction=0.2)) == "the depth contradicts 20% of what the model shows"
    assert doubts(result(out_of_time="the free search")) == "the time budget cut short the free search"
    alt = Candidate(np.eye(4), np.eye(4), 0.9, 0.9, 0.001, 0.9, 1)
    assert doubts(result(ambiguous=True, alternatives=[alt, alt])) == "3 placements fit the data equally (ambiguous)"
    both = doubts(result(coverage=0.5, contradiction=0.2, out_of_time="x", ambiguous=True))
    assert both.count("; ") == 3 and both.startswith("only 50%") and both.endswith("(ambiguous)")
    assert doubts(failed("empty mask")) == ""  # a failure has a reason, not doubts


def test_failed_seconds_and_frozen():
    f = failed("empty mask", preset="default", timings={"proj3d": 0.25, "features": 0.5})
    assert (f.ok, f.reason, f.preset, f.confident) == (False, "empty mask", "default", False)
    assert f.seconds == pytest.approx(0.75) and failed("x").seconds == 0.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        f.ok = True
    with pytest.raises(TypeError):
        RegistrationResult(True, "positional")  # built by keyword only


def test_view_of_a_frame():
    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 32.0, 24.0)

    class F:
        depth, camera, T_world_camera, im_id = np.ones((48, 64)), cam, np.eye(4), 7
        source = ""

    mask = np.zeros((48, 64), bool)
    v = View.of(F, mask)
    assert v.depth is F.depth and v.mask is mask and v.camera == cam and v.name == "frame 7"
    F.source = "capture/a"
    assert View.of(F, mask).name == "capture/a"


def test_doubts_at_a_threshold_name_only_what_is_past_it():
    """Exactly at the coverage floor or the contradiction ceiling is not a doubt, even when another is."""
    assert doubts(result(coverage=0.80, contradiction=0.2)) == "the depth contradicts 20% of what the model shows"
    assert doubts(result(coverage=0.5, contradiction=0.05)) == "only 50% of the target lies near the model"


def test_what_a_failure_reports_besides_its_reason():
    """`apose estimate --json` prints these for a failed frame: nothing measured, one view, empty clouds."""
    from apose_studio.registration.types import Found, Observation, Start

    f = failed("empty mask")
    assert (f.fitness, f.inlier_rmse, f.voxel, f.depth_noise, f.views, f.problem) == (0.0, 0.0, 0.0, 0.0, 1, None)
    assert f.target_cloud.shape == (0, 3) and f.source_cloud.shape == (0, 3) and f.stages == [] and f.timings == {}
    assert np.isnan(f.coverage) and np.isnan(f.contradiction) and f.out_of_time == "" and f.model_mask is None
    assert Observation(None, None, None).noise == 0.0
    s = Start(0.5, 0, np.eye(4), np.eye(4))
    found = Found([s])
    assert found.twins == [] and found.upright is False


def test_a_view_is_frozen():
    v = View(np.ones((2, 2)), np.ones((2, 2), bool), CameraIntrinsics(2, 2, 1.0, 1.0, 1.0, 1.0), np.eye(4))
    with pytest.raises(dataclasses.FrozenInstanceError):
        v.mask = None


def test_a_pose_is_held_to_the_part_it_places():
    """The spread a confident result may have is the smaller of the base's allowance and 5 % of the placed
    part's diameter: 4 mm of freedom passes a 112 mm base (6.7 mm) but not a 70 mm label (3.5 mm)."""
    from types import SimpleNamespace

    from apose_studio.estimation import held_to_part

    r = result(spread=0.004, spread_allowed=0.06 * 0.112)
    assert r.confident
    small = held_to_part(r, SimpleNamespace(diameter=0.070))
    assert not small.confident and small.spread_allowed == pytest.approx(0.0035)
    assert "free to move by 4.0 mm, more than the 3.5 mm the placement allows" in doubts(small)
    assert held_to_part(r, SimpleNamespace(diameter=0.100)).confident  # 5 mm allowed: the base's 6.7 mm is not loosened
    assert held_to_part(r, SimpleNamespace(diameter=1.0)).spread_allowed == pytest.approx(0.06 * 0.112)
    bad = failed("no depth")
    assert held_to_part(bad, SimpleNamespace(diameter=0.070)) is bad
