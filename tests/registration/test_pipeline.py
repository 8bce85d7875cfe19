"""The whole estimate: poses recovered, degenerate and unit-error input refused with a reason, symmetric seats reported."""

import numpy as np
import pytest
import trimesh

from apose_studio import se3
from apose_studio.assembly import load_assembly
from apose_studio.mesh import load_parts
from apose_studio.metrics import mssd
from apose_studio.registration import estimate, prepare_base, resolve_params

from ..conftest import SAMPLES
from .conftest import CAM, synthetic_view


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_pose_recovered_with_the_cad_orientation_known(gearbox_step2, preset):
    view, base, models = gearbox_step2
    T_world_base = se3.make_T(np.eye(3), [0.05, 0.02, 0.0])  # the paper's protocol: orientation as in the CAD
    T_world_camera = se3.look_at([0.35, -0.25, 0.3], [0.05, 0.02, 0.01])
    depth, mask = synthetic_view(base, T_world_base, T_world_camera)
    p = resolve_params(preset, use_orientation_prior=True)
    r = estimate(depth, mask, CAM, T_world_camera, base, view.T_base_part, p, prior_T_world_base=np.eye(4))
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
    r = estimate(depth, empty, CAM, T_wc, base, view.T_base_part, p)
    assert not r.ok and "empty mask" in r.reason
    few = empty.copy()
    few[100, 100:102] = True
    r = estimate(depth, few, CAM, T_wc, base, view.T_base_part, p)
    assert not r.ok and "only 2 valid depth points" in r.reason
    nan_depth = np.full((480, 640), np.nan, np.float32)
    r = estimate(nan_depth, ~empty, CAM, T_wc, base, view.T_base_part, p)
    assert not r.ok and "only 0 valid depth points" in r.reason
    line = empty.copy()
    line[240, 100:500] = True  # a single row of pixels on a plane: a line in 3D
    r = estimate(depth, line, CAM, T_wc, base, view.T_base_part, p)
    assert not r.ok and "degenerate" in r.reason
    # a 4 cm blob of depth for a 0.35 mm base: a unit error, said as one (the paper preset would not
    # even see the mesh)
    speck = prepare_base(trimesh.creation.box((0.0002, 0.0002, 0.0002)), n_samples=500)
    blob = empty.copy()
    blob[200:260, 300:360] = True
    r = estimate(depth, blob, CAM, T_wc, speck, view.T_base_part, resolve_params("paper"))
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
    from apose_studio.dataset import Dataset
    from apose_studio.evaluate import StepContext, estimate_frame, score_frame
    from apose_studio.render import RenderSettings, render_dataset

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



def test_junk_is_never_a_confident_pose(gearbox_dataset):
    """A box on empty table, the wrong object, 40 points of noise: ok=False or not confident, every time."""
    from apose_studio.dataset import Dataset
    from apose_studio.evaluate import StepContext

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
            r = estimate(depth, mask, fr.camera, fr.T_world_camera, ctx.base, ctx.view.T_base_part, p)
            assert not (r.ok and r.confident), (what, im, r.coverage, r.reason)
            assert r.seconds < 3.0, (what, r.seconds)  # the time budget holds (1 s, plus what it cannot cut)


def test_a_pose_the_camera_cannot_have_seen_is_not_ok(gearbox_step2):
    """judge(): behind the camera, outside the image, beyond the farthest depth, or explaining nothing."""
    from apose_studio.registration import Candidate, RegistrationResult
    from apose_studio.registration.pipeline import judge

    _, base, _ = gearbox_step2
    T_world_camera = np.eye(4)  # the camera at the origin, looking along +z
    depth = np.full((CAM.height, CAM.width), 0.5, np.float32)

    mask = np.zeros(depth.shape, bool)
    mask[200:280, 280:360] = True
    plane = np.stack(np.meshgrid(np.linspace(-0.01, 0.01, 5), np.linspace(-0.01, 0.01, 5), [0.0]), -1).reshape(-1, 3)

    def result(t, fitness=0.9, coverage=0.95, seen_z=0.5):
        T = se3.make_T(t=np.asarray(t, float) - base.centre)
        c = Candidate(T, T, fitness, 0.9, 0.001, 0.9, 0, coverage)
        seen = se3.transform_points(se3.inv(T), plane + [0, 0, seen_z])  # what the model shows, base frame
        return RegistrationResult(True, "", T, T, T, fitness=fitness, coverage=coverage, candidates=[c],
                                  source_cloud=seen, voxel=0.002)

    r = judge(result([0, 0, 0.5]), depth, mask, CAM, T_world_camera, base)
    assert r.ok and r.contradiction == 0.0 and r.confident
    for t, kw, why in [([0, 0, -0.5], {}, "behind the camera"), ([5.0, 0, 0.5], {}, "outside the image"),
                       ([0, 0, 3.0], {}, "beyond the farthest depth"),
                       ([0, 0, 0.5], {"fitness": 0.0, "coverage": 0.0}, "explains almost none of the target"),
                       ([0, 0, 0.5], {"seen_z": 0.3}, "the depth contradicts 100% of what the model shows")]:
        r = judge(result(t, **kw), depth, mask, CAM, T_world_camera, base)
        assert not r.ok and why in r.reason and "no pose is reported" in r.reason, (t, kw, r.reason)
        assert not r.confident


def test_the_paper_preset_is_not_confident_about_wrong_poses(tmp_path):
    """The paper keeps the CAD's orientation. On Kinect-like cluttered benches with the base at a random
    yaw (benchmarks/captures.py's gearbox frames of step 1) it lands off with most of the target within
    its 16 mm tolerance; judged at the scale-aware tolerance on what the camera sees of the model there,
    such poses are not confident (frame 3 was, before). Wrong = off by 0.1 x the part's diameter even
    modulo the base's exact symmetries (its half turn is the same assembly)."""
    from apose_studio.assembly import load_assembly
    from apose_studio.dataset import Dataset
    from apose_studio.evaluate import StepContext, estimate_frame, frame_mask, score_frame
    from apose_studio.render import RenderSettings, render_dataset

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


def test_second_look_cuts_clutter_from_the_mask(gearbox_dataset):
    """A mask that took in a slab of table beside the base: the first estimate is right but not
    confident (a third of the target is unexplained); the second look, on the mask cut to the model's
    view at that pose, is confident, and its mask lies inside the given one."""
    from dataclasses import replace

    from apose_studio.dataset import Dataset
    from apose_studio.evaluate import StepContext

    ds = Dataset(gearbox_dataset)
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 1)
    fr = ds.frame(1, 0)
    truth = fr.base_mask()
    ys, xs = np.nonzero(truth)
    slab = np.zeros_like(truth)
    w = int(0.6 * np.ptp(xs))
    slab[ys.min():ys.max(), xs.max() + 1:xs.max() + 1 + w] = True  # beside the base, to its right
    mask = truth | slab
    p = resolve_params("default")
    first = estimate(fr.depth, mask, fr.camera, fr.T_world_camera, ctx.base, ctx.view.T_base_part,
                     replace(p, second_look=False))
    r = estimate(fr.depth, mask, fr.camera, fr.T_world_camera, ctx.base, ctx.view.T_base_part, p)
    d = ctx.part.diameter
    assert first.ok and not first.confident and mssd(first.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * d
    assert r.confident and r.second_look is not None and not (r.second_look & ~mask).any()
    assert mssd(r.T_world_part, fr.T_world_part, ctx.part.samples) < 0.1 * d and "second look" in r.timings
