"""Safety round 3 (#24 re-test): hostile files whose cost no byte cap bounds. A 3 KB STEP file kept
OpenCASCADE busy for minutes (K1), a 1 MB glTF placed one mesh 3000 times (K2), OBJ/PLY/STL text made
gigabytes within the caps (M-c), a 66 KB TIFF decoded to 4 GB (M-a), a TIFF with its size tag twice
gave "please report" (M-b), and a few files were misnamed (minors). Each test was written to fail on the
code before the fix (but the two marked as guards, which pin what must not change); each is bounded by the
limit it checks (seconds)."""

import base64
import json
import os
import struct
import subprocess
import sys
import time
import zlib

import cv2
import numpy as np
import pytest
import trimesh

from apose_studio import safeio
from apose_studio.assembly import mesh as M
from apose_studio.assembly.mesh import load_mesh, load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.data.dataset import Dataset, load_capture, read_depth, read_rgb
from apose_studio.data.sources import open_frames
from apose_studio.errors import AposeError, DatasetError, MeshError
from apose_studio.geometry.units import UNIT_TO_M

from .conftest import SAMPLES

APOSE = [sys.executable, "-m", "apose_studio.cli.commands"]


def run(*args, timeout=120):
    return subprocess.run([*APOSE, *map(str, args)], capture_output=True, text=True, timeout=timeout)


def limits(monkeypatch, **kw):
    monkeypatch.setattr(safeio, "LIMITS", safeio.Limits(**kw))


def spin(*_a, **_k):
    t0 = time.time()
    while time.time() - t0 < 60:  # on the code before the fix this ran in-process: it must end by itself
        pass
    raise AssertionError("spun for a minute")


def never(*_a, **_k):
    raise AssertionError("parsed: the count should have refused it before")


# ----------------------------------------------------------------------------- the bounded child


def test_run_bounded_returns_results_and_cuts_every_limit():
    kw = dict(where="part.stl", doing="reading this STL file", fix="decimate it")
    assert safeio.run_bounded(lambda a: a * 2, np.arange(3), **kw).tolist() == [0, 2, 4]
    with pytest.raises(MeshError, match="^bad mesh$"):  # our errors come back as themselves
        safeio.run_bounded(lambda: (_ for _ in ()).throw(MeshError("bad mesh")), **kw)
    cases = [(dict(cpu_s=1), spin, "cpu", "took more than 1 s of CPU time (the most it may take)"),
             (dict(memory=64 * 2 ** 20), lambda: [np.ones(2 ** 24) for _ in range(100)], "memory",
              "needed more than 64.0 MB of memory (the most it may use)"),
             (dict(wall_s=1), lambda: time.sleep(30), "wall", "took more than 1 s (the most it may take)"),
             (dict(output_bytes=1000), lambda: np.zeros(10 ** 5), "output", "made more than 1000 bytes of data (the most it may)")]
    for limit, fn, kind, text in cases:
        t0 = time.time()
        with pytest.raises(safeio.LimitExceeded) as e:
            safeio.run_bounded(fn, **kw, **limit)
        assert e.value.kind == kind and str(e.value) == f"part.stl: reading this STL file {text}; decimate it"
        assert time.time() - t0 < 10, kind


# ------------------------------------------------------------------------------------------ K1: STEP


def _step_file(path, solids):
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_step", SAMPLES / "make_step.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    w = mod.StepWriter()
    path.write_text(mod.step_text({name: mod.cylinder_solid(w, *args) for name, args in solids.items()}, w))
    return path


def test_a_step_disc_a_kilometre_wide_is_tessellated_in_seconds(tmp_path):
    """The attack file: a 1 mm disc of radius 1 km, 3 KB. OpenCASCADE at 0.01 mm ran for 8.5 minutes (4.7 GB);
    now the tolerance follows the part's size, and the process is bounded anyway."""
    step = _step_file(tmp_path / "disc.step", {"disc": (0, 0, 0, 1.0, 1e6)})
    code = (f"from apose_studio.assembly.mesh import load_mesh; m = load_mesh({str(step)!r}); "
            "print(len(m.faces), round(float(m.extents.max())))")
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=90)
    except subprocess.TimeoutExpired:
        pytest.fail("a 3 KB STEP file still takes more than 90 s to read")
    assert r.returncode == 0, r.stderr[-500:]
    faces, size_m = map(int, r.stdout.split())
    assert size_m == 2000 and faces < 100_000


def test_step_tessellation_past_its_cpu_limit_is_refused_and_remembered(tmp_path, monkeypatch):
    import tempfile

    import cascadio

    step = _step_file(tmp_path / "part.step", {"a": (0, 0, 0, 10.0, 5.0)})
    monkeypatch.setattr(cascadio, "step_to_glb", spin)  # OpenCASCADE that never ends (the child inherits it)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    limits(monkeypatch, parse_cpu_seconds=1)
    M._STEP_CACHE.clear()
    t0 = time.time()
    with pytest.raises(MeshError) as e:
        load_mesh(step)
    assert time.time() - t0 < 10
    assert str(e.value).startswith(f"{step}: tessellating this STEP file (OpenCASCADE) took more than 1 s of CPU time")
    assert "export the part from CAD as a mesh" in str(e.value)
    assert list((tmp_path / "tmp").iterdir()) == []  # the killed child's copy and GLB are gone
    monkeypatch.setattr(safeio, "run_bounded", never)  # the same file again: refused without parsing
    with pytest.raises(MeshError, match="took more than 1 s of CPU time"):
        load_mesh(step)
    with pytest.raises(MeshError, match="took more than 1 s of CPU time"):
        M.step_solids(step)  # the studio's list of a STEP file's solids goes the same way


