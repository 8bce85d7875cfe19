"""The studio's server side, driven through the same callbacks the browser triggers (no browser here;
tests/e2e drives the real page). Each action goes through `_guarded`, as a click does."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from apose_studio import se3
from apose_studio.assembly import load_assembly
from apose_studio.studio import MAX_UPLOAD_BYTES, serve

from .conftest import SAMPLES, free_port


class Click:
    client = None


@pytest.fixture
def studio(monkeypatch, tmp_path):
    made = []

    def start(assembly=None, dataset=None, root=tmp_path):
        server, st = serve(assembly, dataset, host="127.0.0.1", port=free_port(), root=root)
        st.notes = []
        monkeypatch.setattr(st, "notify", lambda client, title, body, error=False: st.notes.append((title, body, error)))
        made.append(server)
        return st

    yield start
    for s in made:
        s.stop()


def act(st, fn, *args):
    st._guarded("test")(lambda c: fn(*args, c))(Click())


def errors(st):
    return [n for n in st.notes if n[2]]


@pytest.fixture
def gearbox_copy(tmp_path) -> Path:
    dst = tmp_path / "gearbox"
    shutil.copytree(SAMPLES / "helical_gearbox", dst)
    return dst / "assembly.yaml"


def test_open_add_step_type_pose_save(studio, gearbox_copy, tmp_path):
    st = studio(gearbox_copy)
    assert st.problems == [] and set(st.mesh_handles) == {"casing", "pinion", "wheel", "lid"}
    trimesh.creation.cylinder(radius=0.004, height=0.02).export(tmp_path / "pin.stl")  # in metres: a unit warning
    st.f_mesh.value = str(tmp_path / "pin.stl")
    act(st, lambda c: st._on_add_parts(c))
    assert "pin" in st.asm.parts
    assert any("looks like it is in m" in n[1] for n in errors(st))  # 0.02 "mm" across is suspicious
    act(st, st._step_action, "Add")
    assert st.step_index == 3 and st.asm.steps[3].part == "pin"
    st.f_t.value = (5.0, -2.5, 30.0)  # typing fires the same callback as the browser
    st.f_r.value = (0.0, 90.0, 0.0)
    T = st.asm.steps[3].T_base_part
    np.testing.assert_allclose(T[:3, 3], [0.005, -0.0025, 0.030], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], se3.euler_deg_to_matrix([0, 90, 0], "xyz"), atol=1e-9)
    act(st, st._on_save)
    on_disk = yaml.safe_load(gearbox_copy.read_text())
    assert on_disk["steps"][3]["part"] == "pin" and on_disk["steps"][3]["pose_in_base"]["translation"] == [5, -2.5, 30]
    back = load_assembly(gearbox_copy)
    np.testing.assert_allclose(back.steps[3].T_base_part, T, atol=1e-9)
    assert ("Saved", f"{gearbox_copy.resolve()} (previous version: assembly.yaml.bak)", False) in st.notes


def test_gizmo_drag_updates_the_typed_pose_with_snapping(studio, gearbox_copy):
    st = studio(gearbox_copy)
    st.step_index = 0
    st._refresh_assembly_scene()
    g = st.nodes["/assembly/gizmo"]
    T_world_base = st._preview["casing"]
    T = T_world_base @ se3.make_T(se3.euler_deg_to_matrix([0, 0, 31.0], "xyz"), np.array([0.01234, 0.0, 0.0147]))
    g._impl.wxyz, g._impl.position = se3.matrix_to_quat_wxyz(T[:3, :3]), T[:3, 3]
    from viser._scene_handles import TransformControlsEvent  # what viser passes (tests/e2e drags with the mouse)

    for cb in g._impl_aux.update_cb:
        cb(TransformControlsEvent(client=None, client_id=None, target=g, phase="update"))
    np.testing.assert_allclose(st.asm.steps[0].T_base_part[:3, 3], [0.0125, 0, 0.0145], atol=1e-9)  # moves at once
    for cb in g._impl_aux.update_cb:
        cb(TransformControlsEvent(client=None, client_id=None, target=g, phase="end"))
    assert errors(st) == []
    np.testing.assert_allclose(st.f_t.value, (12.5, 0.0, 14.5), atol=1e-6)  # snapped to 0.5 mm
    np.testing.assert_allclose(st.f_r.value, (0.0, 0.0, 30.0), atol=1e-6)  # and to 5°
    np.testing.assert_allclose(st.asm.steps[0].T_base_part[:3, 3], [0.0125, 0, 0.0145], atol=1e-9)


def test_bad_input_is_reported_and_nothing_is_lost(studio, gearbox_copy, tmp_path):
    st = studio(gearbox_copy)
    before = st.asm
    broken = tmp_path / "broken.yaml"
    broken.write_text("format: apose-assembly/1\nparts: [oops\n")
    st.f_path.value = str(broken)
    act(st, st._on_open)
    assert "YAML syntax error" in errors(st)[-1][1] and st.asm is before
    # a step reordered into an invalid order: flagged, and Save refuses instead of writing a bad file
    st.step_index = 1
    act(st, st._step_action, "Up")
    assert st.problems and "placed only by a later step" in st.status_md.content
    st.f_path.value = str(tmp_path / "out.yaml")
    act(st, st._on_save)
    assert not (tmp_path / "out.yaml").exists() and "placed only by a later step" in errors(st)[-1][1]
    act(st, st._step_action, "Down")
    assert st.problems == []
    # a corrupt upload: an error, and no file left behind
    from viser import UploadedFile

    st.upload._impl.value = UploadedFile("garbage.stl", b"solid x\n this is not a mesh\n")
    act(st, st._on_upload)
    assert errors(st)[-1][0] == "test" and "garbage" in errors(st)[-1][1]
    assert not list((gearbox_copy.parent / "meshes").glob("garbage*"))
    st.upload._impl.value = UploadedFile("notes.txt", b"hello")
    act(st, st._on_upload)
    assert "not a mesh format" in errors(st)[-1][1]
    # a good upload lands beside the assembly and becomes a part
    m = trimesh.creation.box((10, 10, 10))
    st.upload._impl.value = UploadedFile("cube.stl", m.export(file_type="stl"))
    act(st, st._on_upload)
    assert "cube" in st.asm.parts and (gearbox_copy.parent / "meshes" / "cube.stl").is_file()


def test_oversize_upload_is_refused_when_it_starts(studio):
    from viser import _messages

    st = studio()
    msg = _messages.FileTransferStartUpload(source_component_uuid=st.upload._impl.uuid, transfer_uuid="t1",
                                            filename="huge.stl", mime_type="model/stl", part_count=4000,
                                            size_bytes=MAX_UPLOAD_BYTES + 1)
    gui = st.server.gui
    for handler in gui._websock_interface._incoming_handlers[_messages.FileTransferStartUpload]:
        handler(0, msg)
    assert "t1" not in gui._current_file_upload_states  # nothing is buffered
    assert "huge.stl" in errors(st)[-1][1] and "limit" in errors(st)[-1][1]


def test_inspect_estimate_replay_and_cache(studio, gearbox_dataset):
    st = studio(SAMPLES / "helical_gearbox" / "assembly.yaml", gearbox_dataset)
    assert st.frame is not None and {"/inspect/camera", "/inspect/scene", "/inspect/box_gt"} <= set(st.nodes)
    assert "/inspect/box_est" not in st.nodes
    st.i_prior.value = True
    act(st, st._run_estimation, True)  # the whole step: both frames
    assert len(st.cache) == 2 and not errors(st)
    assert {"/inspect/target", "/inspect/source", "/inspect/box_est", "/inspect/box_gt"} <= set(st.nodes)
    assert st.score.mssd < 0.002 and "MSSD" in st.i_metrics.content
    n = len(st.stages)
    assert n >= 4 and st.stages[0].name == "initial" and st.stages[-1].name == "final"
    final = st.nodes["/inspect/source"].points.copy()
    st.i_stage.value = 0
    first = st.nodes["/inspect/source"].points
    assert np.abs(first - final).max() > 0 and "initial" in st.i_stage_md.content
    # the 2D view draws both boxes: green (estimate) and amber (truth) pixels appear on the RGB
    img = st.i_image.image
    assert ((img[..., 1] > 150) & (img[..., 0] < 80)).any()
    assert ((img[..., 0] > 230) & (img[..., 1] > 130) & (img[..., 1] < 190) & (img[..., 2] < 50)).any()
    st.i_frame.value = 1
    assert st.result is not None and st.frame.im_id == 1  # cached: no estimation needed


def test_an_ambiguous_result_shows_the_other_placements_in_magenta(studio, gearbox_dataset):
    """When several placements fit equally, the others are drawn as magenta boxes (3D and on the RGB)
    and the metrics say so; a clear result draws none."""
    from dataclasses import replace

    from apose_studio import se3
    from apose_studio.registration import Candidate

    st = studio(SAMPLES / "helical_gearbox" / "assembly.yaml", gearbox_dataset)
    st.i_prior.value = True
    act(st, st._run_estimation, False)
    assert "/inspect/box_alt" not in st.nodes and "magenta" not in st.i_metrics.content

    def magenta(img):
        return ((img[..., 0] > 200) & (img[..., 1] < 90) & (img[..., 2] > 200)).any()
    assert not magenta(st.i_image.image)
    T_other = st.result.T_world_part @ se3.make_T(se3.axis_angle_matrix([0, 0, 1.0], np.pi), [0.02, 0, 0])
    other = Candidate(st.result.T_world_base, T_other, 0.99, 0.99, 0.001, 0.99, 1)
    st.result = replace(st.result, ambiguous=True, alternatives=[other])
    st._draw_frame()
    assert "/inspect/box_alt" in st.nodes and "2 placements fit" in st.i_metrics.content
    np.testing.assert_allclose(st.nodes["/inspect/box_alt"].points.reshape(-1, 3).mean(axis=0),
                               se3.transform_points(T_other, st._inspect_models()[st._inspect_assembly().steps[0].part]
                                                    .box_corners()).mean(axis=0), atol=1e-5)
    assert magenta(st.i_image.image)


@pytest.fixture
def capture(gearbox_dataset, tmp_path) -> Path:
    """A real-capture folder (rgb.png, depth.png in mm, camera.json) made from a rendered frame."""
    import json

    import cv2

    from apose_studio.dataset import Dataset

    fr = Dataset(gearbox_dataset).frame(1, 1)
    cap = tmp_path / "capture"
    cap.mkdir()
    cv2.imwrite(str(cap / "rgb.png"), fr.rgb[..., ::-1])
    cv2.imwrite(str(cap / "depth.png"), (fr.depth * 1000).astype(np.uint16))
    (cap / "camera.json").write_text(json.dumps({"fx": fr.camera.fx, "fy": fr.camera.fy, "cx": fr.camera.cx,
                                                 "cy": fr.camera.cy, "depth_scale": 1.0}))
    return cap


def open_capture(studio, cap):
    st = studio(SAMPLES / "helical_gearbox" / "assembly.yaml")
    st.i_path.value = str(cap)
    act(st, lambda c: st._open_frames(st.i_path.value, c))
    return st


def test_capture_without_a_mask_fails_cleanly(studio, capture):
    st = open_capture(studio, capture)
    assert "/inspect/scene" in st.nodes and "/inspect/box_gt" not in st.nodes
    act(st, st._run_estimation, False)
    assert "empty mask" in errors(st)[-1][1] and "failed" in st.i_metrics.content.lower()


def test_capture_with_depth_masks_and_model_choice(studio, capture, tmp_path):
    st = open_capture(studio, capture)
    st.i_mask.value = "depth"
    act(st, st._run_estimation, False)
    assert st.result is not None and st.result.ok, st.notes
    assert {"/inspect/target", "/inspect/source", "/inspect/box_est"} <= set(st.nodes)
    # a model file that is not one: refused with the reason, the mask choice unchanged
    (tmp_path / "junk.pt").write_bytes(b"junk")
    st.i_model.value = str(tmp_path / "junk.pt")
    act(st, st._on_use_model)
    assert "not a readable model file" in errors(st)[-1][1] and st.i_mask.value == "depth"


def test_new_assembly_never_overwrites_the_open_file(studio, gearbox_copy):
    st = studio(gearbox_copy)
    before = gearbox_copy.read_text()
    act(st, st._on_new)  # 'Assembly file' still names the open file: refused, nothing changes
    assert "already exists: press Open to edit it" in errors(st)[-1][1] and len(st.asm.parts) == 4
    st.f_path.value = str(gearbox_copy.parent / "fixture.yaml")  # New uses the typed path
    act(st, st._on_new)
    assert st.asm.parts == {} and st.asm.name == "fixture" and Path(st.f_path.value) == gearbox_copy.parent.resolve() / "fixture.yaml"
    act(st, st._on_save)  # an empty assembly is refused, and the sample is untouched
    assert "no parts yet" in errors(st)[-1][1] and gearbox_copy.read_text() == before
    assert not (gearbox_copy.parent / "fixture.yaml").exists()
    st.f_path.value = str(gearbox_copy.parent)  # a folder: untitled.yaml in it
    act(st, st._on_new)
    assert Path(st.f_path.value) == gearbox_copy.parent.resolve() / "untitled.yaml"


def test_crop_box_limits_depth_masks(studio, gearbox_dataset):
    from apose_studio.dataset import Dataset

    st = studio(SAMPLES / "helical_gearbox" / "assembly.yaml", gearbox_dataset)
    st.i_mask.value = "depth"
    st.i_crop.value = True
    assert "/inspect/crop" in st.nodes and "/inspect/crop/box" in st.nodes
    fr = Dataset(gearbox_dataset).frame(1, 0)
    g = st.nodes["/inspect/crop"]
    # put the box on the ground-truth base pose: the mask stays on the base
    g._impl.position = tuple(fr.T_world_base[:3, 3])
    act(st, st._run_estimation, False)
    assert st.result.ok and st.score.mask_iou > 0.7
    # a box far away from everything leaves nothing to register: a clear failure, not a crash
    # (the cache knows the box moved: no stale result)
    g._impl.position = (5.0, 5.0, 5.0)
    act(st, st._run_estimation, False)
    assert not st.result.ok and "failed" in st.i_metrics.content.lower()


def test_demo_estimates_are_found_in_the_cache(gearbox_dataset):
    """`apose demo` caches its estimates under the key the studio builds for its default settings."""
    from apose_studio.inspection import ResultCache

    server, st = serve(SAMPLES / "helical_gearbox" / "assembly.yaml", gearbox_dataset, port=free_port())
    try:
        assert st.i_upright.value is True
        assert st._cache_key(1, 0) == ResultCache.key(gearbox_dataset.resolve(), 1, 0, "default", "gt", False)
        st.i_upright.value = False  # a free search is another result
        assert st._cache_key(1, 0) == ResultCache.key(gearbox_dataset.resolve(), 1, 0, "default free", "gt", False)
    finally:
        server.stop()


def test_files_outside_the_workspace_are_refused_and_never_echoed(studio, gearbox_copy, tmp_path):
    st = studio(gearbox_copy, root=gearbox_copy.parent)
    before = st.asm
    for path in ("/etc/passwd", tmp_path / "elsewhere.yaml"):
        st.f_path.value = str(path)
        act(st, st._on_open)
        assert "outside the studio's workspace" in errors(st)[-1][1] and "root:" not in errors(st)[-1][1]
        act(st, st._on_save)
        assert "outside the studio's workspace" in errors(st)[-1][1]
    assert not (tmp_path / "elsewhere.yaml").exists() and st.asm is before
    st.f_mesh.value = "/etc"
    act(st, st._on_add_parts)
    assert "outside the studio's workspace" in errors(st)[-1][1]


def test_a_failed_open_says_what_stays_on_screen(studio, gearbox_dataset, tmp_path):
    st = studio(SAMPLES / "helical_gearbox" / "assembly.yaml", gearbox_dataset, root=tmp_path)
    shown = st.frames_path
    (tmp_path / "broken").mkdir()
    st.i_path.value = str(tmp_path / "broken")
    act(st, st._on_open_data)
    assert "neither a dataset" in errors(st)[-1][1] and f"still showing the data opened before: {shown}" in errors(st)[-1][1]
    assert st.frames_path == shown
