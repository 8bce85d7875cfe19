"""Rendering and the BOP dataset: geometry is exact, files load, bad input is refused clearly."""

import json
from dataclasses import replace

import cv2
import numpy as np
import open3d as o3d
import pytest

from apose_studio.assembly.mesh import load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.data.dataset import Dataset, load_capture
from apose_studio.data.sources import open_frames
from apose_studio.errors import AposeError, DatasetError, RenderError
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.noise import add_depth_noise
from apose_studio.synth.frame import RenderSettings
from apose_studio.synth.render import render_dataset

from ..conftest import SAMPLES

SMALL_CAM = CameraIntrinsics(320, 240, 300.0, 300.0, 160.0, 120.0)


def surface_distance(mesh, pts):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()


def back_project(frame, mask):
    vs, us = np.nonzero(mask & (frame.depth > 0))
    z = frame.depth[vs, us]
    K = frame.K
    pc = np.stack([(us - K[0, 2]) * z / K[0, 0], (vs - K[1, 2]) * z / K[1, 1], z], axis=1)
    return se3.transform_points(frame.T_world_camera, pc)


@pytest.fixture(scope="module")
def planetary():
    asm = load_assembly(SAMPLES / "planetary_reducer" / "assembly.yaml")
    return asm, load_parts(asm)


@pytest.fixture(scope="module")
def planetary_ds(planetary, tmp_path_factory):
    asm, models = planetary
    out = tmp_path_factory.mktemp("ds") / "planetary"
    render_dataset(asm, out, RenderSettings(frames=3, seed=1, camera=SMALL_CAM), progress=False, models=models)
    return Dataset(out), models


def test_back_projected_depth_lands_on_the_right_part(planetary_ds):
    ds, models = planetary_ds
    assert ds.steps == [1, 2, 3, 4]
    checked = 0
    for step in ds.steps:
        for im_id in ds.image_ids(step):
            f = ds.frame(step, im_id)
            for pid, mask in f.masks.items():
                if mask.sum() < 20:
                    continue
                pts = se3.transform_points(se3.inv(f.poses[pid]), back_project(f, mask))
                d = surface_distance(models[pid].mesh, pts)
                assert d.max() < 1e-4, (step, im_id, pid, d.max())  # depth is stored in 0.1 mm steps
                checked += 1
    assert checked >= 20


def test_frames_are_consistent(planetary_ds):
    ds, _ = planetary_ds
    f = ds.frame(3, 1)
    assert f.rgb.shape == (240, 320, 3) and f.depth.shape == (240, 320) and f.depth.dtype == np.float32
    np.testing.assert_allclose(f.K, SMALL_CAM.K)
    assert f.part == "carrier" and f.base == ("housing", "motor", "sun_gear")
    np.testing.assert_allclose(f.T_world_part, f.T_world_base @ f.T_base_part, atol=1e-9)
    np.testing.assert_allclose(f.poses["housing"], f.T_world_base, atol=1e-6)  # base[0] is the housing
    # masks: inside the depth, disjoint, base mask is their union
    masks = list(f.masks.values())
    assert all(np.all(f.depth[m] > 0) for m in masks)
    assert sum(m.astype(int) for m in masks).max() <= 1
    assert f.base_mask().sum() == sum(f.masks[p].sum() for p in f.base)
    # the camera looks at the base: the base is near the image centre and in front of the camera
    p_cam = se3.transform_points(se3.inv(f.T_world_camera), f.T_world_base[None, :3, 3])[0]
    assert p_cam[2] > 0