# ------------------------------------------------------------------------------- K2: glTF instances


def _instanced_gltf(path, copies, subdivisions=3, glb=False):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=10)
    v, f = ico.vertices.astype(np.float32), ico.faces.astype(np.uint32)
    blob = v.tobytes() + f.tobytes()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": list(range(copies))}],
           "nodes": [{"mesh": 0, "translation": [30.0 * i, 0, 0]} for i in range(copies)],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
           "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
           "textures": [{"source": 0}], "images": [{"uri": "texture.png"}],  # never read: geometry only
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
                          "min": v.min(0).tolist(), "max": v.max(0).tolist()},
                         {"bufferView": 1, "componentType": 5125, "count": f.size, "type": "SCALAR"}],
           "bufferViews": [{"buffer": 0, "byteLength": len(v.tobytes())},
                           {"buffer": 0, "byteOffset": len(v.tobytes()), "byteLength": len(f.tobytes())}],
           "buffers": [{"byteLength": len(blob)}]}
    if not glb:
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        path.write_text(json.dumps(doc))
        return path
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return path


def test_gltf_copies_of_one_mesh_are_counted_from_its_json_before_parsing(tmp_path, monkeypatch):
    """3000 nodes on one 20480-triangle mesh (1 MB) cost 7.9 GB once copied into one mesh; the count is in
    the JSON. Here 300 nodes on 1280 triangles against a cap of 100 000."""
    limits(monkeypatch, mesh_triangles=100_000)
    (tmp_path / "texture.png").mkdir()  # a texture that would fail if it were read
    for name, glb in (("copies.gltf", False), ("copies.glb", True)):
        path = _instanced_gltf(tmp_path / name, 300, glb=glb)
        with monkeypatch.context() as m:
            m.setattr(trimesh, "load", never)
            with pytest.raises(MeshError, match="its glTF scene places its meshes 300 times, 384000 triangles in all, "
                                                "over the 100000 a part may have"):
                load_mesh(path)
        few = _instanced_gltf(tmp_path / f"few{name[-5:]}", 3, glb=glb)
        assert len(load_mesh(few, "mm").faces) == 3 * 1280  # three copies, materials dropped, texture never read


def test_the_cli_refuses_a_gltf_instance_bomb_in_seconds(tmp_path):
    _instanced_gltf(tmp_path / "bomb.glb", 200, subdivisions=5, glb=True)  # 4.1 M triangles from 0.4 MB
    trimesh.creation.box((20, 20, 20)).export(tmp_path / "base.stl")
    (tmp_path / "assembly.yaml").write_text("format: apose-assembly/1\nname: b\nunits: mm\nparts:\n  p: {mesh: bomb.glb}\n"
                                            "  base: {mesh: base.stl}\nsteps:\n  - {part: p, base: [base], pose_in_base: {translation: [0, 0, 30]}}\n")
    t0 = time.time()
    r = run("show", tmp_path / "assembly.yaml")
    assert r.returncode == 2 and "places its meshes 200 times, 4096000 triangles" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and time.time() - t0 < 30


# --------------------------------------------------------------- M-c: the work a mesh file declares


def test_triangles_a_file_holds_are_counted_before_it_is_parsed(tmp_path, monkeypatch):
    """OBJ face lines and fans, PLY polygons, ASCII STL facets, a binary STL behind a `solid` header (a
    sparse 495 MB one took 17 s and 6.9 GB), OFF counts: refused from the count, never parsed."""
    limits(monkeypatch, mesh_triangles=1000)
    monkeypatch.setattr(trimesh, "load", never)
    verts = "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 10\n"
    (tmp_path / "lines.obj").write_text(verts + "f 1 2 4\n" * 5000)
    (tmp_path / "fan.obj").write_text(verts + "f " + " ".join(["1 2 3 4"] * 400) + "\n")
    ply = (b"ply\nformat binary_little_endian 1.0\nelement vertex 256\nproperty float x\nproperty float y\n"
           b"property float z\nelement face 20\nproperty list uchar int vertex_indices\nend_header\n")
    face = struct.pack("<B", 255) + np.arange(255, dtype=np.int32).tobytes()
    (tmp_path / "polygons.ply").write_bytes(ply + np.random.default_rng(0).random((256, 3), np.float32).tobytes() + face * 20)
    facet = "facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\n"
    (tmp_path / "ascii.stl").write_text("solid a\n" + facet * 3000 + "endsolid a\n")
    with open(tmp_path / "solid_binary.stl", "wb") as f:
        f.write(b"solid x".ljust(80, b"\0") + struct.pack("<I", 5_000_000))
        f.truncate(84 + 50 * 5_000_000)  # 250 MB on paper, nothing on disk
    (tmp_path / "counts.off").write_text("OFF\n4 2000000000 0\n0 0 0\n10 0 0\n0 10 0\n0 0 10\n3 0 1 2\n")
    (tmp_path / "points.obj").write_text("v 1 2 3\n" * 4000 + "f 1 2 3\n")
    (tmp_path / "points.ply").write_bytes(ply.replace(b"vertex 256", b"vertex 40000"))
    cases = {"lines.obj": "its face lines hold 5000 triangles", "fan.obj": "its face lines hold 1598 triangles",
             "polygons.ply": "its header declares 5060 triangles", "ascii.stl": "it holds 3000 triangles",
             "solid_binary.stl": "its header declares 5000000 triangles", "counts.off": "declares 2000000000 triangles",
             "points.obj": "its vertex lines hold 4000 vertices, over the 3000", "points.ply": "declares 40000 vertices"}
    for name, message in cases.items():
        t0 = time.time()
        with pytest.raises(MeshError) as e:
            load_mesh(tmp_path / name)
        assert message in str(e.value) and "a part" in str(e.value) and "; decimate" in str(e.value), str(e.value)
        assert time.time() - t0 < 5, name


