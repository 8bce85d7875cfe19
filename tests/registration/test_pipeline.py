"""The whole estimate: poses recovered, degenerate and unit-error input refused with a reason, symmetric seats reported."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from apose_studio.assembly.mesh import load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.geometry import se3
from apose_studio.geometry.metrics import mssd
from apose_studio.registration import estimate, prepare_base, resolve_params
from apose_studio.registration.types import View

from ..conftest import SAMPLES
from .conftest import CAM, synthetic_view


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_pose_recovered_with_the_cad_orientation_known(gearbox_step2, preset):
    view, base, models = gearbox_step2
    T_world_base = se3.make_T(np.eye(3), [0.05, 0.02, 0.0])  # the paper's protocol: orientation as in the CAD
    T_world_camera = se3.look_at([0.35, -0.25, 0.3], [0.05, 0.02, 0.01])
    depth, mask = synthetic_view(base, T_world_base, T_world_camera)
    p = resolve_params(preset, use_orientation_prior=True)
    r = estimate(View(depth, mask, CAM, T_world_camera), base, view.T_base_part, p, prior_T_world_base=np.eye(4))
    assert r.ok, r.reason
    part = models[view.part]
    err = mssd(r.T_world_part, T_world_base @ view.T_base_part, part.samples, part.symmetries)
    assert err < 1e-3, err
    # the trace replays: initial, global (or, ours, the prior's start), ICP iterations, final (= the result)
    names = [s.name for s in r.stages]
    assert names[0] == "initial" and names[-1] == "final" and len(names) >= 4
    if preset == "default":  # the prior fits, so ours stops there without a global search
        assert names[1] == "prior" and set(r.timings) >= {"proj3d", "prior"} and "global" not in r.timings
    else:
        assert names[1] == "global" and set(r.timings) >= {"proj3d", "global", "icp"}
    np.testing.assert_allclose(r.stages[-1].T_world_base, r.T_world_base)
    assert r.fitness > 0.95 and r.inlier_rmse < r.voxel
    assert len(r.target_cloud) > 100 and len(r.source_cloud) > 100


def test_degenerate_inputs_fail_with_reasons(gearbox_step2):
    view, base, _ = gearbox_step2
    p = resolve_params("default")
    T_wc = se3.look_at([0.3, 0, 0.3], [0, 0, 0])
    depth = np.full((480, 640), 0.4, np.float32)
    empty = np.zeros((480, 640), bool)
    r = estimate(View(depth, empty, CAM, T_wc), base, view.T_base_part, p)
    assert not r.ok and "empty mask" in r.reason
    few = empty.copy()
    few[100, 100:102] = True
    r = estimate(View(depth, few, CAM, T_wc), base, view.T_base_part, p)
    assert not r.ok and "only 2 valid depth points" in r.reason
    nan_depth = np.full((480, 640), np.nan, np.float32)
    r = estimate(View(nan_depth, ~empty, CAM, T_wc), base, view.T_base_part, p)
    assert not r.ok and "only 0 valid depth points" in r.reason
    line = empty.copy()
    line[240, 100:500] = True  # a single row of pixels on a plane: a line in 3D
    r = estimate(View(depth, line, CAM, T_wc), base, view.T_base_part, p)
    assert not r.ok and "degenerate" in r.reason
    # a 4 cm blob of depth for a 0.35 mm base: a unit error, said as one (the paper preset would not
    # even see the mesh)
    speck = prepare_base(trimesh.creation.box((0.0002, 0.0002, 0.0002)), n_samples=500)
    blob = empty.copy()
    blob[200:260, 300:360] = True
    r = estimate(View(depth, blob, CAM, T_wc), speck, view.T_base_part, resolve_params("paper"))
    assert not r.ok and "depth looks about 100x too far" in r.reason


def test_unit_errors_in_depth_are_named(gearbox_step2):
    """depth_scale 10x or 1000x off: the target cannot be the base object; the reason says by how much."""
    from apose_studio.registration import scale_problem

    view, base, _ = gearbox_step2
    pts = base.samples[base.samples[:, 2] > base.centre[2]]  # the upper half of the base: what a camera sees
    assert scale_problem(pts, base.diameter) is None
    assert "about 10x too far" in scale_problem(pts * 10, base.diameter)
    assert "about 1000x too far" in scale_problem(pts * 1000, base.diameter)
    assert "about 100x too near" in scale_problem(pts / 100, base.diameter)


def test_a_symmetric_base_reports_both_seats(fidget_yaml, tmp_path):
    """The fidget's bottom casing is exactly 2-fold symmetric: from it alone the left gear's two seats
    cannot be told apart, and need not be, since both give the same assembly. Each result is not
    `ambiguous` (that is for near-symmetric twins, which are wrong placements), gives the other seat (23
    mm away, half a turn) as its one `equivalent` placement, and the truth is the estimate or that one;
    the metric that forgives exact twins scores it right, the strict one need not."""
    from apose_studio.data.dataset import Dataset
    from apose_studio.estimation import StepContext, estimate_frame
    from apose_studio.evaluate import score_frame
    from apose_studio.registration import RegistrationResult
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    asm = load_assembly(fidget_yaml)
    render_dataset(asm, tmp_path / "ds", RenderSettings(frames=3, seed=11, base_pose="yaw"), steps=[1], progress=False)
    ds = Dataset(tmp_path / "ds")
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 1)
    for im_id in ds.image_ids(1):
        fr = ds.frame(1, im_id)
        r = estimate_frame(fr, ctx, resolve_params("default"))
        assert r.ok and not r.ambiguous and not r.alternatives and len(r.equivalent) == 1, (im_id, r.ambiguous)
        alt = r.equivalent[0]
        assert 0.015 < np.linalg.norm(alt[:3, 3] - r.T_world_part[:3, 3]) < 0.03
        errs = [mssd(T, fr.T_world_part, ctx.part.samples, ctx.part.symmetries) for T in (r.T_world_part, alt)]
        assert min(errs) < 1e-3, errs
        sc = score_frame(fr, r, ctx.part, base_symmetries=ctx.base.symmetries)
        assert sc.mssd_mod_base_sym < 1e-3 and sc.mssd == pytest.approx(errs[0])
        # scored by hand: the truth itself moved 10 mm along x, as if estimated so. Every point moves 10 mm, so
        # te = MSSD = 10 mm and the rotation error 0; the seat's twin (23 mm away, half a turn) is no nearer
        shifted = RegistrationResult(ok=True, T_world_part=se3.make_T(t=[0.01, 0, 0]) @ fr.T_world_part)
        sc = score_frame(fr, shifted, ctx.part, base_symmetries=ctx.base.symmetries)
        assert sc.te == pytest.approx(0.01) and sc.re_deg == pytest.approx(0.0, abs=1e-6)
        assert sc.mssd == pytest.approx(0.01) and sc.mssd_mod_base_sym == pytest.approx(0.01)



def test_junk_is_never_a_confident_pose(gearbox_dataset):
    """A box on empty table, the wrong object, 40 points of noise: ok=False or not confident, every time."""
    from apose_studio.data.dataset import Dataset
    from apose_studio.estimation import StepContext

    ds = Dataset(gearbox_dataset)
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 1)
    p = resolve_params("default")
    for im in ds.image_ids(1):
        fr = ds.frame(1, im)
        anything = np.zeros(fr.depth.shape, bool)
        for m in fr.masks.values():
            anything |= m
        vs, us = np.nonzero(anything)
        table = np.zeros_like(anything)
        table[20:80, 20:80] = True  # a corner of the image: table, far from every object
        assert not (table & anything).any() and (fr.depth[table] > 0).mean() > 0.9
        rng = np.random.default_rng(im)
        noise_depth = np.zeros_like(fr.depth)
        noise_mask = np.zeros_like(anything)
        v, u = rng.integers(0, fr.depth.shape[0], 40), rng.integers(0, fr.depth.shape[1], 40)
        noise_depth[v, u], noise_mask[v, u] = rng.uniform(0.3, 0.8, 40), True
        cases = {"empty table": (fr.depth, table), "the part lying beside it": (fr.depth, fr.masks[ctx.view.part]),
                 "40 points of noise": (noise_depth, noise_mask)}
        for what, (depth, mask) in cases.items():
            r = estimate(View(depth, mask, fr.camera, fr.T_world_camera), ctx.base, ctx.view.T_base_part, p)
            assert not (r.ok and r.confident), (what, im, r.coverage, r.reason)


class FakeClock:
    """Stands in for `time` in the estimator's modules: perf_counter() starts at 100 s and moves `step`
    seconds at each call (0: time stands still; 10: every check after the first is past a 1 s budget)."""

    def __init__(self, step: float):
        self.now, self.step = 100.0, step

    def perf_counter(self) -> float:
        self.now += self.step
        return self.now - self.step


def test_the_time_budget_through_a_fake_clock(gearbox_dataset, monkeypatch):
    """A wall-clock limit (params.max_seconds, off by default) is read from the clock: set to 1 s, with time
    standing still nothing is cut and every timing is 0; with each reading 10 s after the last, the searches
    stop after the first start, say what they cut, and the pose stays but is not confident. The default
    (no limit) under the same racing clock cuts nothing and gives the very pose of the still clock: the
    answer does not depend on how fast the machine runs. Timing itself is measured in benchmarks/."""
    from dataclasses import replace

    from apose_studio.data.dataset import Dataset
    from apose_studio.estimation import StepContext
    from apose_studio.registration import pipeline, task
    from apose_studio.registration.types import doubts

    ds = Dataset(gearbox_dataset)
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 1)
    fr = ds.frame(1, 0)
    default = resolve_params("default")
    assert default.max_seconds == 0.0
    p = replace(default, max_seconds=1.0)

    def run(step, params):
        clock = FakeClock(step)
        monkeypatch.setattr(pipeline, "time", clock)
        monkeypatch.setattr(task, "time", clock)
        return estimate(View(fr.depth, fr.base_mask(), fr.camera, fr.T_world_camera), ctx.base, ctx.view.T_base_part, params)

    still = run(0.0, p)
    assert still.ok and still.confident and still.out_of_time == "" and still.seconds == 0.0
    assert mssd(still.T_world_part, fr.T_world_part, ctx.part.samples, ctx.part.symmetries) < 1e-3
    racing = run(10.0, p)
    assert racing.ok and not racing.confident and racing.out_of_time == "refining the other starting poses"
    assert "the time budget cut short refining the other starting poses" in doubts(racing)
    assert racing.seconds >= 10.0  # the timings are the fake clock's
    unlimited = run(10.0, default)
    assert unlimited.out_of_time == "" and unlimited.confident
    assert np.array_equal(unlimited.T_world_part, run(0.0, default).T_world_part)  # bit for bit, whatever the clock
    assert np.array_equal(unlimited.T_world_part, still.T_world_part)


def test_out_of_time_notes_once_from_the_deadline_on():
    from types import SimpleNamespace

    from apose_studio.registration import task
    from apose_studio.registration.task import Task

    clock = FakeClock(0.0)
    pb = SimpleNamespace(deadline=105.0, notes=[])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(task, "time", clock)
        assert not Task.out_of_time(pb, "a") and pb.notes == []  # 100 s: before the deadline
        clock.now = 105.0  # at the deadline: out of time
        assert Task.out_of_time(pb, "a") and Task.out_of_time(pb, "a") and Task.out_of_time(pb, "b")
    assert pb.notes == ["a", "b"]


PLANE = np.stack(np.meshgrid(np.linspace(-0.01, 0.01, 5), np.linspace(-0.01, 0.01, 5), [0.0]), -1).reshape(-1, 3)


def judged_result(base, t, fitness=0.9, coverage=0.95, seen_world=None, voxel=0.002, target=None):
    """A registration result for judge(): the base's centre at t (world = camera frame, looking along +z);
    what the model shows there `seen_world` (default: a 2 cm square at z = 0.5 m, the image's centre)."""
    from apose_studio.registration import Candidate, RegistrationResult

    T = se3.make_T(t=np.asarray(t, float) - base.centre)
    c = Candidate(T, T, fitness, 0.9, 0.001, 0.9, 0, coverage)
    seen = PLANE + [0, 0, 0.5] if seen_world is None else np.asarray(seen_world, float).reshape(-1, 3)
    return RegistrationResult(ok=True, T_world_base=T, T_world_part=T, T_world_source=T, fitness=fitness, coverage=coverage, candidates=[c],
                              source_cloud=se3.transform_points(se3.inv(T), seen), voxel=voxel,
                              target_cloud=np.zeros((0, 3)) if target is None else target)


def test_a_pose_the_camera_cannot_have_seen_is_not_ok(gearbox_step2):
    """judge(): behind the camera, outside the image, beyond the farthest depth, or explaining nothing."""
    from apose_studio.registration import RegistrationResult
    from apose_studio.registration.pipeline import judge

    _, base, _ = gearbox_step2
    T_world_camera = np.eye(4)  # the camera at the origin, looking along +z
    depth = np.full((CAM.height, CAM.width), 0.5, np.float32)

    mask = np.zeros(depth.shape, bool)
    mask[200:280, 280:360] = True

    def result(t, seen_z=0.5, **kw):
        return judged_result(base, t, seen_world=PLANE + [0, 0, seen_z], **kw)

    r = judge(result([0, 0, 0.5]), View(depth, mask, CAM, T_world_camera), base)
    assert r.ok and r.contradiction == 0.0 and r.confident
    # just above the 5 % floor on either share: supported (ok), if not confident (coverage < 80 %)
    for kw in ({"fitness": 0.06}, {"coverage": 0.06}, {"fitness": 0.06, "coverage": 0.06}):
        r = judge(result([0, 0, 0.5], **kw), View(depth, mask, CAM, T_world_camera), base)
        assert r.ok and r.reason == "", (kw, r.reason)
    # the base's centre may lie outside the image by up to the base's size in pixels (fx d / z), no more:
    # at z = 0.5 m, 0.8 of that past each edge is ok, 1.2 is outside
    z, size_px = 0.5, CAM.fx * base.diameter / 0.5
    for k, ok in ((0.8, True), (1.2, False)):
        for u, v in ((CAM.width + k * size_px, CAM.cy), (-k * size_px, CAM.cy), (CAM.cx, CAM.height + k * size_px),
                     (CAM.cx, -k * size_px)):
            t = [(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z]
            r = judge(result(t), View(depth, mask, CAM, T_world_camera), base)
            assert r.ok == ok and (ok or "outside the image" in r.reason), (k, u, v, r.reason)
    # beyond the farthest depth (0.5 m) by more than the base's diameter: not seen; by less: ok
    assert judge(result([0, 0, 0.5 + 0.8 * base.diameter]), View(depth, mask, CAM, T_world_camera), base).ok
    r = judge(result([0, 0, 0.5 + 1.2 * base.diameter]), View(depth, mask, CAM, T_world_camera), base)
    assert not r.ok and "beyond the farthest depth" in r.reason
    # a failed result passes through untouched
    failed = RegistrationResult(ok=False, reason="empty mask: test")
    assert judge(failed, View(depth, mask, CAM, T_world_camera), base) is failed and failed.reason == "empty mask: test"
    for t, kw, why in [([0, 0, -0.5], {}, "behind the camera"), ([5.0, 0, 0.5], {}, "outside the image"),
                       ([0, 0, 3.0], {}, "beyond the farthest depth"),
                       ([0, 0, 0.5], {"fitness": 0.0, "coverage": 0.0}, "explains almost none of the target"),
                       ([0, 0, 0.5], {"fitness": 0.04}, "explains almost none of the target"),  # fitness alone
                       ([0, 0, 0.5], {"coverage": 0.04}, "explains almost none of the target"),  # coverage alone
                       ([0, 0, 0.5], {"seen_z": 0.3}, "the depth contradicts 100% of what the model shows")]:
        r = judge(result(t, **kw), View(depth, mask, CAM, T_world_camera), base)
        assert not r.ok and why in r.reason and "no pose is reported" in r.reason, (t, kw, r.reason)
        assert not r.confident


def test_judge_edges_by_hand(gearbox_step2):
    """judge()'s rules at their edges, each worked out by hand: the agreement tolerance (2 voxels of the finer
    of the preset's voxel and diameter / 50), the contradiction share, the 5 % floors, no depth, the
    farthest depth, and a coarse preset's coverage measured again on what the camera sees of the model."""
    from apose_studio.registration.pipeline import judge

    _, base, _ = gearbox_step2
    I4 = np.eye(4)
    depth = np.full((CAM.height, CAM.width), 0.5, np.float32)
    mask = np.zeros(depth.shape, bool)
    mask[200:280, 280:360] = True
    scale_voxel = base.diameter / 50
    assert scale_voxel > 0.002  # so the tolerance (no depth noise) is 2 x min(0.002, scale voxel) = 4 mm
    centre = [0, 0, 0.5]

    def j(result, d=depth):
        return judge(result, View(d, mask, CAM, I4), base)

    # the model's square in front of the depth by more than 4 mm (but less than 2 x the scale voxel): the camera
    # sees past all of it; by less than 4 mm: confirmed
    gap = 0.002 + scale_voxel  # between 2 x 0.002 and 2 x scale_voxel
    r = j(judged_result(base, centre, seen_world=PLANE + [0, 0, 0.5 - gap]))
    assert not r.ok and r.contradiction == 1.0 and "contradicts 100%" in r.reason
    r = j(judged_result(base, centre, seen_world=PLANE + [0, 0, 0.5 - 0.0035]))
    assert r.ok and r.contradiction == 0.0
    # one point, contradicted: 1 of 1; one confirmed and one contradicted: 1 of 2 = 50 %, not above the 50 % rule
    r = j(judged_result(base, centre, seen_world=[0, 0, 0.3]))
    assert not r.ok and r.contradiction == 1.0
    r = j(judged_result(base, centre, seen_world=[[0, 0, 0.5], [0.001, 0, 0.3]]))
    assert r.ok and r.contradiction == 0.5
    # nothing the model shows is in the image (all behind the camera): 0 of 0 is no contradiction
    r = j(judged_result(base, centre, seen_world=PLANE + [0, 0, -1.0]))
    assert r.ok and r.contradiction == 0.0
    # no model view at all: the contradiction stays unknown (NaN), the pose ok
    r = j(replace(judged_result(base, centre), source_cloud=np.zeros((0, 3))))
    assert r.ok and np.isnan(r.contradiction)
    # exactly at the 5 % floors: not below them, so ok
    assert j(judged_result(base, centre, fitness=0.05, coverage=0.05)).ok
    # the centre exactly in the camera's plane: behind it (not in front)
    r = j(judged_result(base, [0, 0, 0.0]))
    assert not r.ok and "behind the camera" in r.reason
    # no valid depth anywhere: nothing says the base is too far
    assert j(judged_result(base, [0, 0, 3.0]), np.zeros_like(depth)).ok
    # the farthest depth is the largest (a strip of wall at 1.5 m), not the typical one
    far = depth.copy()
    far[:10] = 1.5
    assert j(judged_result(base, [0, 0, 1.0]), far).ok
    assert "beyond the farthest depth" in j(judged_result(base, [0, 0, 1.5 + 1.2 * base.diameter]), far).reason

    # a coarse preset (voxel 1.5 x the scale voxel: above the 1.01 x switch): coverage is measured again, as
    # the share of target points within the tolerance (2 scale voxels) of what the camera sees of the model
    from apose_studio.registration.base import raycast_source

    T = se3.make_T(t=np.asarray(centre) - base.centre)
    seen, _ = raycast_source(base, T, I4, CAM)
    d_view, m_view = synthetic_view(base, T, I4)
    target = seen[::7][:400]
    assert len(target) == 400
    moved = target.copy()
    moved[:100] += [0, 0, 0.05]  # a quarter of the target 5 cm behind the model: unexplained
    for tgt, cover in ((target, 1.0), (moved, 0.75)):
        r = judge(judged_result(base, centre, coverage=0.3, seen_world=seen, voxel=1.5 * scale_voxel, target=tgt),
                  View(d_view, m_view, CAM, I4), base)
        assert r.ok and r.coverage == pytest.approx(cover), r.coverage
    r = judge(judged_result(base, centre, coverage=0.3, seen_world=seen, voxel=1.5 * scale_voxel, target=np.zeros((0, 3))),
              View(d_view, m_view, CAM, I4), base)
    assert r.ok and r.coverage == 0.3  # no target to measure: kept
    # a fine preset keeps the coverage it was given
    r = judge(judged_result(base, centre, coverage=0.3, seen_world=seen, voxel=0.9 * scale_voxel, target=moved),
              View(d_view, m_view, CAM, I4), base)
    assert r.coverage == 0.3


def test_the_paper_preset_is_not_confident_about_wrong_poses(tmp_path):
    """The paper keeps the CAD's orientation. On Kinect-like cluttered benches with the base at a random
    yaw (benchmarks/captures.py's gearbox frames of step 1) it lands off with most of the target within
    its 16 mm tolerance; judged at the scale-aware tolerance on what the camera sees of the model there,
    such poses are not confident (frame 3 was, before). Wrong = off by 0.1 x the part's diameter even
    modulo the base's exact symmetries (its half turn is the same assembly)."""
    from apose_studio.assembly.model import load_assembly
    from apose_studio.data.dataset import Dataset
    from apose_studio.estimation import StepContext, estimate_frame, frame_mask
    from apose_studio.evaluate import score_frame
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    render_dataset(asm, tmp_path / "ds", RenderSettings(frames=4, seed=5, noise="kinect", clutter=True), steps=[1],
                   progress=False)
    ds = Dataset(tmp_path / "ds")
    ctx = StepContext(asm, load_parts(asm), 1)
    wrong = 0
    for im_id in ds.image_ids(1):
        fr = ds.frame(1, im_id)
        r = estimate_frame(fr, ctx, resolve_params("paper"), mask=frame_mask(fr, "box"))
        sc = score_frame(fr, r, ctx.part, base_symmetries=ctx.base.symmetries)
        if r.ok and sc.mssd_mod_base_sym >= 0.1 * ctx.part.diameter:
            wrong += 1
            assert np.isfinite(r.coverage) and not r.confident, (im_id, r.coverage, r.contradiction)
    assert wrong >= 1  # the case this test is about: the paper's wrong fits


def _slab_beside_the_base(gearbox_dataset):
    """(step context, frame, view): the gearbox's first frame with a mask that took in a slab of table
    beside the base, to its right (0.6 of the base's width)."""
    from apose_studio.data.dataset import Dataset
    from apose_studio.estimation import StepContext

    ds = Dataset(gearbox_dataset)
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 1)
    fr = ds.frame(1, 0)
    truth = fr.base_mask()
    ys, xs = np.nonzero(truth)
    slab = np.zeros_like(truth)
    slab[ys.min():ys.max(), xs.max() + 1:xs.max() + 1 + int(0.6 * np.ptp(xs))] = True
    return ctx, fr, View(fr.depth, truth | slab, fr.camera, fr.T_world_camera)


def test_second_look_cuts_clutter_from_the_mask(gearbox_dataset):
    """A mask that took in a slab of table beside the base: the first estimate is right but not
    confident (a third of the target is unexplained); the second look, on the mask cut to the model's
    view at that pose, is confident, and its mask lies inside the given one."""
    from dataclasses import replace

    ctx, fr, view = _slab_beside_the_base(gearbox_dataset)
    p = resolve_params("default", mask_hypotheses=False)  # the second look alone (the mask's readings find it too)
    first = estimate(view, ctx.base, ctx.view.T_base_part, replace(p, second_look=False))
    r = estimate(view, ctx.base, ctx.view.T_base_part, p)
    d = ctx.part.diameter
    assert first.ok and not first.confident and mssd(first.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * d
    assert r.confident and r.second_look is not None and not (r.second_look & ~view.mask).any()
    assert mssd(r.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * d and "second look" in r.timings


def test_the_second_look_is_for_results_that_do_not_fit(gearbox_dataset, monkeypatch):
    """The second look cuts clutter out of a mask: it runs on a result that does not fit (the slab beside the base
    leaves a third of the target unexplained), and not on one that fits and is unconfident only because another
    placement fits as well (ambiguous): it explains most of its mask, and the cut seldom tells the twins apart."""
    from dataclasses import replace

    from apose_studio.registration import pipeline

    ctx, fr, slabbed = _slab_beside_the_base(gearbox_dataset)
    p = resolve_params("default", mask_hypotheses=False)
    looks = []
    second_look = pipeline.second_look
    monkeypatch.setattr(pipeline, "second_look", lambda r, *a, **k: looks.append(r) or second_look(r, *a, **k))
    judged = pipeline.judged
    clean = replace(slabbed, mask=fr.base_mask())
    monkeypatch.setattr(pipeline, "judged", lambda r, *a, **k: replace(judged(r, *a, **k), ambiguous=True))
    r = estimate(clean, ctx.base, ctx.view.T_base_part, p)
    assert r.ok and r.fits and r.ambiguous and not r.confident and looks == []  # fits: no second look
    monkeypatch.setattr(pipeline, "judged", judged)
    r = estimate(slabbed, ctx.base, ctx.view.T_base_part, p)
    assert len(looks) == 1 and not looks[0].fits and r.confident and r.second_look is not None


def test_second_look_from_pose_refits_without_a_search_and_agrees(gearbox_dataset, monkeypatch):
    """`second_look_from_pose` (a region's part found whole): the second look on the slab-widened mask refits from the
    first pose (no search: search_poses is not called again), confident and right, within a millimetre of the full
    second look's pose; an ambiguous first result is never refitted (its rivals matter), and a refit that is not
    confident leaves the full second look to run."""
    from dataclasses import replace

    from apose_studio.registration import pipeline

    ctx, fr, view = _slab_beside_the_base(gearbox_dataset)
    p = resolve_params("default", mask_hypotheses=False)
    full = estimate(view, ctx.base, ctx.view.T_base_part, p)
    searches = []
    search = pipeline.search_poses
    monkeypatch.setattr(pipeline, "search_poses", lambda *a, **k: searches.append(1) or search(*a, **k))
    quick = estimate(view, ctx.base, ctx.view.T_base_part, replace(p, second_look_from_pose=True))
    assert searches == [1]  # the first estimate's search only
    assert quick.confident and quick.second_look is not None
    assert mssd(quick.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * ctx.part.diameter
    assert np.linalg.norm(quick.T_world_base[:3, 3] - full.T_world_base[:3, 3]) < 0.001
    first = estimate(view, ctx.base, ctx.view.T_base_part, replace(p, second_look=False))
    refits = []
    monkeypatch.setattr(pipeline, "refit", lambda *a, **k: refits.append(1))
    from_pose = replace(p, second_look_from_pose=True)
    assert pipeline.second_look(replace(first, ambiguous=True), view, ctx.base, ctx.view.T_base_part, from_pose,
                                None, False) is not None and not refits  # ambiguous: the full second look
    searches.clear()
    r = pipeline.second_look(first, view, ctx.base, ctx.view.T_base_part, from_pose, None, False)
    assert refits == [1] and not searches and r.confident  # the refit gave nothing: the first look's candidates
    # refined on the cut, with their twins and neighbours (no search)


def test_the_second_look_refines_the_first_looks_candidates_and_compares_their_twins(gearbox_dataset, monkeypatch):
    """The second look registers on the cut mask from the first look's candidates (pipeline.first_look_starts), without
    a search of its own: confident and right on the slab-widened mask with one search in all, its replay starting
    from "first look". A first look turned by
    any of the base's close twins, near-symmetries or half turns is never made confident and wrong by it: the turned
    pose's twins are refined and compared on the cut (or the result stays the unconfident first look); some come back
    confident and right."""
    from dataclasses import replace

    from apose_studio.registration import pipeline

    ctx, fr, view = _slab_beside_the_base(gearbox_dataset)
    base, T_base_part = ctx.base, ctx.view.T_base_part
    p = resolve_params("default", mask_hypotheses=False)
    searches = []
    search = pipeline.search_poses
    monkeypatch.setattr(pipeline, "search_poses", lambda *a, **k: searches.append(1) or search(*a, **k))
    r = estimate(view, base, T_base_part, p)
    assert searches == [1] and r.confident and r.second_look is not None
    assert mssd(r.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * ctx.part.diameter
    assert r.stages[1].name == "first look"  # the replay names where the cut's ICP started: no global search ran
    first = estimate(view, base, T_base_part, replace(p, second_look=False))
    assert first.stages[1].name == "global"
    assert not first.confident
    back = 0
    for S in [*base.close_twins, *base.near_symmetries, *base.flips()[1:]]:
        T = first.T_world_base @ S
        turned = replace(first, T_world_base=T, T_world_part=T @ T_base_part,
                         candidates=[replace(first.candidates[0], T_world_base=T, T_world_part=T @ T_base_part)])
        r = pipeline.second_look(turned, view, base, T_base_part, p, None, False)
        right = mssd(r.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * ctx.part.diameter
        assert right or not r.confident, S
        back += bool(right and r.confident)
    assert back >= 3, back


def test_the_second_look_comes_before_the_free_search(gearbox_dataset, monkeypatch):
    """The upright pose of a mask with a slab of table beside the base does not fit, so the free search is
    due; the second look on the upright pose settles it first (confident and right), and the free search,
    which seldom wins there (docs/ESTIMATOR.md), is not run. Without the second look it is."""
    from dataclasses import replace

    from apose_studio.registration import pipeline

    ctx, fr, view = _slab_beside_the_base(gearbox_dataset)
    runs = []
    free_search = pipeline.better_of_free_search
    monkeypatch.setattr(pipeline, "better_of_free_search", lambda *a, **k: runs.append(1) or free_search(*a, **k))
    p = resolve_params("default", mask_hypotheses=False)
    alone = estimate(view, ctx.base, ctx.view.T_base_part, replace(p, second_look=False))
    assert runs and not alone.confident  # due: the upright pose does not fit
    runs.clear()
    r = estimate(view, ctx.base, ctx.view.T_base_part, p)
    assert r.confident and r.second_look is not None and not runs
    assert mssd(r.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * ctx.part.diameter


def test_the_result_mask_keeps_the_base_holes_and_leaves_the_occluder_holes_out(gearbox_step2):
    """A Kinect-like sensor leaves holes: on a dark face of the base, and on what stands in front of it. The
    result's mask (model_cut_mask with the prompt's reach) takes in each hole whose nearest depth lies on the
    model's surface and leaves out each whose nearest depth is the object in front. Built by hand: the
    renderer's depth of the base alone, a disc of it emptied, a box's depth 30 mm nearer over another part of
    it, and a disc of that emptied. (Before: every hole the prompt had missed was left out, so a base's dark
    faces were missing from its mask: 0.40 of a planetary motor's visible mask on a benchmarks/captures.py
    `stacked` frame, 0.55 since.)"""
    from types import SimpleNamespace

    from apose_studio.registration.pipeline import mask_reach, model_cut_mask

    _, base, _ = gearbox_step2
    T_world_base = se3.make_T(np.eye(3), [0.05, 0.02, 0.0])
    T_world_camera = se3.look_at([0.35, -0.25, 0.3], [0.05, 0.02, 0.01])
    depth, silhouette = synthetic_view(base, T_world_base, T_world_camera)
    vs, us = np.nonzero(silhouette)
    vc, uc = int(np.median(vs)), int(np.median(us))
    rows, cols = np.mgrid[: depth.shape[0], : depth.shape[1]]
    occluder = silhouette & (cols > uc + 8)  # a box standing in front of the right of the base
    depth = depth.copy()
    depth[occluder] -= 0.03
    dark_base = silhouette & ((rows - vc) ** 2 + (cols - (uc - 15)) ** 2 <= 36) & ~occluder
    dark_occluder = occluder & ((rows - vc) ** 2 + (cols - (uc + 25)) ** 2 <= 36)
    assert dark_base.sum() > 80 and dark_occluder.sum() > 80
    depth[dark_base | dark_occluder] = 0.0
    prompted = (depth > 0) & silhouette  # what a prompt takes: the pixels with depth, the box in front too
    v0, v1, u0, u1 = vs.min(), vs.max() + 1, us.min(), us.max() + 1
    view = View(depth, prompted, CAM, T_world_camera, box=(int(u0), int(v0), int(u1), int(v1)))
    result = SimpleNamespace(T_world_base=T_world_base, voxel=0.002, depth_noise=0.0)
    cut = model_cut_mask(result, view, base, reach=mask_reach(view))
    assert cut[dark_base].all()
    assert not cut[dark_occluder].any()
    assert not cut[occluder].any()
    truth = silhouette & ~occluder
    assert (cut & truth).sum() / (cut | truth).sum() > 0.98
