"""Shared fixtures: paths to the real test data beside the repo, and tiny synthetic assemblies."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest
import trimesh

REPO = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("APOSE_SHARED", REPO.parent / "shared"))
FIDGET = SHARED / "data" / "fidget_helical" / "assembly.yaml"
SAMPLES = REPO / "sample_assemblies"


@pytest.fixture
def fidget_yaml() -> Path:
    if not FIDGET.is_file():
        reason = f"real CAD test data not found at {FIDGET} (the ../shared folder beside the repo)"
        if os.environ.get("CI"):  # in CI a missing ../shared fails, as a missing chromium does (tests/e2e)
            pytest.fail(reason)
        pytest.skip(reason)
    return FIDGET


TINY_YAML = """\
format: apose-assembly/1
name: tiny
units: mm
parts:
  plate: {mesh: plate.stl}
  peg:
    mesh: peg.stl
    color: [1, 0, 0]
    symmetry: {axis: [0, 0, 1], order: 0}
  cap: {mesh: cap.stl}
steps:
  - part: peg
    base: [plate]
    pose_in_base:
      translation: [10, 0, 5]
      rotation: {euler_deg: [0, 0, 90], order: xyz}
  - part: cap
    base: [peg, plate]
    pose_in_base:
      translation: [0, 10, 0]
"""


@pytest.fixture
def tiny_dir(tmp_path) -> Path:
    """A 3-part assembly in millimetres: a plate, a peg on it, a cap on the peg."""
    trimesh.creation.box((60, 40, 4)).export(tmp_path / "plate.stl")
    trimesh.creation.cylinder(radius=4, height=20, sections=32).export(tmp_path / "peg.stl")
    trimesh.creation.box((12, 12, 3)).export(tmp_path / "cap.stl")
    (tmp_path / "assembly.yaml").write_text(TINY_YAML)
    return tmp_path


@pytest.fixture(scope="session")
def gearbox_dataset(tmp_path_factory) -> Path:
    """Two RealSense-like views of gearbox step 1 with the base at the CAD's orientation (rendered once)."""
    from apose_studio.assembly.model import load_assembly
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    out = tmp_path_factory.mktemp("studio") / "ds"
    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=2, base_pose="fixed", noise="realsense", seed=5), steps=[1],
                   progress=False)
    return out


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_capture(frame, folder: Path, camera: dict | None = None) -> Path:
    """A real-capture folder (rgb.png, depth.png in mm, camera.json) from a rendered frame; `camera` replaces
    the camera file's contents (default: fx, fy, cx, cy and depth_scale 1.0, no extrinsics)."""
    import json

    import cv2
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "rgb.png"), frame.rgb[..., ::-1])
    cv2.imwrite(str(folder / "depth.png"), (frame.depth * 1000).astype(np.uint16))
    cam = frame.camera
    (folder / "camera.json").write_text(json.dumps(camera or {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                                                              "depth_scale": 1.0}))
    return folder


@pytest.fixture(scope="session")
def clutter_dataset(tmp_path_factory) -> Path:
    """Kinect-like cluttered benches (objects standing against the base, base off-centre): gearbox step 2,
    three views (rendered once)."""
    from apose_studio.assembly.model import load_assembly
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    out = tmp_path_factory.mktemp("clutter") / "ds"
    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=3, noise="kinect", clutter=True, seed=3), steps=[2], progress=False)
    return out


@pytest.fixture(scope="session")
def engine_dataset(tmp_path_factory) -> Path:
    """The engine-head sample's seat 1 (a region of the head) on a cluttered bench, RealSense-like, two views 0.45-0.8 m
    away (rendered once)."""
    from apose_studio.assembly.model import load_assembly
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    out = tmp_path_factory.mktemp("engine") / "ds"
    asm = load_assembly(SAMPLES / "engine_head" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=2, noise="realsense", clutter=True, seed=5, distance_range_m=(0.45, 0.8)),
                   steps=[1], progress=False)
    return out


def region_box(frame, asm, margin: int = 10) -> tuple[int, int, int, int]:
    """The box a user draws round what the camera sees of `frame`'s step's seat (a region): where the region's
    ray-cast surface is the head's first surface, within the renderer's visible mask of the head."""
    import numpy as np

    from apose_studio.assembly.mesh import load_parts
    from apose_studio.geometry.raycast import raycast_depth

    models = load_parts(asm)
    seat = asm.steps[frame.step - 1].base[0]
    z_region = raycast_depth(models[seat].region, frame.T_world_base, frame.T_world_camera, frame.camera)
    z_head = raycast_depth(models[seat].mesh, frame.T_world_base, frame.T_world_camera, frame.camera)
    seen = np.isfinite(z_region) & (z_region <= z_head + 1e-4) & frame.base_mask()
    assert seen.sum() > 300, "the seat is out of view in this render"
    ys, xs = np.nonzero(seen)
    return int(xs.min()) - margin, int(ys.min()) - margin, int(xs.max()) + 1 + margin, int(ys.max()) + 1 + margin


@pytest.fixture(scope="session")
def live_approach(tmp_path_factory) -> list:
    """A camera closing in on gearbox step 2's base over a cluttered bench in 60 small steps (a hand-held or
    eye-in-hand stream's, ~8 mm a frame), RealSense-like noise: the frames of the live-camera tests."""
    from apose_studio.assembly.model import load_assembly
    from apose_studio.data.dataset import Dataset
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    out = tmp_path_factory.mktemp("live") / "ds"
    render_dataset(load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml"), out,
                   RenderSettings(frames=60, trajectory="approach", noise="realsense", clutter=("bench",), seed=2),
                   steps=[2], progress=False)
    ds = Dataset(out)
    return [ds.frame(2, i) for i in ds.image_ids(2)]