def test_what_no_count_bounds_is_cut_at_the_memory_and_cpu_limits(tmp_path, monkeypatch):
    """A parse that needs more memory, or more time, than a part may take: refused, the file and limit named."""
    trimesh.creation.box((10, 10, 10)).export(tmp_path / "part.obj")
    limits(monkeypatch, parse_memory_bytes=64 * 2 ** 20, parse_cpu_seconds=1)
    monkeypatch.setattr(trimesh, "load", lambda *a, **k: [np.ones(2 ** 24) for _ in range(100)])
    with pytest.raises(MeshError, match=r"part.obj: reading this OBJ file needed more than 64.0 MB of memory \(the most "
                                        r"it may use\); decimate the part .*if it is large; else export it again as one plain mesh: binary STL, PLY or GLB"):
        load_mesh(tmp_path / "part.obj")
    monkeypatch.setattr(trimesh, "load", spin)
    t0 = time.time()
    with pytest.raises(MeshError, match="part.obj: reading this OBJ file took more than 1 s of CPU time"):
        load_mesh(tmp_path / "part.obj", "cm")
    assert time.time() - t0 < 10


def test_an_assembly_s_meshes_share_one_time_budget(tiny_dir, monkeypatch):
    limits(monkeypatch, assembly_parse_seconds=0)
    M._MESH_CACHE.clear()
    with pytest.raises(MeshError, match=r"part 'plate': .*plate.stl: not read: the assembly's mesh files took more "
                                        r"than 0 s in all \(the most they may take\)"):
        load_parts(load_assembly(tiny_dir / "assembly.yaml"))


def test_files_whose_cost_their_counts_fix_are_read_without_a_child(tmp_path, monkeypatch):
    """A binary STL, and a binary PLY whose size says every face is a triangle, cost what their checked counts
    say: read in this process (a fork costs ~20 ms; the samples are such files). Text goes to a child."""
    box = trimesh.creation.box((30, 20, 10))
    box.export(tmp_path / "box.stl")
    box.export(tmp_path / "box.ply")
    box.export(tmp_path / "box.obj")
    monkeypatch.setattr(safeio, "run_bounded", never)
    for name in ("box.stl", "box.ply"):
        np.testing.assert_allclose(load_mesh(tmp_path / name, "mm").extents, [0.03, 0.02, 0.01])
    with pytest.raises(AssertionError, match="parsed"):
        load_mesh(tmp_path / "box.obj", "mm")


def test_sample_meshes_read_as_before():
    """A guard: the child process changes nothing a mesh is (the gearbox's STL and OBJ, as trimesh reads them)."""
    for path in (SAMPLES / "helical_gearbox" / "pinion.stl", SAMPLES / "helical_gearbox" / "lid.obj"):
        direct = trimesh.load(path, force="mesh", process=False)
        v, f = M.merge_vertices(np.asarray(direct.vertices, float) * UNIT_TO_M["mm"], np.asarray(direct.faces))
        m = load_mesh(path, "mm")
        np.testing.assert_array_equal(m.vertices, v)
        np.testing.assert_array_equal(m.faces, f)


# ---------------------------------------------------------------------------- M-a, M-b: images


def _tiff(path, width, height, spp=1, bits=8, fmt=1, compression=1, extra=(), data=b"\0" * 64):
    """A TIFF written by hand: one strip, tags in the order given (`extra` appended as written)."""
    entries = [(256, 4, [width]), (257, 4, [height]), (258, 3, [bits] * spp), (259, 3, [compression]),
               (262, 3, [1 if spp == 1 else 2]), (273, 4, [0]), (277, 3, [spp]), (278, 4, [height]),
               (279, 4, [len(data)]), (339, 3, [fmt] * spp), *extra]
    ifd_size = 2 + 12 * len(entries) + 4
    out, tail = [], b""
    for tag, typ, values in entries:
        raw = struct.pack("<" + {3: "H", 4: "I"}[typ] * len(values), *values)
        if len(raw) <= 4:
            out.append(struct.pack("<HHI", tag, typ, len(values)) + raw.ljust(4, b"\0"))
        else:
            out.append(struct.pack("<HHII", tag, typ, len(values), 8 + ifd_size + len(tail)))
            tail += raw
    strip_at = 8 + ifd_size + len(tail)
    out = [e if e[:2] != struct.pack("<H", 273) else e[:8] + struct.pack("<I", strip_at) for e in out]
    path.write_bytes(b"II*\0" + struct.pack("<I", 8) + struct.pack("<H", len(entries)) + b"".join(out) + b"\0" * 4
                     + tail + data)
    return path


