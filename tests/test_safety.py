"""Safety round 2 (#24): hostile and careless input to the core. Each test names the item of the issue it
pins; each was written to fail on the code before the fix (say so when changing one)."""

import json
import os
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import trimesh

from apose_studio import safeio
from apose_studio.assembly.mesh import load_mesh, load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.data.bop import BopScene, read_results_csv
from apose_studio.errors import AposeError, AssemblyError, DatasetError, MeshError
from apose_studio.registration.types import View

from .conftest import TINY_YAML

APOSE = [sys.executable, "-m", "apose_studio.cli.commands"]


def run(*args, timeout=120):
    return subprocess.run([*APOSE, *map(str, args)], capture_output=True, text=True, timeout=timeout)


# ------------------------------------------------------------------------------------ reading (M2)


def test_safeio_refuses_pipes_devices_and_folders_without_blocking(tmp_path):
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    link = tmp_path / "zero.json"
    link.symlink_to("/dev/zero")
    done = []

    def attempt():
        for p in (fifo, link, tmp_path):
            with pytest.raises(AposeError) as e:
                safeio.read_bytes(p, "a camera file")
            done.append(str(e.value))

    t = threading.Thread(target=attempt, daemon=True)
    t.start()
    t.join(10)
    assert not t.is_alive(), "reading a FIFO blocked"
    assert "not a regular file" in done[0] and "not a regular file" in done[1] and "a folder, not a file" in done[2]


def test_safeio_caps_the_bytes_read_not_the_size_claimed(tmp_path):
    big = tmp_path / "big.json"
    with open(big, "wb") as f:  # sparse: 64 MB on paper, nothing on disk
        f.truncate(64 * 2 ** 20)
    with pytest.raises(AposeError, match=r"64.0 MB, over the 5.0 MB"):
        safeio.read_bytes(big, "a camera file", 5 * 2 ** 20)
    assert safeio.read_bytes(big, "x", 64 * 2 ** 20)[:4] == b"\0\0\0\0"


def test_strict_json_numbers_and_nesting():
    assert safeio.parse_json('{"a": 1.5, "b": [1, 2]}', "f") == {"a": 1.5, "b": [1, 2]}
    for text, message in [("{\"a\": NaN}", "NaN is not JSON"), ("[" * 100000 + "]" * 100000, "nested far too deeply"),
                          ("1" * 400, "a number of 400 digits"), ("{\"a\": 1e99999}", "Infinity|characters|finite|inf"),
                          ("{", "not valid JSON")]:
        try:
            v = safeio.parse_json(text, "f.json")
        except AposeError as e:
            assert e.args[0].startswith("f.json:"), e
            continue
        assert np.isfinite(v["a"]), text  # 1e99999 parses to inf in Python: refused above or finite


def test_assembly_file_as_fifo_device_or_oversized(tmp_path):
    fifo = tmp_path / "a.yaml"
    os.mkfifo(fifo)
    with pytest.raises(AssemblyError, match="not a regular file"):
        load_assembly(fifo)
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (5 * 2 ** 20 + 10))
    with pytest.raises(AssemblyError, match=r"5.0 MB, over the 5.0 MB") as e:
        load_assembly(big)
    assert "at most 5 MB)" not in str(e.value)


def test_yaml_reads_exponents_without_a_dot_as_numbers(tiny_dir):
    text = TINY_YAML.replace("translation: [10, 0, 5]", "translation: [1e1, 0, 5E0]")
    (tiny_dir / "assembly.yaml").write_text(text)
    asm = load_assembly(tiny_dir / "assembly.yaml")
    assert asm.steps[0].T_base_part[0, 3] == pytest.approx(0.010)


# ----------------------------------------------------------------------------------- meshes (M6)


