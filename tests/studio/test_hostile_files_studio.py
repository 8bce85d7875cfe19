"""Safety round 3 (#24 re-test) in the studio: Open on an assembly whose STEP part never finishes
tessellating froze the whole server (K1), and Open data on a 66 KB TIFF bomb held the lock for 13 s at
4.8 GB (M-a). Now each is a notification within the limit, and the studio keeps serving."""

import json
import time

import cv2
import numpy as np
import trimesh

from apose_studio import safeio
from apose_studio.assembly import mesh as M

from ..conftest import SAMPLES
from ..test_hostile_files import _step_file, _tiff, spin
from .conftest import act, errors


def test_open_an_assembly_whose_step_part_never_finishes(studio, tmp_path, monkeypatch):
    import cascadio

    _step_file(tmp_path / "slow.step", {"a": (0, 0, 0, 10.0, 5.0)})
    trimesh.creation.box((20, 20, 20)).export(tmp_path / "base.stl")
    (tmp_path / "slow.yaml").write_text("format: apose-assembly/1\nname: s\nunits: mm\nparts:\n  p: {mesh: slow.step}\n"
                                        "  base: {mesh: base.stl}\nsteps:\n  - {part: p, base: [base], "
                                        "pose_in_base: {translation: [0, 0, 30]}}\n")
    monkeypatch.setattr(cascadio, "step_to_glb", spin)  # forked children inherit it
    monkeypatch.setattr(safeio, "LIMITS", safeio.Limits(parse_cpu_seconds=1))
    M._STEP_CACHE.clear()
    st = studio()
    st.files.f_path.value = str(tmp_path / "slow.yaml")
    t0 = time.time()
    act(st, st.files.on_open)
    assert time.time() - t0 < 20
    assert any("slow.step: tessellating this STEP file (OpenCASCADE) took more than 1 s of CPU time" in body
               for _, body, _ in errors(st)), st.notes
    gearbox = tmp_path / "gearbox"
    gearbox.mkdir()
    for f in (SAMPLES / "helical_gearbox").iterdir():
        (gearbox / f.name).write_bytes(f.read_bytes())
    st.files.f_path.value = str(gearbox / "assembly.yaml")
    act(st, st.files.on_open)  # still serving
    assert set(st.steps.mesh_handles) == {"casing", "pinion", "wheel", "lid"}


def test_open_data_on_a_tiff_bomb_is_refused_from_its_header(studio, tmp_path, monkeypatch):
    import zlib

    cap = tmp_path / "cap"
    cap.mkdir()
    cv2.imwrite(str(cap / "rgb.png"), np.full((48, 64, 3), 90, np.uint8))
    _tiff(cap / "depth.png", 8192, 8192, spp=4, bits=64, fmt=3, compression=8, data=zlib.compress(b"\0" * 2 ** 22, 9))
    (cap / "camera.json").write_text(json.dumps({"fx": 60, "fy": 60, "cx": 32, "cy": 24, "depth_scale": 1.0}))
    st = studio(SAMPLES / "helical_gearbox" / "assembly.yaml")
    st.inspect.i_path.value = str(cap)
    t0 = time.time()
    act(st, lambda c: st.inspect.open_frames(st.inspect.i_path.value, c))
    assert time.time() - t0 < 10
    assert any("depth.png: a 64-bit float TIFF with 4 channels" in body for _, body, _ in errors(st)), st.notes