def _capture(folder, rgb=None, depth=None):
    folder.mkdir()
    cv2.imwrite(str(folder / "rgb.png"), np.full((48, 64, 3), 90, np.uint8) if rgb is None else rgb)
    cv2.imwrite(str(folder / "depth.png"), np.full((48, 64), 500, np.uint16) if depth is None else depth)
    (folder / "camera.json").write_text(json.dumps({"fx": 60, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1.0}))
    return folder


def test_image_bombs_are_measured_in_decoded_bytes_from_the_header(tmp_path, monkeypatch):
    """A 66 KB deflated TIFF of 8192 x 8192 x 4 float64 (4.3 GB, 12 s in `apose estimate`): refused from
    its header, nothing decoded; and a 16-bit RGBA PNG over the decoded-bytes cap."""
    def no_decoding(*_a, **_k):
        raise AssertionError("decoded: the header should have refused it")

    bomb = zlib.compress(b"\0" * (2 ** 22), 9)
    for role, reader in (("rgb", read_rgb), ("depth", lambda p: read_depth(p, 1.0))):
        folder = _capture(tmp_path / role)
        _tiff(folder / f"{role}.png", 8192, 8192, spp=4, bits=64, fmt=3, compression=8, data=bomb)
        with monkeypatch.context() as m:
            m.setattr(cv2, "imdecode", no_decoding)
            with pytest.raises(DatasetError, match=f"{role}.png: a 64-bit float TIFF with 4 channels"):
                reader(folder / f"{role}.png")
        if role == "depth":  # the capture as `apose estimate` and the studio's Open data read it
            with pytest.raises(DatasetError, match="depth.png: a 64-bit float TIFF with 4 channels"):
                open_frames(folder)
    deep = tmp_path / "deep.png"
    cv2.imwrite(str(deep), np.zeros((512, 512, 4), np.uint16))
    limits(monkeypatch, image_decoded_bytes=2 ** 20)
    with monkeypatch.context() as m:
        m.setattr(cv2, "imdecode", no_decoding)
        with pytest.raises(DatasetError, match=r"deep.png: a 512 x 512 16-bit PNG with 4 channels, 2.0 MB once decoded, "
                                               r"over the 1.0 MB an image may take"):
            read_rgb(deep)


def test_depth_must_be_one_16_bit_channel_said_by_the_header(tmp_path, monkeypatch):
    def no_decoding(*_a, **_k):
        raise AssertionError("decoded: the header said enough")

    cv2.imwrite(str(tmp_path / "rgb16.png"), np.zeros((8, 8, 3), np.uint16))
    cv2.imwrite(str(tmp_path / "float.tiff"), np.zeros((8, 8), np.float32))
    cv2.imwrite(str(tmp_path / "u16x4.tiff"), np.zeros((8, 8, 4), np.uint16))
    cv2.imwrite(str(tmp_path / "gray8.png"), np.zeros((8, 8), np.uint8))
    cases = {"rgb16.png": "a 16-bit PNG with 3 channels; depth is one channel of 16-bit integers",
             "float.tiff": "a float32 depth image; expected 16-bit integers",
             "u16x4.tiff": "a 16-bit TIFF with 4 channels",  # used to say "8-bit" for every TIFF of several channels
             "gray8.png": "a uint8 depth image; expected 16-bit integers"}
    with monkeypatch.context() as m:
        m.setattr(cv2, "imdecode", no_decoding)
        for name, message in cases.items():
            with pytest.raises(DatasetError, match=message):
                read_depth(tmp_path / name, 1.0)
    # what cameras and BOP write still reads: 16-bit PNG and TIFF depth, 8-bit TIFF colour
    cv2.imwrite(str(tmp_path / "d.tiff"), np.full((8, 8), 700, np.uint16))
    cv2.imwrite(str(tmp_path / "d.png"), np.full((8, 8), 700, np.uint16))
    cv2.imwrite(str(tmp_path / "c.tiff"), np.full((8, 8, 3), 9, np.uint8))
    assert read_depth(tmp_path / "d.tiff", 1.0)[0, 0] == pytest.approx(0.7)
    assert read_depth(tmp_path / "d.png", 1.0)[0, 0] == pytest.approx(0.7)
    assert read_rgb(tmp_path / "c.tiff").shape == (8, 8, 3)


