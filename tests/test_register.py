"""The estimator's stages on small data, and degenerate inputs that must fail cleanly."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from apose_studio import se3
from apose_studio.assembly import load_assembly
from apose_studio.config import CameraIntrinsics, RegistrationConfig
from apose_studio.errors import AposeError
from apose_studio.mesh import base_mesh, load_parts
from apose_studio.metrics import mssd
from apose_studio.registration import (detect_symmetries, estimate, icp, prepare_base, project_to_cloud,
                                       raycast_source, resolve_params)
from apose_studio.registration.stages import cloud

from .conftest import SAMPLES

CAM = CameraIntrinsics(640, 480, 615.0, 615.0, 320.0, 240.0)


def test_project_to_cloud_by_hand():
    depth = np.zeros((480, 640), np.float32)
    depth[240, 320] = 0.5  # the principal point: straight ahead
    depth[240, 443] = 1.0  # 123 px right of it at 1 m: x = 123 / 615 = 0.2 m
    depth[0, 0] = np.nan
    mask = np.ones_like(depth, bool)
    T_world_camera = se3.make_T(t=[0, 0, 2.0])
    pts = project_to_cloud(depth, mask, CAM, T_world_camera)
    np.testing.assert_allclose(sorted(pts.tolist()), [[0, 0, 2.5], [0.2, 0, 3.0]], atol=1e-6)
    with pytest.raises(AposeError, match="mask is 2x2 but depth is 640x480"):
        project_to_cloud(depth, np.ones((2, 2), bool), CAM, T_world_camera)


@pytest.fixture(scope="module")
def gearbox_step2():
    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    models = load_parts(asm)
    view = asm.step_view(2)
    return view, prepare_base(base_mesh(models, view)), models


def synthetic_view(base, T_world_base, T_world_camera):
    """Depth and mask of the base alone, ray-cast exactly (no table, no noise)."""
    from apose_studio.raycast import raycast_points

    pts, _ = raycast_points(base.mesh, T_world_base, T_world_camera, CAM)
    pc = se3.transform_points(se3.inv(T_world_camera), pts)
    u = np.round(CAM.fx * pc[:, 0] / pc[:, 2] + CAM.cx).astype(int)
    v = np.round(CAM.fy * pc[:, 1] / pc[:, 2] + CAM.cy).astype(int)
    depth = np.zeros((CAM.height, CAM.width), np.float32)
    depth[v, u] = pc[:, 2]
    return depth, depth > 0


def test_icp_recovers_a_known_small_motion(gearbox_step2):
    _, base, _ = gearbox_step2
    T_world_camera = se3.look_at([0.25, -0.2, 0.3], [0, 0, 0.01])
    T_true = se3.make_T(se3.axis_angle_matrix([0.3, 0.2, 1.0], np.radians(40)), [0.01, -0.02, 0.0])
    target_w, target_n = raycast_source(base, T_true, T_world_camera, CAM)
    target = cloud(target_w, target_n)
    source = cloud(se3.transform_points(se3.inv(T_true), target_w)).voxel_down_sample(0.001)
    T0 = T_true @ se3.make_T(se3.axis_angle_matrix([1, 0, 0], np.radians(3)), [0.002, -0.001, 0.0015])
    T = icp(source, target, T0, 0.005, 60)
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 5e-4
    assert se3.rotation_angle_deg(T[:3, :3].T @ T_true[:3, :3]) < 0.2
    trace = []
    icp(source, target, T0, 0.005, 60, trace)
    assert len(trace) >= 2 and np.linalg.norm(trace[-1][:3, 3] - T_true[:3, 3]) < 5e-4


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


def test_a_wrong_prior_falls_back_to_the_global_search(gearbox_step2):
    view, base, _ = gearbox_step2
    T_world_base = se3.make_T(np.eye(3), [0.05, 0.02, 0.0])
    T_world_camera = se3.look_at([0.35, -0.25, 0.3], [0.05, 0.02, 0.01])
    depth, mask = synthetic_view(base, T_world_base, T_world_camera)
    wrong = se3.make_T(se3.axis_angle_matrix([0, 0, 1], np.radians(90)))
    r = estimate(depth, mask, CAM, T_world_camera, base, view.T_base_part, resolve_params("default"),
                 prior_T_world_base=wrong)
    assert r.ok and r.stages[1].name == "global" and {"prior", "global", "icp"} <= set(r.timings)


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


def test_symmetry_detection():
    box = trimesh.creation.box((0.04, 0.02, 0.01))
    syms, res = detect_symmetries(trimesh.sample.sample_surface_even(box, 6000, seed=1)[0], 0.046)
    assert len(syms) == 4  # identity and the three half turns
    assert np.all(res < 0.0005)
    l_shape = trimesh.util.concatenate([box, trimesh.creation.box((0.01, 0.03, 0.01)).apply_translation([0.015, 0.02, 0])])
    syms, _ = detect_symmetries(trimesh.sample.sample_surface_even(l_shape, 6000, seed=1)[0], 0.06)
    assert len(syms) == 1


def test_fidget_casing_is_two_fold(fidget_yaml):
    asm = load_assembly(fidget_yaml)
    models = load_parts(asm)
    base = prepare_base(base_mesh(models, asm.step_view(1)))
    assert len(base.symmetries) == 2
    axis = base.symmetries[1][:3, :3]
    assert se3.rotation_angle_deg(axis) == pytest.approx(180, abs=1)
    assert abs(axis[2, 2] - 1) < 1e-3  # about z
    assert base.symmetry_residuals[1] < 0.0005


def test_params_from_file_and_caller():
    p = resolve_params("default", RegistrationConfig(voxel_size_m=0.002, seed=7))
    assert p.voxel_size_m == 0.002 and p.seed == 7 and p.preset == "default"
    assert p.voxel(1.0) == 0.002
    assert resolve_params("default").voxel(0.05) == pytest.approx(0.001)  # diameter / 50
    paper = resolve_params("paper")
    assert (paper.voxel(1.0), paper.ransac_max_iterations, paper.ransac_confidence) == (0.008, 100000, 0.899)
    assert resolve_params("default", RegistrationConfig(preset="paper")).preset == "paper"
    assert replace(paper, seed=3).seed == 3
    with pytest.raises(AposeError, match="unknown preset 'fast'"):
        resolve_params("fast")


@pytest.fixture(scope="module")
def gearbox_yaw(tmp_path_factory):
    from apose_studio.dataset import Dataset
    from apose_studio.render import RenderSettings, render_dataset

    out = tmp_path_factory.mktemp("yaw") / "ds"
    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=2, seed=4), steps=[2], progress=False)
    return Dataset(out)


def test_upright_search_finds_the_yaw_without_ransac(gearbox_yaw):
    """--upright: the table's normal from the depth around the base, then every yaw about it (no
    RANSAC, so deterministic); both frames land within a millimetre."""
    from apose_studio.evaluate import StepContext, estimate_frame
    from apose_studio.registration import table_normal

    ds = gearbox_yaw
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 2)
    p = resolve_params("default", upright=True)
    for im_id in ds.image_ids(2):
        fr = ds.frame(2, im_id)
        n = table_normal(fr.depth, fr.base_mask(), fr.camera, fr.T_world_camera)
        assert n is not None and n[2] > 0.999  # the table is the world's xy plane
        r = estimate_frame(fr, ctx, p)
        assert r.ok and "global" in r.timings
        err = mssd(r.T_world_part, fr.T_world_part, ctx.part.samples, ctx.part.symmetries)
        assert err < 1e-3, (im_id, err)


def test_a_base_not_standing_as_modelled_falls_back_to_the_free_search(gearbox_yaw):
    """Upright is on by default and a table is seen, but here the CAD's z axis is not the table's
    normal (the same frames, with the base's model turned a quarter about x, as if it lay on its
    side): the upright yaws screen poorly (or end in a fit that is not confident), so the free search
    runs and still lands within 1 mm. Either guard alone passes this test; neither fails it."""
    from apose_studio.evaluate import StepContext

    ds = gearbox_yaw
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 2)
    T_new_old = se3.make_T(se3.axis_angle_matrix([1.0, 0, 0], np.radians(90)), [0, 0, 0])  # old CAD frame -> new
    mesh = ctx.base.mesh.copy()
    mesh.apply_transform(T_new_old)
    base = prepare_base(mesh)
    T_base_part = T_new_old @ ctx.view.T_base_part
    p = resolve_params("default")
    assert p.upright
    for im_id in ds.image_ids(2):
        fr = ds.frame(2, im_id)
        r = estimate(fr.depth, fr.base_mask(), fr.camera, fr.T_world_camera, base, T_base_part, p, trace_iterations=False)
        assert r.ok and r.confident, (im_id, r.reason, r.coverage)
        err = mssd(r.T_world_part, fr.T_world_part, ctx.part.samples, ctx.part.symmetries)
        assert err < 1e-3, (im_id, err)


def test_evidence_confirms_contradicts_or_ignores_by_hand():
    """A flat surface 1 m away fills the mask (a 100 x 100 px square); the rest of the image sees a
    wall at 2 m. Model points on the surface are confirmed; points floating at 0.9 m inside the mask
    are contradicted (the camera sees past them); points 0.9 m away outside the mask too; points
    behind the surface (1.1 m) are hidden by it: neither; points outside the mask but within its
    2 px margin are neither (mask edges are a pixel or two off)."""
    from apose_studio.registration import MASK_MARGIN_PX, mask_edge
    from apose_studio.registration.scoring import evidence

    depth = np.full((CAM.height, CAM.width), 2.0)
    mask = np.zeros_like(depth, bool)
    mask[190:290, 270:370] = True
    depth[mask] = 1.0
    edge = mask_edge(mask, MASK_MARGIN_PX)
    assert edge[240, 271] and edge[240, 268] and not edge[240, 266] and not edge[240, 320]  # 2 px either side
    outside = ~(mask | edge)

    def at(us, vs, z):  # world = camera frame here
        return CAM.backproject(np.asarray(us), np.asarray(vs), np.full(len(us), z))

    eye = np.eye(4)
    on = at([300, 320, 340], [200, 240, 280], 1.0)
    floating_in = at([300, 320], [240, 240], 0.9)
    floating_out = at([100, 500], [100, 400], 0.9)
    hidden = at([320], [240], 1.1)
    margin = at([371], [240], 0.9)  # 1 px right of the mask
    assert evidence(on, eye, CAM, depth, mask, outside, 0.01) == (3, 0)
    assert evidence(floating_in, eye, CAM, depth, mask, outside, 0.01) == (0, 2)
    assert evidence(floating_out, eye, CAM, depth, mask, outside, 0.01) == (0, 2)
    assert evidence(hidden, eye, CAM, depth, mask, outside, 0.01) == (0, 0)
    assert evidence(margin, eye, CAM, depth, mask, outside, 0.01) == (0, 0)
    assert evidence(np.zeros((0, 3)), eye, CAM, depth, mask, outside, 0.01) == (0, 0)


@pytest.fixture(scope="module")
def planetary_yaw(tmp_path_factory):
    from apose_studio.dataset import Dataset
    from apose_studio.render import RenderSettings, render_dataset

    out = tmp_path_factory.mktemp("planetary") / "ds"
    asm = load_assembly(SAMPLES / "planetary_reducer" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=6, seed=11, base_pose="yaw"), steps=[3], progress=False)
    return Dataset(out)


def test_a_nearly_symmetric_base_is_told_apart_where_the_view_allows(planetary_yaw):
    """Planetary step 3: a motor block that is 4-fold symmetric but for its cable connector, under a
    round housing. Each quarter turn of the best upright pose is refined, so the true yaw is always
    among the candidates; where the view tells the turns apart the estimate is right, and where it
    does not (the connector hidden at both) the result says `ambiguous` and lists the true pose."""
    from apose_studio.evaluate import StepContext, estimate_frame

    ds = planetary_yaw
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 3)
    assert len(ctx.base.symmetries) == 4  # the quarter turns fit within 0.5 % of the diameter
    p = resolve_params("default")
    right = 0
    for im_id in ds.image_ids(3):
        fr = ds.frame(3, im_id)
        r = estimate_frame(fr, ctx, p)
        errs = [mssd(c.T_world_part, fr.T_world_part, ctx.part.samples, ctx.part.symmetries) for c in r.candidates]
        assert min(errs) < 1e-3, (im_id, errs)
        err = mssd(r.T_world_part, fr.T_world_part, ctx.part.samples, ctx.part.symmetries)
        assert err < 1e-3 or (r.ambiguous and min(mssd(c.T_world_part, fr.T_world_part, ctx.part.samples, ctx.part.symmetries)
                                                for c in r.alternatives) < 1e-3), (im_id, err)
        right += err < 1e-3
    assert right >= 4, right


def test_polish_refines_a_noisy_view_onto_the_model(gearbox_step2):
    """The last refinement registers the (noisy) target onto the model seen at the pose, with the
    model's exact normals: from 1 mm and 0.5 deg off, on a view with 1 mm depth noise, it ends within
    0.15 mm (ADI of the base), where the usual ICP (target normals) at the same start does clearly worse."""
    from apose_studio.metrics import adi
    from apose_studio.registration import Observation, mask_edge
    from apose_studio.registration.problem import prepare_problem
    from apose_studio.registration.refine import polish

    _, base, _ = gearbox_step2
    T_world_camera = se3.look_at([0.25, -0.2, 0.3], [0, 0, 0.01])
    T_true = se3.make_T(se3.axis_angle_matrix([0, 0, 1.0], np.radians(25)), [0.01, -0.02, 0.0])
    depth, mask = synthetic_view(base, T_true, T_world_camera)
    rng = np.random.default_rng(0)
    depth = np.where(mask, depth + rng.normal(0, 0.001, depth.shape), 0).astype(np.float32)
    target = cloud(project_to_cloud(depth, mask, CAM, T_world_camera))
    p = resolve_params("default")
    voxel = p.voxel(base.diameter)
    T_start = se3.make_T(se3.axis_angle_matrix([1.0, 1.0, 0], np.radians(0.5)), [0.001, 0, 0]) @ T_true
    pb = prepare_problem(np.asarray(target.points), CAM, T_world_camera, base, np.eye(4), p, voxel,
                         Observation(mask, depth, mask_edge(mask)))
    T, seen = polish(pb, T_start, None)
    err = adi(T, T_true, base.samples)
    assert adi(T_start, T_true, base.samples) > 5e-4 and err < 1.5e-4, err
    assert seen.shape[1] == 3 and len(seen) > 1000
    # the same start, refined the usual way: model points onto the target, with the target's normals
    import open3d as o3d

    fine = target.voxel_down_sample(voxel * p.polish_voxel_factor)
    fine.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=p.normal_radius_factor * voxel, max_nn=30))
    fine.orient_normals_towards_camera_location(T_world_camera[:3, 3])
    src_w, _ = raycast_source(base, T_start, T_world_camera, CAM)
    src = cloud(se3.transform_points(se3.inv(T_start), src_w)).voxel_down_sample(voxel * p.polish_voxel_factor)
    T_usual = icp(src, fine, T_start, p.polish_threshold_factor * voxel, 30)
    assert adi(T_usual, T_true, base.samples) > 1.5 * err, (adi(T_usual, T_true, base.samples), err)  # 0.09 vs 0.035 mm


def test_a_right_prior_is_accepted_on_noisy_depth(tmp_path):
    """With RealSense-like noise, the depth at the mask's outline (mixed pixels) and its dropouts
    can neither confirm nor deny the model; left out of the prior's check, a right prior is taken
    at once (no global search), and the pose is within 0.5 mm."""
    from apose_studio.dataset import Dataset
    from apose_studio.evaluate import StepContext, estimate_frame
    from apose_studio.render import RenderSettings, render_dataset

    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    render_dataset(asm, tmp_path / "ds", RenderSettings(frames=3, seed=11, noise="realsense", base_pose="fixed"),
                   steps=[3], progress=False)
    ds = Dataset(tmp_path / "ds")
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 3)
    for im_id in ds.image_ids(3):
        fr = ds.frame(3, im_id)
        r = estimate_frame(fr, ctx, resolve_params("default"), orientation_prior=True)
        assert r.ok and "prior" in r.timings and "global" not in r.timings, (im_id, r.timings)
        assert mssd(r.T_world_part, fr.T_world_part, ctx.part.samples, ctx.part.symmetries) < 5e-4


def test_a_symmetric_base_reports_both_seats(fidget_yaml, tmp_path):
    """The fidget's bottom casing is 2-fold symmetric: from it alone the left gear's two seats cannot
    be told apart. Each result says `ambiguous` and gives the other seat (23 mm away, half a turn) as
    its one alternative; the truth is the estimate or that alternative."""
    from apose_studio.dataset import Dataset
    from apose_studio.evaluate import StepContext, estimate_frame
    from apose_studio.render import RenderSettings, render_dataset

    asm = load_assembly(fidget_yaml)
    render_dataset(asm, tmp_path / "ds", RenderSettings(frames=3, seed=11, base_pose="yaw"), steps=[1], progress=False)
    ds = Dataset(tmp_path / "ds")
    ctx = StepContext(ds.assembly, load_parts(ds.assembly), 1)
    for im_id in ds.image_ids(1):
        fr = ds.frame(1, im_id)
        r = estimate_frame(fr, ctx, resolve_params("default"))
        assert r.ok and r.ambiguous and len(r.alternatives) == 1, (im_id, r.ambiguous, len(r.alternatives))
        alt = r.alternatives[0].T_world_part
        assert 0.015 < np.linalg.norm(alt[:3, 3] - r.T_world_part[:3, 3]) < 0.03
        errs = [mssd(T, fr.T_world_part, ctx.part.samples, ctx.part.symmetries) for T in (r.T_world_part, alt)]
        assert min(errs) < 1e-3, errs


def test_near_grid_answers_like_the_distance_to_the_cloud():
    """The screening's grid says 'near' for points well within the radius and 'far' for points well
    beyond it (it is exact up to a cell's half diagonal, 0.22 x radius); off the grid is far."""
    from scipy.spatial import cKDTree

    from apose_studio.registration import NearGrid

    rng = np.random.default_rng(3)
    cloud = trimesh.sample.sample_surface_even(trimesh.creation.box((0.04, 0.02, 0.01)), 3000, seed=1)[0]
    r = 0.002
    grid = NearGrid.around(cloud, r)
    q = cloud[rng.choice(len(cloud), 4000)] + rng.normal(scale=r, size=(4000, 3))
    q = np.concatenate([q, [[1.0, 1.0, 1.0], [-1.0, 0.0, 0.0]]])
    d = cKDTree(cloud).query(q)[0]
    got = grid.contains(q)
    assert got[d < 0.75 * r].all() and not got[d > 1.25 * r].any()
    assert (d < 0.75 * r).sum() > 500 and (d > 1.25 * r).sum() > 500  # both kinds were asked


def test_rotations_vectorised_and_rigid_fit():
    from scipy.spatial.transform import Rotation

    axis = np.array([0.3, -1.0, 2.0])
    angles = np.array([0.0, 0.4, 2.5, np.pi])
    Rs = se3.axis_angle_matrix(axis, angles)
    assert Rs.shape == (4, 3, 3)
    for R, a in zip(Rs, angles):
        np.testing.assert_allclose(R, Rotation.from_rotvec(axis / np.linalg.norm(axis) * a).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(se3.axis_angle_matrix(axis, a), R, atol=1e-15)
    src = np.random.default_rng(0).normal(size=(50, 3))
    T = se3.make_T(Rs[2], [0.1, -0.2, 0.3])
    np.testing.assert_allclose(se3.fit_rigid(src, se3.transform_points(T, src)), T, atol=1e-9)


def test_a_symmetry_turns_about_the_true_axis_despite_an_off_centre_feature():
    """A 2-fold symmetric block with a small knob off to one side: the knob pulls the samples'
    centroid off the block's axis, so a half turn about the centroid would put the twin pose ~0.3 mm
    off; the detected symmetry is refined onto the block and turns about the block's own axis."""
    block = trimesh.creation.box((0.1, 0.06, 0.04))
    knob = trimesh.creation.box((0.004, 0.004, 0.005)).apply_translation([0.045, 0.025, 0.0225])
    mesh = trimesh.util.concatenate([block, knob])
    pts = trimesh.sample.sample_surface_even(mesh, 20000, seed=2)[0]
    assert np.linalg.norm(pts.mean(axis=0)[:2]) > 1e-4  # the centroid is off the axis
    syms, res = detect_symmetries(pts, 0.125)
    half = [S for S in syms[1:] if abs(S[2, 2] - 1) < 1e-3]  # the half turn about z
    assert len(half) == 1 and se3.rotation_angle_deg(half[0][:3, :3]) == pytest.approx(180, abs=0.5)
    assert np.linalg.norm(half[0][:3, 3]) < 1.5e-4  # maps the block's centre (the origin) onto itself (0.36 mm unrefined)


def test_near_grid_stays_small_for_a_fine_radius_on_a_big_part():
    from apose_studio.registration import NearGrid

    cloud = trimesh.sample.sample_surface_even(trimesh.creation.box((1.0, 0.8, 0.5)), 20000, seed=1)[0]
    grid = NearGrid.around(cloud, 0.002)  # radius/4 cells would be 400 x 320 x 200 = 26 M
    assert grid.occupied.size <= 1.1 * NearGrid.MAX_CELLS
    assert grid.contains(cloud[:100]).all() and not grid.contains(np.array([[0.0, 0.0, 0.0]])).any()