def test_mesh_caps_refuse_before_parsing(tmp_path, monkeypatch):
    sparse = tmp_path / "huge.stl"
    with open(sparse, "wb") as f:
        f.truncate(2 * 2 ** 30)  # 2 GB, 4 KB on disk
    t0 = time.time()
    with pytest.raises(MeshError, match="over the 512 MB a mesh file may have"):
        load_mesh(sparse)
    assert time.time() - t0 < 5
    lying = tmp_path / "lying.stl"  # a binary STL whose header declares 50 M triangles
    lying.write_bytes(b"\0" * 80 + (50_000_000).to_bytes(4, "little") + b"\0" * 500)
    with pytest.raises(MeshError, match="declares 50000000 triangles|not a STL|corrupt"):
        load_mesh(lying)
    monkeypatch.setattr(safeio, "LIMITS", safeio.Limits(mesh_triangles=100))
    trimesh.creation.icosphere(subdivisions=3).export(tmp_path / "ball.stl")  # 1280 triangles
    with pytest.raises(MeshError, match="1280 triangles, over the 100"):
        load_mesh(tmp_path / "ball.stl")


def test_corrupt_face_indices_and_far_vertices(tmp_path):
    ply = tmp_path / "bad.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    with pytest.raises(MeshError, match="triangle names vertex 7 but the file has 3 vertices|corrupt"):
        load_mesh(ply)
    obj = tmp_path / "far.obj"
    obj.write_text("v 0 0 0\nv 1e308 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 2 4\n")
    with pytest.raises(MeshError, match="from the part's origin"):
        load_mesh(obj, "mm")


def test_gltf_buffer_that_is_a_fifo_does_not_hang(tmp_path):
    (tmp_path / "buf.bin").unlink(missing_ok=True)
    os.mkfifo(tmp_path / "buf.bin")
    gltf = {"asset": {"version": "2.0"}, "buffers": [{"uri": "buf.bin", "byteLength": 36}],
            "bufferViews": [{"buffer": 0, "byteLength": 36}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "max": [1, 1, 0],
                           "min": [0, 0, 0]}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}], "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}
    (tmp_path / "part.gltf").write_text(json.dumps(gltf))
    out = []

    def attempt():
        try:
            load_mesh(tmp_path / "part.gltf")
        except MeshError as e:
            out.append(str(e))

    t = threading.Thread(target=attempt, daemon=True)
    t.start()
    t.join(20)
    assert not t.is_alive(), "a glTF buffer that is a FIFO hung the load"
    assert out and "not a regular file" in out[0]


def test_each_mesh_file_is_loaded_once(tiny_dir, monkeypatch):
    import apose_studio.assembly.mesh as M

    text = TINY_YAML.split("steps:")[0] + "".join(f"  copy{i}: {{mesh: plate.stl}}\n" for i in range(40)) + "steps: []\n"
    (tiny_dir / "many.yaml").write_text(text.replace("parts:\n", "parts:\n", 1))
    calls = []
    real = M.load_mesh
    monkeypatch.setattr(M, "load_mesh", lambda *a, **k: calls.append(a[0]) or real(*a, **k))
    M._MESH_CACHE.clear()
    models = load_parts(load_assembly(tiny_dir / "many.yaml"))
    assert len(models) == 43 and len(calls) == 3  # plate, peg, cap: each read once
    assert models["copy0"].mesh is models["copy39"].mesh is models["plate"].mesh


# ------------------------------------------------------------------------------- BOP input (M8, M9)


def test_nan_and_infinite_scores_are_refused_with_the_line(tmp_path):
    header = "scene_id,im_id,obj_id,score,R,t,time\n"
    row = "1,0,1,{},1 0 0 0 1 0 0 0 1,0 0 500,0.1\n"
    for bad in ("nan", "inf", "-inf"):
        p = tmp_path / f"{bad}.csv"
        p.write_text(header + row.format(bad) + row.format("0.9"))
        with pytest.raises(DatasetError, match=f"line 2: score is {bad}"):
            read_results_csv(p)
    bom = tmp_path / "bom.csv"
    bom.write_text("\ufeff" + header + row.format("0.9"), encoding="utf-8")
    assert len(read_results_csv(bom)) == 1
    wide = tmp_path / "wide.csv"
    wide.write_text(header + "1,0,1,0.5," + "1 " * 100000 + ",0 0 1,0\n")
    with pytest.raises(DatasetError, match="line 2"):
        read_results_csv(wide)