def test_a_tiff_whose_size_tag_repeats_is_refused_with_exit_2(tmp_path):
    """libtiff keeps the first of two width tags (100000), our reader kept the last (8): "unexpected error ...
    please report" and exit 1."""
    folder = _capture(tmp_path / "cap")
    _tiff(folder / "rgb.png", 100000, 8, extra=[(256, 4, [8])])
    with pytest.raises(AposeError, match=r"rgb.png: its TIFF header gives tag 256 \(width\) twice; the file is damaged "
                                         "or crafted"):
        safeio.read_image(folder / "rgb.png", cv2.IMREAD_COLOR)
    for tag, value in ((257, 8), (258, 8)):  # height, bits: the same
        _tiff(tmp_path / "x.tif", 8, 8, extra=[(tag, 3, [value])])
        with pytest.raises(AposeError, match=f"gives tag {tag} .* twice"):
            safeio.read_image(tmp_path / "x.tif", cv2.IMREAD_COLOR)
    _tiff(tmp_path / "bits.tif", 8, 8, spp=3, extra=[])
    data = bytearray((tmp_path / "bits.tif").read_bytes())
    at = data.find(struct.pack("<HHI", 258, 3, 3))
    (off,) = struct.unpack("<I", data[at + 8:at + 12])
    data[off:off + 6] = struct.pack("<HHH", 8, 16, 8)  # bits per sample 8, 16, 8
    (tmp_path / "bits.tif").write_bytes(bytes(data))
    with pytest.raises(AposeError, match=r"bits per sample \[8, 16, 8\] .* disagree"):
        safeio.read_image(tmp_path / "bits.tif", cv2.IMREAD_COLOR)
    r = run("estimate", folder, "--assembly", SAMPLES / "helical_gearbox" / "assembly.yaml", "--step", "1", "--box",
            "10,10,40,40")
    assert r.returncode == 2 and "gives tag 256 (width) twice" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_a_decoder_s_own_refusal_is_bad_input(tmp_path, monkeypatch):
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((8, 8, 3), np.uint8))

    def refuse(*_a, **_k):
        raise cv2.error("OpenCV(5.0.0) loadsave.cpp:1: error: (-215:Assertion failed) pixels <= CV_IO_MAX_IMAGE_PIXELS")

    monkeypatch.setattr(cv2, "imdecode", refuse)
    with pytest.raises(AposeError, match="rgb.png: not a readable PNG image .*CV_IO_MAX_IMAGE_PIXELS"):
        safeio.read_image(tmp_path / "rgb.png", cv2.IMREAD_COLOR)


# ------------------------------------------------------------------------------------------ minors


def test_a_pipe_named_like_a_capture_or_dataset_file_is_called_what_it_is(tmp_path):
    cap = _capture(tmp_path / "cap")
    (cap / "rgb.png").unlink()
    os.mkfifo(cap / "rgb.png")
    with pytest.raises(DatasetError, match=r"rgb.png: not a regular file \(a pipe, device or socket\)"):
        open_frames(cap)
    ds = tmp_path / "ds"
    ds.mkdir()
    os.mkfifo(ds / "dataset_info.json")
    for opener in (open_frames, Dataset):
        with pytest.raises(DatasetError, match=r"dataset_info.json: not a regular file \(a pipe, device or socket\)"):
            opener(ds)
    r = run("eval", ds)
    assert r.returncode == 2 and "dataset_info.json: not a regular file" in r.stderr, r.stderr


def test_a_file_that_fails_while_being_read_is_named(tmp_path):
    cap = _capture(tmp_path / "cap")
    (cap / "camera.json").unlink()
    (cap / "camera.json").symlink_to("/proc/self/mem")  # a regular file that answers EIO
    with pytest.raises(AposeError, match=r"camera.json: cannot be read \(Input/output error\)"):
        load_capture(cap)


def test_gltf_side_files_are_refused_in_our_words(tmp_path):
    (tmp_path / "outside.bin").write_bytes(b"\0" * 36)
    part = tmp_path / "part"
    part.mkdir()
    (part / "link.bin").symlink_to(tmp_path / "outside.bin")
    os.mkfifo(part / "pipe.bin")
    for uri, message in (("../outside.bin", "lies outside the mesh's folder"), ("/etc/passwd", "lies outside"),
                         ("link.bin", "lies outside"), ("pipe.bin", "not a regular file")):
        doc = {"asset": {"version": "2.0"}, "buffers": [{"uri": uri, "byteLength": 36}],
               "bufferViews": [{"buffer": 0, "byteLength": 36}],
               "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}],
               "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}], "nodes": [{"mesh": 0}],
               "scenes": [{"nodes": [0]}]}
        (part / "m.gltf").write_text(json.dumps(doc))
        with pytest.raises(MeshError) as e:
            load_mesh(part / "m.gltf")
        text = str(e.value)
        assert text.startswith(f"{part / 'm.gltf'}: it names the file {uri!r}") and message in text, text
        assert "FilePathResolver" not in text and "allow_anywhere" not in text


def test_an_assembly_loads_with_its_meshes_read_in_children(tiny_dir):
    """A guard: load_parts as the CLI, the studio and the API call it."""
    M._MESH_CACHE.clear()
    models = load_parts(load_assembly(tiny_dir / "assembly.yaml"))
    assert sorted(models) == ["cap", "peg", "plate"] and len(models["plate"].mesh.faces) == 12


# ---------------------------------------------------------------- second outside attack (#24): the neighbours


def test_an_obj_with_a_material_switch_per_face_reads_in_a_second(tmp_path):
    """10 MB, 150 000 triangles, one `usemtl` per face (some CAD exporters write it): 30 s of CPU and
    "decimate the part". Materials are never used, so their lines are dropped before the parse."""
    k = 80
    v = [f"v {i} {j} {(i * j) % 7}" for i in range(k) for j in range(k)]
    f = []
    for i in range(k - 1):
        for j in range(k - 1):
            a = i * k + j + 1
            f += [f"usemtl m{len(f)}", f"f {a} {a + 1} {a + k}", f"usemtl m{len(f) + 1}", f"f {a + 1} {a + k + 1} {a + k}"]
    (tmp_path / "mtl.obj").write_text("mtllib nowhere.mtl\n" + "\n".join(v + f) + "\n")
    t0 = time.process_time()
    mesh = load_mesh(tmp_path / "mtl.obj", "mm")
    assert len(mesh.faces) == 2 * (k - 1) ** 2 and time.process_time() - t0 < 10


