"""STEP parts (#15): named solids through cascadio, several parts from one file, the committed sample
made by its script, and that sample end to end (load, render, estimate)."""

from __future__ import annotations

import importlib.util
import json
import math

import numpy as np
import pytest

from apose_studio.assembly.mesh import load_mesh, load_parts, step_solids
from apose_studio.assembly.model import load_assembly, save_assembly
from apose_studio.errors import MeshError
from apose_studio.studio import authoring

from ..cli.test_cli import run
from ..conftest import SAMPLES

BRACKET = SAMPLES / "step_bracket"


def _make_step():
    spec = importlib.util.spec_from_file_location("make_step", SAMPLES / "make_step.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_committed_step_sample_is_what_the_script_writes(tmp_path):
    for f in _make_step().generate(tmp_path):
        assert f.read_bytes() == (BRACKET / f.name).read_bytes(), f"{f.name} differs: run sample_assemblies/make_step.py"


def test_step_solids_keep_their_names_and_sizes():
    solids = step_solids(BRACKET / "bracket.step")
    assert sorted(solids) == ["bushing", "pin", "plate"]
    # volumes by hand (mm^3): the plate 60 x 40 x 8 less a 10 mm hole, plus a 10 mm boss 4 mm high; the pin a
    # 10 mm rod 30 long; the bushing a 20 mm tube with a 10 mm bore, 12 high. STEP is in mm, the meshes in m.
    expected = {"plate": 60 * 40 * 8 - math.pi * 25 * 8 + math.pi * 25 * 4, "pin": math.pi * 25 * 30,
                "bushing": math.pi * (100 - 25) * 12}
    for name, vol_mm3 in expected.items():
        mesh = load_mesh(BRACKET / "bracket.step", unit="mm", solid=name)  # the file's unit wins over `unit`
        assert mesh.is_watertight, name
        assert mesh.volume * 1e9 == pytest.approx(vol_mm3, rel=0.01), name
    np.testing.assert_allclose(load_mesh(BRACKET / "bracket.step", solid="pin").bounds, [[-0.005, -0.005, 0], [0.005, 0.005, 0.03]],
                               atol=1e-4)


def test_step_errors_name_the_file_and_the_fix(tmp_path):
    with pytest.raises(MeshError, match="has no solid named 'bolt'; its solids are .*plate.*set the part's `solid`"):
        load_mesh(BRACKET / "bracket.step", solid="bolt")
    ply = tmp_path / "a.ply"
    load_mesh(BRACKET / "bracket.step", solid="pin").export(ply)
    with pytest.raises(MeshError, match="names a solid of a STEP file, but this is a PLY mesh; remove `solid`"):
        load_mesh(ply, solid="pin")
    text = (BRACKET / "bracket.step").read_text()
    bad = tmp_path / "cut.step"
    bad.write_text(text[: len(text) // 3])
    with pytest.raises(MeshError, match="cut.step"):
        load_mesh(bad)
    notstep = tmp_path / "notes.step"
    notstep.write_text("hello\n")
    with pytest.raises(MeshError, match="a text file, not a STEP mesh"):
        load_mesh(notstep)


def test_a_step_file_with_several_solids_adds_a_part_per_solid(tmp_path):
    asm = authoring.new_assembly("t", "mm", tmp_path)
    asm, ids = authoring.add_mesh_parts(asm, BRACKET / "bracket.step")
    assert ids == ["plate", "pin", "bushing"] or sorted(ids) == ["bushing", "pin", "plate"]
    assert {asm.parts[i].solid for i in ids} == {"plate", "pin", "bushing"}
    models = load_parts(asm)
    assert models["pin"].diameter == pytest.approx(math.hypot(10, 30) / 1000, rel=0.02)
    asm = authoring.add_step(asm)
    saved = save_assembly(asm, tmp_path / "t.yaml")
    assert "solid: pin" in saved.read_text() and load_assembly(saved) == asm


def test_step_sample_end_to_end(tmp_path):
    asm = load_assembly(BRACKET / "assembly.yaml")
    # by hand: the pin in the hole at (15, 0), flush with the underside; the bushing on it, on the top (z = 8)
    np.testing.assert_allclose(asm.T_root_part("pin")[:3, 3], [0.015, 0, 0], atol=1e-12)
    np.testing.assert_allclose(asm.T_root_part("bushing")[:3, 3], [0.015, 0, 0.008], atol=1e-12)
    out = tmp_path / "ds"
    r = run("render", BRACKET / "assembly.yaml", "--out", out, "--frames", "2", "--steps", "2", "-q")
    assert r.returncode == 0, r.stderr
    est = run("estimate", out, "--step", "2", "--frame", "0", "--json")
    assert est.returncode == 0, est.stderr
    doc = json.loads(est.stdout)
    gt = json.loads((out / "test" / "000002" / "scene_gt.json").read_text())["0"]
    # ground truth from the renderer's record of where the plate is in the camera, composed with the hand pose
    T_cam_plate = np.eye(4)
    T_cam_plate[:3, :3] = np.reshape(gt[0]["cam_R_m2c"], (3, 3))
    T_cam_plate[:3, 3] = np.asarray(gt[0]["cam_t_m2c"]) / 1000
    assert doc["ok"], doc["reason"]
    expected = T_cam_plate[:3, 3] + T_cam_plate[:3, :3] @ [0.015, 0, 0.008]
    err = np.linalg.norm(np.asarray(doc["T_camera_part"])[:3, 3] - expected)
    assert err < 0.002, f"bushing {err * 1000:.2f} mm from where the hand pose puts it"
    # the approach: 30 mm above, along the plate's +z
    T_app = np.asarray(doc["T_world_part_approach"])
    up = np.asarray(doc["T_world_base"])[:3, 2]
    np.testing.assert_allclose(T_app[:3, 3] - np.asarray(doc["T_world_part"])[:3, 3], 0.03 * up, atol=1e-9)