def test_bop_files(planetary_ds):
    ds, models = planetary_ds
    root = ds.root
    info = json.loads((root / "models" / "models_info.json").read_text())
    assert set(info) == {"1", "2", "3", "4", "5"}
    assert info["1"]["diameter"] == pytest.approx(models["motor"].diameter * 1000)
    cam = json.loads((root / "camera.json").read_text())
    assert cam["width"] == 320 and cam["depth_scale"] == 0.1
    sc = root / "test" / "000002"
    gt = json.loads((sc / "scene_gt.json").read_text())
    gt_info = json.loads((sc / "scene_gt_info.json").read_text())
    scam = json.loads((sc / "scene_camera.json").read_text())
    assert set(gt) == set(gt_info) == set(scam) == {"0", "1", "2"}
    assert {g["obj_id"] for g in gt["0"]} == {1, 2, 3}  # motor, sun gear (base), housing (loose)
    for entry in gt_info["0"]:
        assert 0.0 <= entry["visib_fract"] <= 1.0 and entry["px_count_visib"] <= entry["px_count_all"]
        assert entry["px_count_valid"] <= entry["px_count_visib"]
    import cv2
    for i, entry in enumerate(gt_info["1"]):
        m = cv2.imread(str(sc / "mask_visib" / f"000001_{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        assert m.sum() == entry["px_count_visib"]
        full = cv2.imread(str(sc / "mask" / f"000001_{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0  # BOP's mask/
        assert full.sum() == entry["px_count_all"] and not (m & ~full).any()
        if m.any():
            x, y, w, h = entry["bbox_visib"]
            ys, xs = np.nonzero(m)
            assert (x, y, w, h) == (xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
    # the occluded sun gear: once the housing is on (step 3 base), the ring hides much of it
    fracs = [e["visib_fract"] for fid, es in json.loads((root / "test" / "000003" / "scene_gt_info.json").read_text()).items()
             for g, e in zip(json.loads((root / "test" / "000003" / "scene_gt.json").read_text())[fid], es) if g["obj_id"] == 2]
    assert min(fracs) < 0.5 and np.mean(fracs) < 0.8


def test_same_seed_same_data_fixed_vs_yaw(planetary, tmp_path):
    asm, models = planetary
    s = RenderSettings(frames=2, seed=5, camera=SMALL_CAM, noise="realsense")
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    for out, seed in ((a, 5), (b, 5), (c, 6)):
        render_dataset(asm, out, replace(s, seed=seed), steps=[1], progress=False, models=models)
    fa, fb, fc = (Dataset(p).frame(1, 1) for p in (a, b, c))
    np.testing.assert_array_equal(fa.depth, fb.depth)
    np.testing.assert_array_equal(fa.rgb, fb.rgb)
    assert not np.array_equal(fa.depth, fc.depth)
    # fixed: the base stays put, only the camera moves; yaw: the base moves
    render_dataset(asm, tmp_path / "fixed", replace(s, base_pose="fixed", frames=3), steps=[1], progress=False, models=models)
    ds = Dataset(tmp_path / "fixed")
    poses = [ds.frame(1, i).T_world_base for i in range(3)]
    cams = [ds.frame(1, i).T_world_camera for i in range(3)]
    assert all(np.allclose(p, poses[0]) for p in poses) and not np.allclose(cams[0], cams[1])
    yaw = [Dataset(a).frame(1, i).T_world_base for i in range(2)]
    assert not np.allclose(yaw[0], yaw[1])


def test_views_per_scene_share_a_placement(planetary, tmp_path):
    """--views-per-scene 2 with 5 frames: placements 0, 0, 1, 1, 2; the frames of a placement show the
    base at one pose (and the same scene: the loose part where it was), from cameras at least 30
    degrees apart; different placements differ. The folder stays a BOP scene (read by the BOP reader)."""
    from apose_studio.data.bop import BopScene

    asm, models = planetary
    s = RenderSettings(frames=5, seed=2, camera=SMALL_CAM, views_per_scene=2)
    render_dataset(asm, tmp_path / "mv", s, steps=[1], progress=False, models=models)
    ds = Dataset(tmp_path / "mv")
    assert ds.placements(1) == {0: [0, 1], 1: [2, 3], 2: [4]}
    f = [ds.frame(1, i) for i in range(5)]
    assert [x.placement for x in f] == [0, 0, 1, 1, 2]
    for a, b in ((0, 1), (2, 3)):
        np.testing.assert_allclose(f[a].T_world_base, f[b].T_world_base, atol=1e-9)
        np.testing.assert_allclose(f[a].poses[asm.step_view(1).part], f[b].poses[asm.step_view(1).part], atol=1e-9)
        assert se3.rotation_angle_deg(f[a].T_world_camera[:3, :3].T @ f[b].T_world_camera[:3, :3]) >= 30.0
    assert not np.allclose(f[0].T_world_base, f[2].T_world_base)
    bop = BopScene(tmp_path / "mv" / "test" / "000001")
    assert len(bop.image_ids()) == 5
    with pytest.raises(RenderError, match="--views-per-scene 6: expected 1 to --frames"):
        render_dataset(asm, tmp_path / "bad", replace(s, views_per_scene=6), steps=[1], progress=False, models=models)


def test_depth_noise_models():
    rng = np.random.default_rng(0)
    flat = np.full((200, 200), 0.5, np.float32)
    assert add_depth_noise(flat, "none", 0.001, rng) is flat
    s05 = np.std(add_depth_noise(flat, "gaussian", 0.001, rng) - flat)
    s10 = np.std(add_depth_noise(flat * 2, "gaussian", 0.001, rng) - flat * 2)
    assert s05 == pytest.approx(0.001, rel=0.05) and s10 / s05 == pytest.approx(4.0, rel=0.1)  # grows with z^2
    step = flat.copy()
    step[:, 100:] = 0.8  # a depth edge
    rs = add_depth_noise(step, "realsense", 0.0, rng, fx=615.0)
    edge_drop = np.mean(rs[:, 99:101] == 0)
    assert 0.4 < edge_drop < 0.8 and np.mean(rs[:, :90] == 0) < 0.01
    assert len(np.unique(rs[rs > 0])) <= 3  # disparity quantisation: a flat depth keeps a few levels


def test_kinect_noise_model():
    """Kinect v1: coarser disparity steps than the RealSense model, the projector's shadow on the far
    surface left of a nearer one (width = the disparity difference), no depth on dark surfaces."""
    from apose_studio.geometry.noise import projector_shadow

    rng = np.random.default_rng(1)
    fx = 580.0
    scene = np.full((60, 200), 1.0, np.float32)
    scene[:, 100:150] = 0.8  # a nearer box; the projector (75 mm to the right) shades the far surface left of it
    k = add_depth_noise(scene, "kinect", 0.0, rng, fx=fx)
    width = fx * 0.075 * (1 / 0.8 - 1 / 1.0)  # 10.9 px
    row = k[30]
    assert (row[100 - int(width) + 1:98] == 0).all() and (row[:100 - int(width) - 3] > 0).mean() > 0.95
    assert (row[152:] > 0).mean() > 0.95  # nothing is shaded right of the box
    shadow = projector_shadow(scene, fx * 0.075)
    assert shadow[:, 100 - int(width) + 1:100].all() and not shadow[:, 100:].any()
    ramp = np.tile(np.linspace(0.95, 1.05, 400, dtype=np.float32), (4, 1))
    levels = np.unique(add_depth_noise(ramp, "kinect", 0.0, rng, fx=fx))
    gaps = np.diff(levels[levels > 0])
    assert np.median(gaps) == pytest.approx(1.0 / (580 * 0.075 * 8), rel=0.1)  # 1/8 px of Kinect's disparity: 2.9 mm
    flat = np.full((100, 100), 1.0, np.float32)
    dark = np.zeros((100, 100, 3), np.uint8)
    dark[:, 50:] = 120
    kd = add_depth_noise(flat, "kinect", 0.0, rng, fx=fx, rgb=dark)
    assert (kd[:, :50] == 0).mean() > 0.75 and (kd[:, 60:] == 0).mean() < 0.02


def test_frame_noise_is_measured_from_the_depth_itself():
    from apose_studio.geometry.noise import estimate_depth_noise

    rng = np.random.default_rng(2)
    v, u = np.mgrid[0:240, 0:320]
    plane = (0.6 + 0.0004 * u + 0.0002 * v).astype(np.float32)  # a tilted table
    for sigma in (0.0005, 0.002):
        noisy = plane + rng.normal(0, sigma, plane.shape).astype(np.float32)
        assert estimate_depth_noise(noisy) == pytest.approx(sigma, rel=0.15)
    assert estimate_depth_noise(plane) < 1e-4
    assert np.isnan(estimate_depth_noise(np.zeros((10, 10), np.float32)))
    # in a region: the median of the second differences centred there, as the whole frame's give them (the
    # function works on the region's box only); two noise levels side by side tell a wrong crop
    noisy = plane + rng.normal(0, 0.0005, plane.shape).astype(np.float32)
    noisy[:, 160:] += rng.normal(0, 0.004, (240, 160)).astype(np.float32)
    noisy[rng.random(noisy.shape) < 0.05] = 0.0
    for y0, y1, x0, x1 in ((40, 90, 100, 170), (0, 240, 150, 165), (0, 12, 300, 320), (200, 240, 0, 3)):
        region = np.zeros(noisy.shape, bool)
        region[y0:y1, x0:x1] = True
        vals = []
        for a, r in ((noisy, region), (noisy.T, region.T)):
            d2 = a[:, :-2] - 2 * a[:, 1:-1] + a[:, 2:]
            ok = (a[:, :-2] > 0) & (a[:, 1:-1] > 0) & (a[:, 2:] > 0) & r[:, 1:-1]
            vals.append(np.abs(d2[ok]))
        vals = np.concatenate(vals)
        want = float(np.median(vals) * 1.4826 / np.sqrt(6.0)) if len(vals) >= 200 else float("nan")
        got = estimate_depth_noise(noisy, region)
        assert got == want or (np.isnan(got) and np.isnan(want)), ((y0, y1, x0, x1), got, want)


def test_bad_inputs_are_refused(planetary, tmp_path):
    asm, models = planetary
    ok = RenderSettings(frames=1, camera=SMALL_CAM)
    with pytest.raises(RenderError, match="step 9 does not exist; planetary_reducer has steps 1..4"):
        render_dataset(asm, tmp_path / "x", ok, steps=[9], progress=False, models=models)
    with pytest.raises(RenderError, match="--pitch-range 40,40: expected min,max"):
        render_dataset(asm, tmp_path / "x", replace(ok, pitch_range_deg=(40, 40)), progress=False, models=models)
    with pytest.raises(RenderError, match="--frames 0"):
        render_dataset(asm, tmp_path / "x", replace(ok, frames=0), progress=False, models=models)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(AposeError, match="exists and is not a folder"):
        render_dataset(asm, blocker, ok, progress=False, models=models)
    full = tmp_path / "full"
    full.mkdir()
    (full / "mine.txt").write_text("precious")
    with pytest.raises(AposeError, match="folder is not empty; .* --overwrite"):
        render_dataset(asm, full, ok, progress=False, models=models)
    with pytest.raises(AposeError, match=r"holds files that no apose render wrote \(mine.txt\)"):
        render_dataset(asm, full, ok, steps=[1], overwrite=True, progress=False, models=models)
    assert sorted(p.name for p in full.iterdir()) == ["mine.txt"] and (full / "mine.txt").read_text() == "precious"
    with pytest.raises(AposeError, match="cannot create this folder"):  # a file where a folder must go
        render_dataset(asm, blocker / "ds", ok, progress=False, models=models)


def test_overwrite_deletes_only_the_datasets_own_files(planetary, tmp_path):
    """--overwrite (and the demo) replace a dataset; a user's file anywhere inside stops them, untouched."""
    asm, models = planetary
    ok = RenderSettings(frames=2, seed=1, noise="none")
    out = tmp_path / "ds"
    render_dataset(asm, out, ok, steps=[1, 2], progress=False, models=models)
    import json

    listed = json.loads((out / "dataset_info.json").read_text())["files"]
    on_disk = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert sorted(listed + ["dataset_info.json"]) == on_disk and "test/000001/scene_gt.json" in listed
    for mine in ("test/test_mine.py", "models/my_model.bin"):
        (out / mine).write_text("precious")
        with pytest.raises(AposeError, match=mine.replace(".", r"\.")):
            render_dataset(asm, out, ok, steps=[1], overwrite=True, progress=False, models=models)
        assert (out / mine).read_text() == "precious" and (out / "test/000002/scene_gt.json").is_file()
        (out / mine).unlink()
    render_dataset(asm, out, ok, steps=[1], overwrite=True, progress=False, models=models)
    assert not (out / "test/000002").exists()  # the old dataset's step 2 went with it
    assert (out / "test/000001/scene_gt.json").is_file()


def test_a_second_render_into_the_same_folder_is_refused(planetary, tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from apose_studio.data.outdir import OutputLock

    asm, models = planetary
    out = tmp_path / "race"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import sys; from apose_studio.data.outdir import OutputLock; "
                               f"l = OutputLock({str(out)!r}).__enter__(); print('held', flush=True); sys.stdin.read()"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(AposeError, match=f"in use by PID {holder.pid}"):
            render_dataset(asm, out, RenderSettings(frames=1, noise="none"), steps=[1], progress=False, models=models)
    finally:
        holder.send_signal(signal.SIGKILL)  # dies holding it: the kernel releases the lock, the file stays
        holder.wait()
    assert (out / ".apose-render.lock").read_text() == str(holder.pid)
    render_dataset(asm, out, RenderSettings(frames=1, noise="none"), steps=[1], progress=False, models=models)
    assert not (out / ".apose-render.lock").exists()
    with OutputLock(out):
        with pytest.raises(AposeError, match=f"in use by PID {os.getpid()}"):  # while this process renders there
            with OutputLock(out):
                pass


def test_interrupted_render_leaves_finished_frames_readable(planetary, tmp_path, monkeypatch):
    import apose_studio.synth.render as R

    asm, models = planetary
    real, calls = R.render_frame, []

    def flaky(*a, **k):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(R, "render_frame", flaky)
    with pytest.raises(KeyboardInterrupt):
        render_dataset(asm, tmp_path / "ds", RenderSettings(frames=10, camera=SMALL_CAM), steps=[2], progress=False, models=models)
    ds = Dataset(tmp_path / "ds")
    assert ds.image_ids(2) == [0, 1, 2]
    assert ds.frame(2, 2).depth.max() > 0


def test_reader_errors(planetary_ds, tmp_path):
    ds, _ = planetary_ds
    with pytest.raises(DatasetError, match="step 2 has no frame 99; frames are 0..2"):
        ds.frame(2, 99)
    with pytest.raises(DatasetError, match="not an apose dataset"):
        Dataset(tmp_path)


def test_real_capture_folder(tmp_path):
    import cv2

    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = 200
    depth = np.full((48, 64), 500, np.uint16)  # 500 mm at depth_scale 1.0
    cv2.imwrite(str(tmp_path / "rgb.png"), rgb[..., ::-1])
    cv2.imwrite(str(tmp_path / "depth.png"), depth)
    (tmp_path / "camera.json").write_text(json.dumps({"fx": 60, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1.0}))
    f = open_frames(tmp_path)
    assert f.rgb[0, 0, 0] == 200 and f.depth[0, 0] == pytest.approx(0.5)
    assert f.camera.width == 64 and f.masks == {}
    # no extrinsics: the world sits on the plane the depth shows (a flat 500 mm view): the camera 0.5 m above
    # it, looking straight down (its z along the world's -z)
    np.testing.assert_allclose(f.T_world_camera[:3, 3], [0, 0, 0.5], atol=1e-6)
    np.testing.assert_allclose(f.T_world_camera[:3, 2], [0, 0, -1], atol=1e-6)
    # BOP's form: cam_K row-major, camera pose in mm
    (tmp_path / "camera.json").write_text(json.dumps({"cam_K": [60, 0, 32, 0, 61, 24, 0, 0, 1], "depth_scale": 1.0,
                                                      "cam_R_w2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_w2c": [0, 0, 100]}))
    f = load_capture(tmp_path)
    assert (f.camera.fx, f.camera.fy, f.camera.cx, f.camera.cy) == (60, 61, 32, 24)
    np.testing.assert_allclose(f.T_world_camera[:3, 3], [0, 0, -0.1])
    bad = [({"fx": 60}, "missing fy, cx, cy: give the intrinsics"),
           ({"fx": 60, "fy": 60, "cx": 32, "cy": 24}, "missing depth_scale"),
           ({"fx": 0, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1}, "fx and fy must be positive"),
           ({"fx": -60, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1}, "fx and fy must be positive"),
           ({"fx": 60, "fy": 60, "cx": 320, "cy": 240, "depth_scale": 1}, "principal point .* centre of a 640x480 image, not of this 64x48"),
           ({"fx": 60, "fy": 60, "cx": 70, "cy": 24, "depth_scale": 1}, "principal point .* outside the 64x48 image"),
           ({"fx": 60, "fy": 60, "cx": 0, "cy": 0, "depth_scale": 1}, "outside the 64x48 image or on its edge"),
           ({"fx": 60, "fy": 60, "cx": 32, "cy": 24, "width": 128, "height": 96, "depth_scale": 1},
            "width is 128 but the images are 64x48"),
           ({"cam_K": [60, 0, 32], "depth_scale": 1}, "cam_K must be 9 numbers"),
           ({"fx": 60, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 0.001}, "depth_scale 0.001 from .*camera.json: is depth_scale too small"),
           ({"fx": "a", "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1}, "fx must be a finite number")]
    for cam, message in bad:
        (tmp_path / "camera.json").write_text(json.dumps(cam))
        with pytest.raises(DatasetError, match=message):
            load_capture(tmp_path)
    (tmp_path / "camera.json").write_text(json.dumps({"fx": 60, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1.0}))
    cv2.imwrite(str(tmp_path / "depth.png"), depth[:40])
    with pytest.raises(DatasetError, match="depth.png is 64x40 but rgb.png is 64x48"):
        load_capture(tmp_path)
    cv2.imwrite(str(tmp_path / "depth.png"), (depth // 4).astype(np.uint8))
    with pytest.raises(DatasetError, match="a uint8 depth image; expected 16-bit"):
        load_capture(tmp_path)
    (tmp_path / "depth.png").unlink()
    (tmp_path / "depth.png").mkdir()
    with pytest.raises(DatasetError, match="a folder, not a file"):
        load_capture(tmp_path)


@pytest.mark.parametrize("name", ["helical_gearbox", "planetary_reducer", "fidget"])
def test_five_frames_per_step_at_full_size(name, tmp_path, request):
    path = request.getfixturevalue("fidget_yaml") if name == "fidget" else SAMPLES / name / "assembly.yaml"
    asm = load_assembly(path)
    summary = render_dataset(asm, tmp_path / "ds", RenderSettings(frames=5, noise="realsense"), progress=False)
    ds = Dataset(tmp_path / "ds")
    assert summary["frames"] == 5 * len(asm.steps)
    for step in ds.steps:
        f = ds.frame(step, 4)
        assert f.rgb.shape == (480, 640, 3)
        assert f.base_mask().sum() > 500, (step, f.base_mask().sum())  # the base object is in view


def test_a_capture_without_extrinsics_gets_the_table_as_its_world(gearbox_dataset, tmp_path):
    """The camera's height above the table and its tilt, from the depth alone, match the renderer's truth."""
    from ..conftest import write_capture

    fr = Dataset(gearbox_dataset).frame(1, 0)
    cap = write_capture(fr, tmp_path / "cap", {"cam_K": fr.camera.K.reshape(-1).tolist(), "depth_scale": 1.0})
    got = load_capture(cap).T_world_camera
    true = fr.T_world_camera  # the renderer's table is z = 0, z up
    assert abs(got[2, 3] - true[2, 3]) < 0.003, (got[2, 3], true[2, 3])  # camera height above the table
    assert abs(got[2, 2] - true[2, 2]) < 0.01  # the tilt of the optical axis against the table's normal


def _one_frame(asm, models, settings, step=1, im_id=0):
    """One frame as render_dataset makes it (seeded per frame), with its scene and clean depth."""
    from apose_studio.assembly.mesh import base_mesh
    from apose_studio.geometry.raycast import RayGrid
    from apose_studio.synth.frame import render_frame

    view = asm.step_view(step)
    return render_frame(models, view, settings, RayGrid(settings.camera),
                        np.random.default_rng([settings.seed, step, im_id]), base_mesh(models, view)), view


@pytest.mark.parametrize("im_id", range(3))
def test_a_stacked_object_lies_on_the_base(planetary, im_id):
    """--clutter stacked: the last object touches the base's surface (within 1 mm, measured by Open3D's
    distance from trimesh's samples of it to the base mesh, not by the code that placed it) and lies
    higher than the base's middle."""
    asm, models = planetary
    s = RenderSettings(frames=1, seed=3, clutter="stacked", camera=SMALL_CAM)
    fr, view = _one_frame(asm, models, s, im_id=im_id)
    flat = fr.scene.objects[-1]
    assert flat.part is None and flat.mesh.extents[2] < 0.35 * models["motor"].mesh.extents[2]
    base = fr.scene.objects[0]
    base_world = base.mesh.copy().apply_transform(base.T_world_obj)
    surface = se3.transform_points(flat.T_world_obj, flat.mesh.sample(3000, seed=0))
    assert surface_distance(base_world, surface).min() < 0.001  # touching the base
    assert surface[:, 2].min() > 0.5 * base_world.bounds[1][2]  # on its top, not on the table beside it


def test_hidden_leaves_a_fifth_to_a_third_of_the_base_visible(planetary):
    """--clutter hidden with the camera 20-50 degrees up: an object stands between the base and the camera, and
    the base's visible share (the renderer's labels over its unoccluded silhouette) is at most 35 % (20-35 %
    by that object alone; the loose part and the distractors may hide more) and never nothing."""
    asm, models = planetary
    s = RenderSettings(frames=1, seed=3, clutter="hidden", pitch_range_deg=(20.0, 50.0), camera=SMALL_CAM)
    shares = []
    for im_id in range(4):
        fr, view = _one_frame(asm, models, s, step=2, im_id=im_id)
        n_base = fr.scene.n_base
        full = np.zeros(fr.labels.shape, bool)
        for i in range(n_base):
            if i in fr.hits.windows:
                (v0, v1, u0, u1), m = fr.hits.windows[i]
                full[v0:v1, u0:u1] |= m
        shares.append(float((fr.labels[full] < n_base).sum()) / full.sum())
        screen = fr.scene.objects[-1]
        eye = fr.T_world_camera[:3, 3]
        assert np.linalg.norm(screen.T_world_obj[:2, 3] - eye[:2]) < np.linalg.norm(fr.scene.base_centre[:2] - eye[:2])
    assert all(0.05 <= v <= 0.36 for v in shares) and np.median(shares) >= 0.12, shares


def test_sensor_effects_are_recorded_and_reproducible(planetary, tmp_path):
    """--depth-bias adds its millimetres to every reading and --misregistration shifts the depth against the
    colour image by the recorded depth_shift_px (the same scene, the colour image and masks unchanged)."""
    asm, models = planetary
    base = RenderSettings(frames=2, seed=4, camera=SMALL_CAM)
    render_dataset(asm, tmp_path / "plain", base, steps=[1], progress=False, models=models)
    render_dataset(asm, tmp_path / "real", replace(base, depth_bias_m=0.003, misregistration_px=3.0), steps=[1],
                   progress=False, models=models)
    plain, real = Dataset(tmp_path / "plain"), Dataset(tmp_path / "real")
    frames = json.loads((tmp_path / "real" / "test" / "000001" / "scene_assembly.json").read_text())["frames"]
    for im_id in (0, 1):
        a, b = plain.frame(1, im_id), real.frame(1, im_id)
        du, dv = frames[str(im_id)]["depth_shift_px"]
        assert 2 <= np.hypot(du, dv) <= 4
        h, w = a.depth.shape
        moved = np.zeros_like(a.depth)  # the plain depth moved as the render says, plus the bias
        moved[max(dv, 0):h + min(dv, 0), max(du, 0):w + min(du, 0)] = a.depth[max(-dv, 0):h + min(-dv, 0),
                                                                               max(-du, 0):w + min(-du, 0)]
        both = (moved > 0) & (b.depth > 0)
        assert both.sum() > 0.5 * both.size
        np.testing.assert_allclose(b.depth[both] - moved[both], 0.003, atol=1.5e-4)
        np.testing.assert_array_equal(a.base_mask(), b.base_mask())  # masks and poses keep to the colour image
        np.testing.assert_array_equal(a.rgb, b.rgb)
    info = json.loads((tmp_path / "real" / "dataset_info.json").read_text())["settings"]
    assert info["depth_bias_m"] == 0.003 and info["misregistration_px"] == 3.0


def test_bleed_widens_near_surfaces_in_depth_over_farther_ones(planetary, tmp_path):
    """--bleed 2: the depth round the base (the renderer's own visible mask, not the code under test) reads the
    base's depth up to 2 px beyond its outline where the table lies far behind it, and nowhere farther out; the
    colour image and the masks stay as they were, and the dataset records the setting."""
    asm, models = planetary
    base = RenderSettings(frames=2, seed=4, camera=SMALL_CAM)
    render_dataset(asm, tmp_path / "plain", base, steps=[1], progress=False, models=models)
    render_dataset(asm, tmp_path / "bled", replace(base, bleed_px=2), steps=[1], progress=False, models=models)
    plain, bled = Dataset(tmp_path / "plain"), Dataset(tmp_path / "bled")
    ring_cells = 0
    for im_id in (0, 1):
        a, b = plain.frame(1, im_id), bled.frame(1, im_id)
        np.testing.assert_array_equal(a.base_mask(), b.base_mask())
        np.testing.assert_array_equal(a.rgb, b.rgb)
        changed = a.depth != b.depth
        assert changed.any()
        assert np.all(b.depth[changed] < a.depth[changed]) and np.all(a.depth[changed] > 0)  # only ever nearer
        assert np.array_equal(a.depth == 0, b.depth == 0)  # holes stay holes
        mask = a.base_mask()
        k = lambda n: np.ones((2 * n + 1, 2 * n + 1), np.uint8)  # noqa: E731
        base_near = cv2.erode(np.where(mask & (a.depth > 0), a.depth, np.inf).astype(np.float32), k(1),
                              borderType=cv2.BORDER_CONSTANT, borderValue=float("inf"))  # the base's depth 1 px away
        # pixels just outside the base's outline whose surface lies well behind the base's edge there
        edge_ring = ~mask & (a.depth > 0) & np.isfinite(base_near) & (a.depth > base_near + 0.03)
        assert edge_ring.sum() > 20
        assert np.all(b.depth[edge_ring] <= base_near[edge_ring])  # read the base's depth (or a nearer one) now
        nearest = cv2.erode(np.where(a.depth > 0, a.depth, np.inf).astype(np.float32), k(2),
                            borderType=cv2.BORDER_CONSTANT, borderValue=float("inf"))
        assert not (changed & (nearest > a.depth - 0.004)).any()  # nothing without a nearer surface within 2 px
        ring_cells += int(edge_ring.sum())
    info = json.loads((tmp_path / "bled" / "dataset_info.json").read_text())["settings"]
    assert info["bleed_px"] == 2 and ring_cells > 0
    with pytest.raises(RenderError, match="--bleed 9"):
        replace(base, bleed_px=9).validate()


def test_textured_prints_patterns_on_the_table(planetary):
    """--clutter textured: the table is no longer one grey (its luminance varies several times more than the
    sensor noise alone makes it vary)."""
    asm, models = planetary
    spread = {}
    for kinds in ("", "textured"):
        fr, _ = _one_frame(asm, models, RenderSettings(frames=1, seed=4, clutter=kinds, camera=SMALL_CAM))
        table = fr.labels == fr.scene.table_label
        lum = fr.rgb[table].astype(float) @ [0.299, 0.587, 0.114]
        spread[kinds] = np.percentile(lum, 95) - np.percentile(lum, 5)
    assert spread["textured"] > 2 * spread[""], spread


def test_bad_render_conditions_are_refused(planetary, tmp_path):
    asm, models = planetary
    ok = RenderSettings(frames=2, camera=SMALL_CAM)
    for bad, match in [(dict(clutter="bench,piles"), "'piles' is not a kind of clutter"),
                       (dict(clutter="hidden", views_per_scene=2), "--clutter hidden with --views-per-scene"),
                       (dict(depth_bias_m=0.2), "--depth-bias 200"), (dict(depth_bias_m=float("nan")), "--depth-bias"),
                       (dict(misregistration_px=-1.0), "--misregistration -1"),
                       (dict(base_fill=(0.5, 0.2)), "--base-fill 0.5,0.2")]:
        with pytest.raises(RenderError, match=match):
            render_dataset(asm, tmp_path / "x", replace(ok, **bad), progress=False, models=models)