def test_gltf_node_trees_are_bounded_from_the_json(tmp_path):
    """A one-triangle glTF with 100 000 nested nodes spent the whole 30 s CPU limit."""
    o, x, y, z = [0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]
    tri = np.array([o, y, x, o, x, z, o, z, y, x, y, z], np.float32).tobytes()  # a tetrahedron, 4 triangles

    def gltf(nodes):
        return json.dumps({"asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}], "nodes": nodes,
                           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
                           "accessors": [{"bufferView": 0, "componentType": 5126, "count": 12, "type": "VEC3",
                                          "min": [0, 0, 0], "max": [0.1, 0.1, 0.1]}],
                           "bufferViews": [{"buffer": 0, "byteLength": 144}],
                           "buffers": [{"byteLength": 144, "uri": "data:application/octet-stream;base64,"
                                        + base64.b64encode(tri).decode()}]})

    chain = lambda n: [{"children": [i + 1]} for i in range(n - 1)] + [{"mesh": 0}]  # noqa: E731
    for n, message in ((M.GLTF_MAX_NODES + 1, "nodes, over the"), (M.GLTF_MAX_DEPTH + 1, "nested over")):
        (tmp_path / "deep.gltf").write_text(gltf(chain(n)))
        t0 = time.time()
        with pytest.raises(MeshError, match=message):
            load_mesh(tmp_path / "deep.gltf")
        assert time.time() - t0 < 5
    (tmp_path / "ok.gltf").write_text(gltf(chain(M.GLTF_MAX_DEPTH)))
    assert len(load_mesh(tmp_path / "ok.gltf").faces) == 4


def test_a_json_key_given_twice_is_refused():
    """camera.json with "depth_scale" twice used the last one silently (YAML and TIFF refuse repeats)."""
    with pytest.raises(AposeError, match="the key 'depth_scale' is given twice"):
        safeio.parse_json('{"depth_scale": 1, "cx": 2, "depth_scale": 1e-9}', "camera.json")
    assert safeio.parse_json('{"a": {"k": 1}, "b": {"k": 2}}', "x") == {"a": {"k": 1}, "b": {"k": 2}}


def test_names_paths_and_keys_cannot_forge_or_disguise_output(tiny_dir, tmp_path):
    """A newline in an assembly's name or a part id forged an `error:` line; ESC, bidi and line
    separators in file names reached the terminal and the disk. Names refuse them; keys echoed in
    messages and paths show them as escapes."""
    from apose_studio.errors import AssemblyError

    text = (tiny_dir / "assembly.yaml").read_text()
    for bad, where in (('name: "bad\\n error: fake"', "name: holds the control or invisible character \\x0a"),
                       ('name: "a\\u202egpj"', "name: holds the control or invisible character \\u202e")):
        (tiny_dir / "bad.yaml").write_text(text.replace("name: ", bad + " #", 1))
        with pytest.raises(AssemblyError) as e:
            load_assembly(tiny_dir / "bad.yaml")
        assert where in str(e.value) and "\n error: fake" not in str(e.value)
    (tiny_dir / "bad.yaml").write_text(text.replace("parts:\n", 'parts:\n  "p\\nerror: fake":\n    mesh: x.stl\n', 1))
    with pytest.raises(AssemblyError) as e:
        load_assembly(tiny_dir / "bad.yaml")
    assert all(line.startswith(str(tiny_dir / "bad.yaml")) for line in str(e.value).splitlines()), str(e.value)
    for c in "\n\r\x1b\x85\u2028\u202e\u200b\ufeff":
        with pytest.raises(AposeError, match="control or invisible character"):
            safeio.check_path_text(f"meshes/a{c}b.stl", "mesh")
    assert safeio.check_path_text("meshes/Zahnrad é 字.stl") is not None


def test_poses_in_an_assembly_file_are_bounded_at_their_key(tiny_dir):
    """`translation: [1e308, 0, 10]` rendered 1e305 m; `euler_deg: [1e308, 0, 0]` was taken too."""
    from apose_studio.errors import AssemblyError

    text = (tiny_dir / "assembly.yaml").read_text()
    for old, new, message in (("[10, 0, 5]", "[1e308, 0, 5]", r"pose_in_base.translation\[0\]: 1e\+308 mm is beyond belief"),
                              ("[0, 0, 90]", "[0, 1e9, 0]", r"euler_deg\[1\]: 1e\+09° is beyond"),
                              ("[0, 10, 0]", "[0, -1.1e7, 0]", r"steps\[1\].pose_in_base.translation\[1\]: -1.1e\+07 mm is beyond")):
        (tiny_dir / "far.yaml").write_text(text.replace(old, new))
        with pytest.raises(AssemblyError, match=message):
            load_assembly(tiny_dir / "far.yaml")
    (tiny_dir / "near.yaml").write_text(text.replace("[10, 0, 5]", "[9.9e6, 0, 5]"))  # 9.9 km: allowed
    load_assembly(tiny_dir / "near.yaml")