def _bop_scene(folder, gt):
    import cv2

    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    cv2.imwrite(str(folder / "rgb" / "000000.png"), np.zeros((48, 64, 3), np.uint8))
    cv2.imwrite(str(folder / "depth" / "000000.png"), np.full((48, 64), 500, np.uint16))
    (folder / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [60, 0, 32, 0, 60, 24, 0, 0, 1],
                                                                "depth_scale": 1.0}}))
    (folder / "scene_gt.json").write_text(json.dumps(gt) if not isinstance(gt, str) else gt)
    return folder


def test_malformed_scene_gt_is_named_not_a_traceback(tmp_path):
    R, t = [1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 500]
    good = {"cam_R_m2c": R, "cam_t_m2c": t, "obj_id": 1}
    cases = [([good], "expected a JSON object keyed by image id"),
             ({"0": [{"cam_t_m2c": t, "obj_id": 1}]}, "0[0]: missing cam_R_m2c"),
             ({"0": [{**good, "cam_R_m2c": R[:8]}]}, "cam_R_m2c must be a list of 9 numbers"),
             ({"0": [{**good, "cam_t_m2c": ["0", "0", "500"]}]}, "cam_t_m2c must be a list of 3 numbers"),
             ({"0": [{**good, "obj_id": -1}]}, "obj_id must be a whole number >= 0"),
             ({"zero": [good]}, "key 'zero': image ids are whole numbers")]
    for i, (gt, message) in enumerate(cases):
        folder = _bop_scene(tmp_path / f"s{i}", gt)
        with pytest.raises(DatasetError, match=message.replace("[", r"\[")):
            BopScene(folder, {"plate": 1}).frame(0)
    ok = BopScene(_bop_scene(tmp_path / "ok", {"0": [good]}), {"plate": 1}).frame(0)
    np.testing.assert_allclose(ok.poses["plate"][:3, :3] @ ok.poses["plate"][:3, :3].T, np.eye(3), atol=1e-9)


# ------------------------------------------------------------------------------------- CLI (minor)


def test_show_escapes_control_characters(tiny_dir):
    text = TINY_YAML.replace("name: tiny", 'name: "ti\\e]0;pwned\\aNY\\e[2J"')
    (tiny_dir / "assembly.yaml").write_text(text)
    r = run("show", tiny_dir / "assembly.yaml")  # such a name is refused at its key, and the refusal escaped
    assert r.returncode == 2 and "name: holds the control or invisible character \\x1b" in r.stderr, r.stderr
    assert "\x1b" not in r.stdout + r.stderr and "\x07" not in r.stdout + r.stderr


def test_eval_json_never_replaces_a_file_of_the_dataset(tmp_path):
    ds = tmp_path / "ds"
    ds.mkdir()
    manifest = ds / "dataset_info.json"
    manifest.write_text('{"format": "apose-bop/1"}')
    r = run("eval", ds, "--json", manifest)
    assert r.returncode == 2 and "a file of the input" in r.stderr, r.stderr
    assert manifest.read_text() == '{"format": "apose-bop/1"}'


