import logging
import re

import numpy as np
import pytest
import trimesh

from apose_studio.assembly.mesh import (
    build_part_model,
    diameter,
    load_mesh,
    load_part,
    load_parts,
    sample_surface,
    symmetry_transforms,
)
from apose_studio.assembly.model import Part, Symmetry, load_assembly
from apose_studio.errors import MeshError
from apose_studio.geometry.se3 import transform_points


@pytest.mark.parametrize("ext", ["stl", "ply", "obj", "off", "glb"])
def test_formats_load_and_scale(tmp_path, ext):
    box = trimesh.creation.box((30, 20, 10))
    path = tmp_path / f"box.{ext}"
    box.export(path)
    m = load_mesh(path, "mm")
    np.testing.assert_allclose(m.extents, [0.030, 0.020, 0.010], atol=1e-9)


def test_gltf_with_several_nodes(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box((1, 1, 1)), transform=trimesh.transformations.translation_matrix([2, 0, 0]))
    scene.add_geometry(trimesh.creation.box((1, 1, 1)))
    scene.export(tmp_path / "two.glb")
    m = load_mesh(tmp_path / "two.glb", "cm")
    np.testing.assert_allclose(m.extents, [0.03, 0.01, 0.01], atol=1e-9)


@pytest.mark.parametrize("name,content,message", [
    ("missing.stl", None, "missing.stl: file not found"),
    ("empty.stl", b"", "empty.stl: the file is empty"),
    ("notes.txt", b"hello", "unsupported file type .txt; use one of .stl, .ply"),
    ("garbage.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01", "garbage.ply: could not be read as a PLY mesh"),
    ("cloud.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                  b"end_header\n0 0 0\n1 0 0\n0 1 0\n", "cloud.ply: has no triangles (a point cloud or empty mesh)"),
])
def test_bad_files(tmp_path, name, content, message):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(MeshError, match=re.escape(message)):
        load_mesh(path)


def test_nan_vertices(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="NaN or infinite"):
        load_mesh(path)


def test_step_without_cascadio_is_explained(tmp_path, monkeypatch):
    from apose_studio.assembly import mesh as M

    p = tmp_path / "part.step"
    p.write_text("ISO-10303-21;")
    monkeypatch.setattr(M, "step_supported", lambda: False)  # an install that lost it (it is a dependency)
    with pytest.raises(MeshError, match="STEP needs the package cascadio"):
        load_mesh(p)


def test_suspicious_units_warn_with_the_likely_unit(tmp_path, caplog):
    trimesh.creation.box((40, 30, 10)).export(tmp_path / "mm_part.stl")  # drawn in mm
    trimesh.creation.box((0.04, 0.03, 0.01)).export(tmp_path / "m_part.stl")  # drawn in m
    with caplog.at_level(logging.WARNING):
        as_m = load_part(Part("big", tmp_path / "mm_part.stl"), "m")
        as_mm = load_part(Part("tiny", tmp_path / "m_part.stl"), "mm")
        fine = load_part(Part("ok", tmp_path / "mm_part.stl"), "mm")
    assert "looks like it is in mm" in as_m.unit_warning and "'big'" in as_m.unit_warning
    assert "looks like it is in m " in as_mm.unit_warning
    assert fine.unit_warning is None
    assert "looks like it is in mm" in caplog.text


def test_diameter_and_boxes():
    cube = trimesh.creation.box((1, 2, 2))
    assert diameter(cube.vertices) == pytest.approx(3.0)
    model = build_part_model("c", cube)
    np.testing.assert_allclose(model.aabb, [[-0.5, -1, -1], [0.5, 1, 1]])
    np.testing.assert_allclose(sorted(model.obb_extents), [1, 2, 2], atol=1e-9)
    assert model.box_corners().shape == (8, 3)


def test_samples_on_surface_and_deterministic():
    cube = trimesh.creation.box((2, 2, 2))
    a, b = sample_surface(cube, 500, seed=3), sample_surface(cube, 500, seed=3)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(np.abs(a).max(axis=1), 1.0, atol=1e-12)  # every point on a face


def test_nfold_symmetry_maps_the_part_onto_itself():
    hexagon = trimesh.creation.cylinder(radius=1.0, height=0.5, sections=6)
    syms = symmetry_transforms(Symmetry((0, 0, 1), (0, 0, 0), 6))
    assert syms.shape == (6, 4, 4)
    np.testing.assert_allclose(syms[0], np.eye(4))
    pts = hexagon.vertices
    for S in syms:
        moved = transform_points(S, pts)
        d = np.linalg.norm(moved[:, None] - pts[None], axis=-1).min(axis=1)
        assert d.max() < 1e-9
    # the wrong order does not
    S = symmetry_transforms(Symmetry((0, 0, 1), (0, 0, 0), 4))[1]
    d = np.linalg.norm(transform_points(S, pts)[:, None] - pts[None], axis=-1).min(axis=1)
    assert d.max() > 0.1


def test_continuous_symmetry_discretised_like_bop():
    syms = symmetry_transforms(Symmetry((0, 0, 1), (0.1, 0, 0), 0))
    assert len(syms) == int(np.ceil(np.pi / 0.01))  # 315 steps: surface travel <= 1% of the diameter each
    origin = np.array([[0.1, 0.0, 0.5]])  # on the axis through the offset origin: fixed by every rotation
    for S in syms[:: 50]:
        np.testing.assert_allclose(transform_points(S, origin), origin, atol=1e-12)
    assert symmetry_transforms(None).shape == (1, 4, 4)


def test_load_parts_names_the_bad_part(tiny_dir):
    (tiny_dir / "cap.stl").write_bytes(b"solid broken\n facet normal")
    asm = load_assembly(tiny_dir / "assembly.yaml")
    with pytest.raises(MeshError, match="part 'cap': .*cap.stl"):
        load_parts(asm)


def test_real_parts_match_paper_diameters(fidget_yaml):
    models = load_parts(load_assembly(fidget_yaml))
    paper_cm = {"bottom_casing": 3.81, "left_gear": 2.78, "right_gear": 2.78, "top_casing": 3.82}
    for pid, d in paper_cm.items():
        assert models[pid].diameter * 100 == pytest.approx(d, abs=0.015), pid  # paper rounds to 0.01 cm
        assert models[pid].unit_warning is None


def test_large_meshes_fast_diameter_and_box_agree_with_exact():
    """Above EXACT_DIAMETER_POINTS the diameter comes from extreme points; check it against the exact one."""
    from apose_studio.assembly import mesh as M

    rng = np.random.default_rng(4)
    pts = rng.normal(size=(30000, 3)) * [0.03, 0.01, 0.004]
    fast = M.diameter(pts)
    exact = M._max_pairwise(pts[__import__("scipy").spatial.ConvexHull(pts).vertices])[0]
    assert exact * 0.999 <= fast <= exact + 1e-12
    torus = trimesh.creation.torus(0.03, 0.01, major_sections=400, minor_sections=100)  # 40k vertices
    assert len(torus.vertices) > M.EXACT_DIAMETER_POINTS
    assert abs(M.diameter(torus.vertices) - 0.08) < 0.08 * 1e-3
    T, ext = M.oriented_box(torus)
    local = trimesh.transform_points(torus.vertices, np.linalg.inv(T))
    assert (np.abs(local) <= ext / 2 + 1e-9).all()  # contains every vertex
    np.testing.assert_allclose(sorted(ext), [0.02, 0.08, 0.08], rtol=1e-2)  # and nearly tight


def test_merge_vertices_welds_stl_soup():
    from apose_studio.assembly.mesh import merge_vertices

    box = trimesh.creation.box((1, 2, 3))
    soup_v = box.vertices[box.faces].reshape(-1, 3)  # three vertices per triangle, as STL stores them
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    soup_f = np.vstack([soup_f, [[0, 0, 1]]])  # plus a collapsed triangle
    v, f = merge_vertices(soup_v, soup_f)
    assert len(v) == 8 and len(f) == 12
    m = trimesh.Trimesh(v, f, process=False)
    assert m.is_watertight and abs(m.volume - 6.0) < 1e-9