def test_a_backup_costs_no_read_and_no_copy(tmp_path, monkeypatch):
    """Save over a 2 GB file read it whole into memory to write NAME.bak (2.65 GB RSS, a real 2 GB copy).
    The old file itself becomes the backup (a hard link); without hard links a small one is copied and a
    big one refused, never lost."""
    from apose_studio.assembly import fileio

    big = tmp_path / "huge.yaml"
    with open(big, "wb") as f:
        f.truncate(2 * 2 ** 30)  # sparse: no disk
    ino = big.stat().st_ino
    monkeypatch.setattr(type(big), "read_bytes", lambda self: pytest.fail("the old file was read"))
    fileio.atomic_write_bytes(big, b"name: new\n", backup=True)
    bak = tmp_path / "huge.yaml.bak"
    assert bak.stat().st_ino == ino and bak.stat().st_size == 2 * 2 ** 30 and big.read_text() == "name: new\n"
    assert big.stat().st_ino != ino
    monkeypatch.undo()

    def no_links(*a, **k):
        raise OSError(1, "Operation not permitted")

    monkeypatch.setattr(fileio.os, "link", no_links)
    fileio.atomic_write_bytes(big, b"name: newer\n", backup=True)  # small: copied
    assert bak.read_text() == "name: new\n" and big.read_text() == "name: newer\n"
    monkeypatch.setattr(fileio, "BACKUP_COPY_BYTES", 4)
    with pytest.raises(AposeError, match="cannot keep it as huge.yaml.bak without a copy"):
        fileio.atomic_write_bytes(big, b"name: newest\n", backup=True)
    assert big.read_text() == "name: newer\n" and bak.read_text() == "name: new\n"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_reads_within_follows_links_to_where_the_file_really_is(tmp_path):
    inside, outside = tmp_path / "ws", tmp_path / "elsewhere"
    inside.mkdir()
    outside.mkdir()
    (outside / "secret.txt").write_text("s")
    (inside / "own.txt").write_text("o")
    (inside / "link.txt").symlink_to(outside / "secret.txt")
    (inside / "dirlink").symlink_to(outside)
    with safeio.reads_within([inside]):
        assert safeio.read_text(inside / "own.txt") == "o"
        for path in (inside / "link.txt", inside / "dirlink" / "secret.txt", inside / ".." / "elsewhere" / "secret.txt"):
            with pytest.raises(AposeError, match="leads outside the studio's workspace"):
                safeio.read_text(path)
        with safeio.reads_within(None):  # nested: lifted for the block only
            assert safeio.read_text(inside / "link.txt") == "s"
        with pytest.raises(AposeError):
            safeio.read_text(inside / "link.txt")
    assert safeio.read_text(inside / "link.txt") == "s"


# ---------------------------------------------------------------- third round (#24): the neighbours of the neighbours


def test_every_number_of_an_assembly_file_is_bounded_at_its_key(tmp_path, tiny_dir):
    """A mate offset of 1e308 solved to a NaN pose that loaded (exit 0, `--json` with bare NaN) and broke
    render, estimate and the studio; approach distances, symmetry origins, huge quaternions and
    directions, and the YAML camera's focal length had no bound either."""
    import shutil

    from apose_studio.errors import AssemblyError

    src = SAMPLES / "planetary_reducer"
    folder = tmp_path / "p"
    shutil.copytree(src, folder)
    text = (folder / "assembly.yaml").read_text()
    assert "offset: 3" in text
    cases = [("offset: 3", "offset: 1e308", r"mates\[\d\]\.offset: expected a gap in the file's units within 10 km"),
             ("offset: 3", "offset: 1.1e7", r"mates\[\d\]\.offset: expected a gap"),
             ("format: apose-assembly/1", "format: apose-assembly/1\ncamera: {width: 640, height: 480, fx: 1e308, fy: 500, "
              "cx: 320, cy: 240}", r"camera\.fx: 1e\+308 px; a focal length is 10 to 100000")]
    for old, new, message in cases:
        (folder / "bad.yaml").write_text(text.replace(old, new, 1))
        with pytest.raises(AssemblyError, match=message):
            load_assembly(folder / "bad.yaml")
    from .conftest import TINY_YAML

    tiny = tiny_dir
    for old, new, message in (("order: 0}", "order: 0, origin: [0, 0, 1e308]}", r"symmetry\.origin\[2\]: 1e\+308 mm is beyond"),
                              ("euler_deg: [0, 0, 90], order: xyz", "quat_wxyz: [1e300, 0, 0, 0]", r"quat_wxyz\[0\]: 1e\+300 is beyond"),
                              ("translation: [0, 10, 0]\n", "translation: [0, 10, 0]\n    approach: {direction: [0, 0, 1], "
                               "distance: 1e308}\n", r"approach\.distance: expected a length > 0 in the file's units within 10 km")):
        assert old in TINY_YAML, old
        (tiny / "bad.yaml").write_text(TINY_YAML.replace(old, new, 1))
        with pytest.raises(AssemblyError, match=message):
            load_assembly(tiny / "bad.yaml")


