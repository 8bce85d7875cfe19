"""Tracking through a rendered trajectory (`apose render --trajectory`): every tracked pose checked against the
renderer's truth (MSSD, tests/conftest.mssd_to_truth), a base that vanishes is lost and not reported, a wrong
starting pose is not carried on as confident, and the answers repeat to the bit."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from apose_studio.assembly.model import load_assembly
from apose_studio.data.dataset import Dataset
from apose_studio.errors import RenderError
from apose_studio.estimation import Tracker, estimate_frame, step_context
from apose_studio.geometry import se3
from apose_studio.params import resolve_params
from apose_studio.registration.track import moved_by, track
from apose_studio.synth.frame import RenderSettings
from apose_studio.synth.render import render_dataset
from tests.conftest import SAMPLES, mssd_to_truth

GEARBOX = SAMPLES / "helical_gearbox" / "assembly.yaml"
FRAMES = 10


@pytest.fixture(scope="module")
def trajectory(tmp_path_factory):
    """Ten frames of gearbox step 2 seen by a camera closing in over a cluttered, Kinect-like bench."""
    out = tmp_path_factory.mktemp("traj") / "ds"
    render_dataset(load_assembly(GEARBOX), out, RenderSettings(frames=FRAMES, trajectory="approach", noise="kinect",
                                                               clutter=("bench",), seed=4), steps=[2], progress=False)
    return Dataset(out)


def _tracker(ds):
    asm, ctx = step_context(ds.assembly, 2)
    params = resolve_params("default", asm.registration)
    return Tracker(ctx, params, lambda frame, box: estimate_frame(frame, ctx, params, "gt")), ctx, params


def test_a_trajectory_is_one_placement_seen_by_a_camera_moving_smoothly(trajectory):
    frames = [trajectory.frame(2, i) for i in range(FRAMES)]
    assert len(trajectory.placements(2)) == 1  # one placement: the frames are views of one scene
    for a, b in zip(frames, frames[1:]):
        np.testing.assert_allclose(a.T_world_part, b.T_world_part, atol=1e-9)  # the base stays put
        step = np.linalg.norm(a.T_world_camera[:3, 3] - b.T_world_camera[:3, 3])
        reach = np.linalg.norm(a.T_world_camera[:3, 3] - a.T_world_part[:3, 3])
        assert 0 < step < 0.2 * reach, (step, reach)  # moves, by a little of its distance per frame (10 frames)
    d0 = np.linalg.norm(frames[0].T_world_camera[:3, 3] - frames[0].T_world_part[:3, 3])
    d1 = np.linalg.norm(frames[-1].T_world_camera[:3, 3] - frames[-1].T_world_part[:3, 3])
    assert d1 < 0.8 * d0  # an approach closes in


def test_render_refuses_a_trajectory_with_views_per_scene_or_hidden_clutter():
    with pytest.raises(RenderError, match="--views-per-scene"):
        RenderSettings(frames=4, trajectory="approach", views_per_scene=2).validate()
    with pytest.raises(RenderError, match="hidden"):
        RenderSettings(frames=4, trajectory="orbit", clutter=("hidden",)).validate()
    with pytest.raises(RenderError, match="--trajectory spiral"):
        RenderSettings(frames=4, trajectory="spiral").validate()


def test_every_frame_after_the_first_is_tracked_and_right(trajectory):
    tracker, ctx, _ = _tracker(trajectory)
    steps = [tracker.step(trajectory.frame(2, i)) for i in range(FRAMES)]
    assert [s.mode for s in steps] == ["detected"] + ["tracked"] * (FRAMES - 1)
    diameter = ctx.part.diameter
    for s in steps:
        frame = trajectory.frame(2, s.im_id)
        assert s.result.confident and s.result.tracked == (s.mode == "tracked")
        err = mssd_to_truth(s.result.T_world_part, frame.T_world_part, GEARBOX, ctx.view.part)
        assert err < 0.1 * diameter, (s.im_id, err)  # right, as the paper counts it


def test_a_tracked_frame_is_as_accurate_as_its_own_estimate(trajectory):
    """Issue #30: the error no worse than per-frame estimation. Each tracked frame's pose against the truth
    (mssd_to_truth: the renderer's pose, not the tracker's judge) is within 0.15 mm of what the frame's own
    estimate with a box prompt gets. The far frames of this approach had been 1.2-2.5 mm off against
    0.15-0.55 mm: the table cut kept the points that the Kinect-like noise lifted, and the whole model's
    hidden faces drew the casing towards the camera."""
    tracker, ctx, params = _tracker(trajectory)
    for i in range(FRAMES):
        frame = trajectory.frame(2, i)
        s = tracker.step(frame)
        if s.mode != "tracked":
            continue
        own = estimate_frame(frame, ctx, params, "box")
        tracked = mssd_to_truth(s.result.T_world_part, frame.T_world_part, GEARBOX, ctx.view.part)
        alone = mssd_to_truth(own.T_world_part, frame.T_world_part, GEARBOX, ctx.view.part)
        assert tracked < alone + 1.5e-4, (i, tracked, alone)


def test_tracking_repeats_to_the_bit(trajectory):
    runs = []
    for _ in range(2):
        tracker, _, _ = _tracker(trajectory)
        runs.append([tracker.step(trajectory.frame(2, i)).result.T_world_base for i in range(4)])
    for a, b in zip(*runs):
        assert np.array_equal(a, b)


def test_a_base_that_vanishes_is_lost_not_reported_and_found_again(trajectory):
    tracker, ctx, _ = _tracker(trajectory)
    tracker.step(trajectory.frame(2, 0))
    blank = trajectory.frame(2, 1)
    gone = blank.base_mask()
    depth = blank.depth.copy()
    depth[gone] = 0.0  # no depth where the base was: a dark, shiny base, or the camera looks away
    s = tracker.step(replace(blank, depth=depth))
    assert s.mode in ("lost", "re-detected") and s.lost_because
    assert not (s.result.confident and mssd_to_truth(s.result.T_world_part, blank.T_world_part, GEARBOX,
                                                     ctx.view.part) > 0.1 * ctx.part.diameter)
    after = tracker.step(trajectory.frame(2, 2))
    assert after.result.confident and after.mode in ("detected", "tracked")


@pytest.mark.parametrize("how", ["turned", "shifted"])
def test_a_wrong_start_is_not_carried_on_as_confident(trajectory, how):
    """No silent drift: started from a pose that is off, tracking either finds the truth again or says it is
    lost; it never reports the wrong pose as confident."""
    _, ctx, params = _tracker(trajectory)
    first = estimate_frame(trajectory.frame(2, 0), ctx, params, "gt")
    assert first.confident
    c = se3.transform_points(first.T_world_base, ctx.base.centre[None])[0]
    if how == "turned":  # a quarter turn about the vertical through the base's centre
        R = se3.axis_angle_matrix(np.array([0.0, 0.0, 1.0]), np.pi / 2)
        off = se3.make_T(R, c - R @ c)
    else:  # moved sideways by a third of the base's size
        off = se3.make_T(t=np.array([ctx.base.diameter / 3, 0.0, 0.0]))
    wrong = replace(first, T_world_base=off @ first.T_world_base)
    frame = trajectory.frame(2, 1)
    r = track(frame.depth, frame.camera, frame.T_world_camera, ctx.base, ctx.view.T_base_part, params, wrong,
              first.problem.table)
    err = mssd_to_truth(r.T_world_base @ ctx.view.T_base_part, frame.T_world_part, GEARBOX, ctx.view.part) \
        if r.ok else np.inf
    assert not r.confident or err < 0.1 * ctx.part.diameter, (r.confident, err)


def test_apose_track_on_a_rendered_trajectory(tmp_path):
    ds = tmp_path / "ds"
    run = [sys.executable, "-m", "apose_studio.cli"]
    subprocess.run(run + ["render", str(GEARBOX), "--out", str(ds), "--frames", "5", "--trajectory", "--steps", "1",
                          "--noise", "realsense", "-q"], check=True, capture_output=True)
    info = json.loads((ds / "dataset_info.json").read_text())
    assert info["settings"]["trajectory"] == "approach"
    out = tmp_path / "track.json"
    p = subprocess.run(run + ["track", str(ds), "--step", "1", "--json", str(out)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "5 frames: 1 detected, 4 tracked" in p.stdout and "0 confident and wrong" in p.stdout
    doc = json.loads(out.read_text())
    assert [f["mode"] for f in doc["frames"]] == ["detected"] + ["tracked"] * 4
    assert doc["summary"]["right"] == 5
    bad = subprocess.run(run + ["track", str(ds), "--step", "3"], capture_output=True, text=True)
    assert bad.returncode == 2 and "step 3" in bad.stderr and "Traceback" not in bad.stderr


def test_a_camera_without_poses_never_tracks_onto_a_stale_table(tmp_path):
    """A live camera without the robot's kinematics: every frame's world is the camera's own, so the table found
    when the base was detected moves with the camera. Kept as it was, it cut the wrong depth and let a pose sunk
    22 mm into the real table pass as resting on it (confident, 31 mm off on frame 15 of this approach, every
    other frame read); `table_now` checks it against the depth around the base and fits it anew."""
    out = tmp_path / "ds"
    render_dataset(load_assembly(GEARBOX), out, RenderSettings(frames=20, trajectory="approach", noise="realsense",
                                                               clutter=("bench",), seed=2), steps=[2], progress=False)
    ds = Dataset(out)
    tracker, ctx, _ = _tracker(ds)
    for im_id in [0, *range(1, 20, 2)]:
        fr = ds.frame(2, im_id)
        s = tracker.step(replace(fr, T_world_camera=np.eye(4)))  # no pose: the world is this camera's frame
        truth = se3.inv(fr.T_world_camera) @ fr.T_world_part
        err = mssd_to_truth(s.result.T_world_part, truth, GEARBOX, fr.part)
        assert not (s.result.confident and err > 0.1 * ctx.part.diameter), (im_id, s.mode, err)
    assert "tracked" in [s.mode for s in tracker.steps]


def test_an_ambiguous_frame_is_fused_with_the_next_one_seen_from_where_it_advised():
    """Planetary step 3 (the carrier on a nearly symmetric housing) on a cluttered Kinect-like bench: the first
    frame fits two placements alike, so nothing is tracked and the step carries the advice (where to look from);
    the same frame again is not from there (not fused); a frame rendered from the advised camera is, and the two
    estimated together are confident and right. Truth from the renderer, not from the tracker."""
    from apose_studio.assembly.mesh import base_mesh, load_parts
    from apose_studio.data.dataset import Frame
    from apose_studio.estimation import array_mask, truth_box
    from apose_studio.geometry.raycast import RayGrid
    from apose_studio.synth.frame import render_frame, view_of

    path = SAMPLES / "planetary_reducer" / "assembly.yaml"
    asm = load_assembly(path)
    models, view = load_parts(asm), asm.step_view(3)
    s = RenderSettings(frames=1, noise="kinect", clutter=("bench",), seed=0)
    grid = RayGrid(s.camera)

    def frame_of(rf, im_id):
        masks = {o.part: rf.labels == i for i, o in enumerate(rf.scene.objects) if o.part in view.T_base_members}
        Tb = rf.scene.T_world_base
        return Frame(rgb=rf.rgb, depth=rf.depth, camera=s.camera, T_world_camera=rf.T_world_camera, masks=masks,
                     step=3, part=view.part, base=tuple(view.base), T_base_part=view.T_base_part, T_world_base=Tb,
                     T_world_part=Tb @ view.T_base_part, im_id=im_id)

    rf = render_frame(models, view, s, grid, np.random.default_rng([3, 3, 0]), base_mesh(models, view))
    first = frame_of(rf, 0)
    _, ctx = step_context(asm, 3)
    params = resolve_params("default", asm.registration)

    def detect(frame, box):  # the user's box around the base (the truth's visible box)
        box = truth_box(frame.base_mask())
        return estimate_frame(frame, ctx, params, mask=array_mask(frame.rgb, frame.depth, frame.camera, box=box)[0],
                              box=box)

    tracker = Tracker(ctx, params, detect)
    s0 = tracker.step(first)
    assert s0.mode == "not found" and s0.result.ambiguous and s0.advice is not None
    again = tracker.step(replace(first, im_id=1))
    assert again.mode == "not found"  # the same camera: nothing new to fuse
    there = frame_of(view_of(rf.scene, s0.advice.T_world_camera, grid, np.random.default_rng([3, 9]), s), 2)
    s2 = tracker.step(there)
    assert s2.mode == "fused" and s2.result.confident and s2.result.views == 2, (s2.mode, s2.result.reason)
    assert mssd_to_truth(s2.result.T_world_part, there.T_world_part, path, view.part) < 0.1 * ctx.part.diameter
    assert tracker.step(replace(there, im_id=3)).mode == "tracked"  # and tracked from the fused pose


def test_a_base_filling_the_view_is_judged_at_half_resolution_with_the_same_pose(trajectory, monkeypatch):
    """Where the base covers more than FULL_RES_PX pixels, the model is cast and the pose judged on every other
    pixel (the depth registered is the full image's): the same pose within a tenth of a millimetre, the same
    verdict, the mask at the frame's size and mostly the full-resolution judge's."""
    from apose_studio.registration import track as track_module

    tracker, ctx, params = _tracker(trajectory)
    first = tracker.step(trajectory.frame(2, FRAMES - 2))
    frame = trajectory.frame(2, FRAMES - 1)
    pred = track_module.predict(first.result, frame.T_world_camera, frame.camera)
    assert np.isfinite(pred.zbuf).sum() > track_module.FULL_RES_PX  # the closest frame: the base fills the view
    half = track(frame.depth, frame.camera, frame.T_world_camera, ctx.base, ctx.view.T_base_part, params, first.result)
    monkeypatch.setattr(track_module, "FULL_RES_PX", 10 ** 9)
    full = track(frame.depth, frame.camera, frame.T_world_camera, ctx.base, ctx.view.T_base_part, params, first.result)
    assert moved_by(ctx.base, half.T_world_base, full.T_world_base) < 1e-4
    assert half.confident and full.confident and abs(half.coverage - full.coverage) < 0.02
    assert half.model_mask.shape == full.model_mask.shape == frame.depth.shape
    iou = (half.model_mask & full.model_mask).sum() / (half.model_mask | full.model_mask).sum()
    assert iou > 0.75, iou  # the casing's thin walls: pixels of Kinect-like depth agree or not one by one
    assert len(half.source_cloud) < 0.4 * len(full.source_cloud)  # judged on a quarter of the pixels


def test_hidden_points_are_those_something_stands_over_not_those_the_model_hides_itself():
    """registration.track.hidden_points on a 10 cm cube 0.5 m in front of the camera: with a plate 2 cm above its
    left half, the points under the plate; none where the depth is the cube's own (noise within the tolerance);
    and the far faces of a source that another camera saw (a fused result's) are not taken for hidden behind the
    cube's own front face."""
    import trimesh

    from apose_studio.geometry.camera import CameraIntrinsics
    from apose_studio.geometry.raycast import raycast_depth, raycast_points
    from apose_studio.registration.track import hidden_points
    from apose_studio.registration.types import RegistrationResult

    cam = CameraIntrinsics(160, 120, 150.0, 150.0, 80.0, 60.0)
    cube = trimesh.creation.box((0.1, 0.1, 0.1))
    T_world_base = np.eye(4)
    T_world_base[:3, 3] = (0.0, 0.0, 0.5)
    seen, _ = raycast_points(cube, T_world_base, np.eye(4), cam)
    depth = raycast_depth(cube, T_world_base, np.eye(4), cam).astype(np.float32)
    depth[~np.isfinite(depth)] = 0
    result = RegistrationResult(ok=True, T_world_base=T_world_base, source_cloud=seen - T_world_base[:3, 3])
    rng = np.random.default_rng(0)
    noisy = np.where(depth > 0, depth + rng.normal(0, 0.001, depth.shape).astype(np.float32), 0)
    assert len(hidden_points(result, noisy, cam, np.eye(4), 0.005)) == 0
    plate = depth.copy()
    plate[:, :80][plate[:, :80] > 0] -= 0.02  # something 2 cm nearer over the cube's left half
    hidden = hidden_points(result, plate, cam, np.eye(4), 0.005)
    xs = hidden[:, 0]
    assert len(hidden) > 0.3 * len(seen) and (xs <= 0.001).all(), (len(hidden), len(seen), xs.max())
    back = np.concatenate([result.source_cloud, result.source_cloud * np.array([1.0, 1.0, -1.0])])  # + the far face
    assert len(hidden_points(replace(result, source_cloud=back), noisy, cam, np.eye(4), 0.005)) == 0