def test_system_errors_are_one_line_exit_2(tiny_dir, monkeypatch, capsys):
    """A full disk, a read-only folder: whatever command meets them prints the file, the reason and the fix."""
    import errno

    import apose_studio.cli.commands as cli

    for code, fix in ((errno.ENOSPC, "free some disk space"), (errno.EROFS, "read-only"), (errno.EACCES, "permission")):
        def fail(*a, **k):
            raise OSError(code, os.strerror(code), "/data/out.json")
        monkeypatch.setattr(cli, "show_text", fail)
        assert cli.main(["show", str(tiny_dir / "assembly.yaml")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: /data/out.json: ") and fix in err and len(err.strip().splitlines()) == 1, err


# ------------------------------------------------- cases an outside attack on the safety fixes found


def test_a_jpeg_size_hidden_behind_fill_bytes_is_still_seen(tmp_path):
    """libjpeg skips 0xFF fill bytes before a marker; a walk that does not lands on a decoy 16x16 frame
    header while the real one says 12000 x 12000 (a 50 KB file that decodes to 144 M pixels)."""
    import struct

    import cv2

    ok, enc = cv2.imencode(".jpg", np.full((16, 16), 128, np.uint8))
    b = bytearray(enc.tobytes())
    i = b.find(b"\xff\xc0")
    b[i + 5:i + 9] = struct.pack(">HH", 12000, 12000)
    b[i:i] = b"\xff"  # one fill byte
    target = i + 2 + 0xC000
    b += b"\x00" * (target - len(b)) + b"\xff\xc0\x00\x0b\x08\x00\x10\x00\x10\x01\x01\x11\x00"
    assert safeio.image_header(bytes(b))[1:3] == (12000, 12000)
    (tmp_path / "rgb.jpg").write_bytes(bytes(b))
    with pytest.raises(AposeError, match="12000 x 12000 pixels, over the 8192"):
        safeio.read_image(tmp_path / "rgb.jpg", cv2.IMREAD_UNCHANGED)
    assert int(os.environ["OPENCV_IO_MAX_IMAGE_PIXELS"]) == 8192 * 8192  # OpenCV's own cap behind it


def test_a_gltf_naming_one_big_buffer_many_times_is_refused_early(tmp_path):
    with open(tmp_path / "big.bin", "wb") as f:
        f.truncate(300 * 2 ** 20)  # sparse
    (tmp_path / "model.gltf").write_text(json.dumps({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": []}],
                                                     "buffers": [{"uri": "big.bin", "byteLength": 300 * 2 ** 20}] * 6}))
    with pytest.raises(MeshError, match="add up to more than the 512 MB"):
        load_mesh(tmp_path / "model.gltf")


def test_a_link_planted_as_the_lock_or_journal_is_never_written_through(tmp_path):
    from apose_studio.data.outdir import JOURNAL, LOCK, OutputLock, check_output_dir

    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK).symlink_to(victim)
    with pytest.raises(AposeError, match="a symbolic link where the render's lock file goes"):
        with OutputLock(out):
            pass
    (out / LOCK).unlink()
    (out / JOURNAL).symlink_to(victim)
    with pytest.raises(AposeError, match="not empty"):
        check_output_dir(out, overwrite=False)
    with OutputLock(out) as lock:
        with pytest.raises(OSError):
            lock.note("test/a.png")
    (out / ".apose-write-test").symlink_to(victim)  # a link named like the write probe is someone else's file
    with pytest.raises(AposeError, match="no apose render wrote"):
        check_output_dir(out, overwrite=True)
    assert victim.read_text() == "precious"


def test_every_registration_parameter_has_a_range(tiny_dir):
    for key, value, expected in (("ransac_max_iterations", "1000000000", "from 1 to 1000000"),
                                 ("ransac_max_iterations", "1e12", "from 1 to 1000000"),
                                 ("icp_max_iterations", "100000", "from 1 to 1000"),
                                 ("voxel_size_m", "1e-9", "from 0.0001 to 0.5"),
                                 ("max_seconds", "1e9", "from 0 (no limit) to 3600"),
                                 ("seed", "-1", "from 0 to 4294967295")):
        (tiny_dir / "assembly.yaml").write_text(TINY_YAML + f"registration:\n  {key}: {value}\n")
        with pytest.raises(AssemblyError, match=f"registration.{key}: expected .*{re.escape(expected)}"):
            load_assembly(tiny_dir / "assembly.yaml")


def test_a_mask_over_the_whole_image_is_named_as_such():
    from apose_studio.geometry.camera import CameraIntrinsics
    from apose_studio.registration import estimate, resolve_params
    from apose_studio.registration.base import prepare_base

    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 32.0, 24.0)
    depth = np.full((48, 64), 0.5, np.float32)
    depth[:, :32] = 2.0  # a wide scene: far larger than a 2 cm cube
    base = prepare_base(trimesh.creation.box((0.02, 0.02, 0.02)), n_samples=2000)
    r = estimate(View(depth, np.ones((48, 64), bool), cam, np.eye(4)), base, np.eye(4), resolve_params("default"))
    assert not r.ok and "the mask covers 100% of the image" in r.reason and "depth_scale" not in r.reason