def test_the_rest_of_unicode_s_invisible_characters_are_refused_and_escaped():
    """The soft hyphen, tag characters, U+034F, U+180E, U+3164 and variation selectors got into names,
    paths and upload names, and `apose show` printed them raw; one set now decides (Unicode categories
    Cc, Cf, Zl, Zp, Cs, Co, Cn and the blank-looking letters)."""
    from apose_studio.cli.common import printable

    for c in ("\u00ad", "\U000e0041", "\u034f", "\u180e", "\u3164", "\ufe0f", "\u2060", "\udc80", "\ue000"):
        assert safeio.unsafe_char(f"a{c}b") is not None, repr(c)
        assert c not in printable(f"a{c}b") and "\\" in printable(f"a{c}b"), repr(c)
        with pytest.raises(AposeError, match="control or invisible character"):
            safeio.check_path_text(f"a{c}b.stl")
    for fine in ("Zahnrad-Getriebe é ü ß", "歯車 字", "Ωmega – “quoted” 😀", "tab\there"):
        assert printable(fine) == fine and safeio.unsafe_char(fine, "\t") is None


def test_a_camera_json_with_two_forms_that_disagree_is_refused():
    """fx 615 beside a cam_K saying 900: one silently won and changed the estimate."""
    from apose_studio.data.dataset import check_camera_entry

    K = [615.0, 0, 320, 0, 615, 240, 0, 0, 1]
    cam, _, _ = check_camera_entry({"cam_K": K, "fx": 615, "depth_scale": 1.0}, "camera.json", 640, 480)
    assert cam.fx == 615
    with pytest.raises(DatasetError, match="fx is 615 but cam_K says 900; keep one form"):
        check_camera_entry({"cam_K": [900.0, *K[1:4], 900.0, *K[5:]], "fx": 615, "depth_scale": 1.0}, "camera.json",
                           640, 480)


def test_an_obj_s_unused_vertex_attributes_are_counted_before_parsing(tmp_path, monkeypatch):
    """30 M `vt` lines beside 4 triangles used the whole 2 GB limit, with the advice "decimate"."""
    trimesh.creation.box((10, 10, 10)).export(tmp_path / "box.obj")
    text = (tmp_path / "box.obj").read_text()
    (tmp_path / "vt.obj").write_text(text + "vt 0 0\n" * 40)
    (tmp_path / "vn.obj").write_text("vn\t0 0 1\n" * 40 + text)
    limits(monkeypatch, mesh_triangles=10)  # 3 x 10 = 30 attribute lines allowed
    for name, what in (("vt.obj", "40 texture coordinates"), ("vn.obj", "40 normals")):
        with pytest.raises(MeshError, match=f"it holds {what}.*export it again with geometry only"):
            load_mesh(tmp_path / name)


def test_a_backup_folder_in_the_way_is_named_not_an_internal_error(tmp_path):
    from apose_studio.assembly import fileio

    target = tmp_path / "a.yaml"
    target.write_text("old\n")
    (tmp_path / "a.yaml.bak").mkdir()
    with pytest.raises(AposeError, match="a.yaml.bak: a folder where the previous version of a.yaml is kept"):
        fileio.atomic_write_bytes(target, b"new\n", backup=True)
    assert target.read_text() == "old\n"


def test_random_bytes_named_stl_are_called_corrupt_not_too_big(tmp_path):
    """3 KB of random bytes as a .stl got "declares 168 M triangles ... decimate the part" (newcomer's
    finding): a header count the file's size cannot hold is corruption."""
    (tmp_path / "corrupt.stl").write_bytes(np.random.default_rng(3).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(MeshError, match=r"but the file is 3000 bytes.*corrupt or truncated: export it again") as e:
        load_mesh(tmp_path / "corrupt.stl")
    assert "decimate" not in str(e.value)


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """The JPEG with an EXIF APP1 segment whose only tag is Orientation (0x0112), as a phone or an editor writes it."""
    tiff = b"MM\x00*\x00\x00\x00\x08" + struct.pack(">H", 1) + struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0) + b"\x00" * 4
    app1 = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpeg[2:]


def test_a_jpeg_s_exif_orientation_does_not_turn_the_colour_against_the_depth(tmp_path):
    """An RGB-D colour image is registered to its depth pixel by pixel as stored: an EXIF orientation tag (3: shown
    upside down) must not turn it (OpenCV applies it by default), and a portrait-stored one is not called damaged."""
    from apose_studio.data.dataset import read_rgb

    img = np.zeros((48, 64, 3), np.uint8)
    img[:10, :20] = (255, 0, 0)  # red in the top-left corner, as stored
    ok, jpeg = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    (tmp_path / "tagged.jpg").write_bytes(_with_exif_orientation(jpeg.tobytes(), 3))
    assert cv2.imread(str(tmp_path / "tagged.jpg"))[:10, :20, 2].mean() < 100  # OpenCV alone turns it round
    rgb = read_rgb(tmp_path / "tagged.jpg")
    assert rgb.shape == (48, 64, 3) and rgb[:10, :20, 0].mean() > 200 and rgb[-10:, -20:, 0].mean() < 50
    (tmp_path / "portrait.jpg").write_bytes(_with_exif_orientation(jpeg.tobytes(), 6))  # shown turned a quarter
    assert read_rgb(tmp_path / "portrait.jpg").shape == (48, 64, 3)  # (before: "header says ... damaged or crafted")