_PART_MODELS: dict = {}


def mssd_to_truth(T_est, T_true, assembly: Path, part: str) -> float:
    """MSSD (metres) of an estimated T_*_part against the renderer's, modulo the part's own symmetries
    (tests/geometry/test_metrics.py pins the metric to hand-computed values). Unlike a translation check
    it catches a pose that is turned: its surface points move by the rotation error times their lever."""
    import numpy as np

    from apose_studio.assembly.mesh import load_parts
    from apose_studio.assembly.model import load_assembly
    from apose_studio.geometry.metrics import mssd

    key = str(Path(assembly).resolve())
    if key not in _PART_MODELS:
        _PART_MODELS[key] = load_parts(load_assembly(assembly))
    model = _PART_MODELS[key][part]
    return float(mssd(np.asarray(T_est, float), np.asarray(T_true, float), model.samples, model.symmetries))


def rendered_frame(assembly: Path, step: int, im_id: int, **settings):
    """Frame `im_id` of step `step` exactly as `apose render --seed S ...` writes it into a dataset (each frame is
    seeded on its own, so it renders alone): its depth noise, depth in 0.1 mm steps, JPEG colour (quality 95),
    the renderer's own visible masks and poses. `settings`: RenderSettings fields (seed, noise, clutter, ...)."""
    import cv2
    import numpy as np

    from apose_studio.assembly.mesh import base_mesh, load_parts
    from apose_studio.assembly.model import load_assembly
    from apose_studio.data.dataset import Frame
    from apose_studio.geometry import se3
    from apose_studio.geometry.raycast import RayGrid
    from apose_studio.synth.frame import RenderSettings, render_frame

    asm = load_assembly(assembly)
    models = load_parts(asm)
    s = RenderSettings(**settings)
    if asm.camera is not None:
        s = dataclasses.replace(s, camera=asm.camera)
    view = asm.step_view(step)
    fr = render_frame(models, view, s, RayGrid(s.camera), np.random.default_rng([s.seed, step, im_id]),
                      base_mesh(models, view))
    depth_u16 = np.clip(np.round(fr.depth * 10000.0), 0, 65535).astype(np.uint16)  # as the dataset writes and reads it
    depth = depth_u16.astype(np.float32) * np.float32(0.1 / 1000.0)
    jpeg = cv2.imencode(".jpg", cv2.cvtColor(fr.rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
    rgb = cv2.cvtColor(cv2.imdecode(jpeg, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    masks = {o.part: fr.labels == i for i, o in enumerate(fr.scene.objects) if o.part in view.T_base_members}
    T_world_base = fr.scene.T_world_base
    T_cam_world = se3.inv(fr.T_world_camera)  # the camera pose as scene_camera.json keeps it (R, t in mm) and reads it
    R, t = T_cam_world[:3, :3].reshape(-1).tolist(), (T_cam_world[:3, 3] * 1000.0).tolist()
    T_world_camera = se3.inv(se3.make_T(np.asarray(R, float).reshape(3, 3), np.asarray(t, float).reshape(3) / 1000.0))
    return Frame(rgb=rgb, depth=depth, camera=s.camera, T_world_camera=T_world_camera, masks=masks,
                 poses={}, step=step, part=view.part, base=tuple(view.base), T_base_part=view.T_base_part,
                 T_world_base=T_world_base, T_world_part=T_world_base @ view.T_base_part, im_id=im_id)


def true_shift(shifted, unshifted, r: int = 6) -> tuple[int, int]:
    """(du, dv) with shifted[v, u] == unshifted[v - dv, u - du] away from the border (np.roll, compared): how far
    the renderer moved a depth image against the same render unshifted."""
    import numpy as np

    inner = (slice(r, -r), slice(r, -r))
    for dv in range(-r, r + 1):
        for du in range(-r, r + 1):
            if np.array_equal(np.roll(unshifted, (dv, du), axis=(0, 1))[inner], shifted[inner]):
                return du, dv
    raise AssertionError("no shift maps one render onto the other")


def plain_bop_scene(src: Path, dst: Path) -> Path:
    """A copy of a rendered scene folder (test/NNNNNN) with BOP's own files only: what a BOP dataset holds."""
    import shutil

    dst.mkdir(parents=True)
    for name in ("scene_camera.json", "scene_gt.json", "rgb", "depth", "mask_visib"):
        (shutil.copytree if (src / name).is_dir() else shutil.copy)(src / name, dst / name)
    return dst


def two_carriers(folder: Path) -> Path:
    """An assembly whose part has its base's shape (two carriers, the part with a grasp and an approach): a loose
    part's true pose is the base's, so a pick estimate can be checked against the renderer's."""
    import shutil

    shutil.copy(SAMPLES / "planetary_reducer" / "carrier.ply", folder / "carrier.ply")
    (folder / "two.yaml").write_text(
        "format: apose-assembly/1\nname: two\nunits: mm\nparts:\n  carrier: {mesh: carrier.ply}\n  twin:\n"
        "    mesh: carrier.ply\n    grasps:\n      - name: shaft\n        pose_in_part: {translation: [0, 0, 16], "
        "rotation: {euler_deg: [180, 0, 0], order: xyz}}\n        width: 8\nsteps:\n  - part: twin\n    base: [carrier]\n"
        "    pose_in_base: {translation: [60, 0, 0]}\n    approach: {direction: [0, 0, -1], distance: 40}\n")
    return folder / "two.yaml"
