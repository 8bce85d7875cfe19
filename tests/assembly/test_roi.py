"""`roi:` on a part: a base that is a region of a larger part (assembly/roi.py)."""

import numpy as np
import pytest
import trimesh
import yaml

from apose_studio.assembly.mesh import base_body_mesh, base_mesh, load_parts
from apose_studio.assembly.model import load_assembly, save_assembly
from apose_studio.errors import AssemblyError, MeshError

from ..conftest import SAMPLES

SLAB_YAML = """\
format: apose-assembly/1
name: slab
units: mm
parts:
  seat_a:
    mesh: slab.stl
    roi: {box: {center: [-60, 0, 10], size: [40, 40, 30]}}
  seat_b:
    mesh: slab.stl
    roi: {sphere: {center: [60, 0, 10], radius: 25}}
  plain: {mesh: slab.stl}
  other: {mesh: slab.stl}
  pin: {mesh: pin.stl}
steps:
  - part: pin
    base: [seat_a]
    pose_in_base:
      translation: [-60, 0, 10]
"""


@pytest.fixture
def slab_dir(tmp_path):
    """A 200 x 80 x 10 mm slab (two long triangles per face: a region must split them) with two seats."""
    trimesh.creation.box((200, 80, 10), transform=trimesh.transformations.translation_matrix((0, 0, 5))).export(
        tmp_path / "slab.stl")
    trimesh.creation.cylinder(radius=3, height=10, sections=16).export(tmp_path / "pin.stl")
    (tmp_path / "assembly.yaml").write_text(SLAB_YAML)
    return tmp_path


def test_an_roi_is_read_in_the_files_units_and_saved_as_written(slab_dir):
    asm = load_assembly(slab_dir / "assembly.yaml")
    a, b = asm.parts["seat_a"].roi, asm.parts["seat_b"].roi
    assert a.kind == "box" and np.allclose(a.center, (-0.06, 0, 0.01)) and np.allclose(a.size, (0.04, 0.04, 0.03))
    assert b.kind == "sphere" and np.isclose(b.radius, 0.025) and asm.parts["plain"].roi is None
    again = load_assembly(save_assembly(asm, slab_dir / "saved.yaml"))
    assert again.parts["seat_a"].roi == a and again.parts["seat_b"].roi == b
    written = yaml.safe_load((slab_dir / "saved.yaml").read_text())["parts"]
    assert written["seat_a"]["roi"] == {"box": {"center": [-60, 0, 10], "size": [40, 40, 30]}}
    assert written["seat_b"]["roi"] == {"sphere": {"center": [60, 0, 10], "radius": 25}}
    assert "roi" not in written["plain"]


@pytest.mark.parametrize("roi,key,said", [
    ("{box: {center: [0, 0], size: [1, 1, 1]}}", "parts.seat_a.roi.box.center", "expected 3"),
    ("{box: {center: [0, 0, 0], size: [1, 0, 1]}}", "parts.seat_a.roi.box.size", "above 0"),
    ("{sphere: {center: [0, 0, 0], radius: -2}}", "parts.seat_a.roi.sphere.radius", "above 0"),
    ("{sphere: {center: [0, 0, 0], radius: .nan}}", "parts.seat_a.roi.sphere.radius", "above 0"),
    ("{box: {center: [0, 0, 0], size: [1, 1, 1]}, sphere: {center: [0, 0, 0], radius: 1}}", "parts.seat_a.roi",
     "one of box or sphere"),
    ("{cube: {center: [0, 0, 0]}}", "parts.seat_a.roi", "cube"),
    ("{box: {center: [0, 0, 0], size: [1, 1, 1], turn: 3}}", "parts.seat_a.roi.box", "turn"),
    ("{box: {center: [0, 0, 1e12], size: [1, 1, 1]}}", "parts.seat_a.roi.box.center[2]", "beyond belief"),
    ("[1, 2, 3]", "parts.seat_a.roi", "box"),
    ("{sphere: {center: [0, 0, 0], radius: -10000000000000000000000000}}", "parts.seat_a.roi.sphere.radius", "above 0"),
    ("{cylinder: {center: [0, 0, 0], size: [1, 1, 1]}}", "parts.seat_a.roi.cylinder", "unknown key"),
])
def test_a_bad_roi_is_refused_naming_its_key(slab_dir, roi, key, said):
    text = SLAB_YAML.replace("{box: {center: [-60, 0, 10], size: [40, 40, 30]}}", roi)
    (slab_dir / "bad.yaml").write_text(text)
    with pytest.raises(AssemblyError) as e:
        load_assembly(slab_dir / "bad.yaml")
    assert key in str(e.value) and said in str(e.value)


def test_the_registered_base_is_the_region_and_the_rendered_base_the_whole_part(slab_dir):
    asm = load_assembly(slab_dir / "assembly.yaml")
    models = load_parts(asm)
    region = base_mesh(models, asm.step_view(1))
    lo, hi = region.bounds
    # the slab's top and sides within the box (x -80..-40, y -20..20, z -5..25): split out of two long triangles
    assert np.allclose(lo, (-0.08, -0.02, 0.0), atol=0.004) and np.allclose(hi, (-0.04, 0.02, 0.01), atol=0.004)
    whole = base_body_mesh(models, asm.step_view(1))
    assert np.allclose(whole.bounds, [(-0.1, -0.04, 0.0), (0.1, 0.04, 0.01)], atol=1e-9)
    assert np.isclose(region.area, 0.04 * 0.04 * 2, rtol=0.15)  # the top and the bottom of the cut, no side
    sphere = models["seat_b"].region
    assert np.all(np.linalg.norm(sphere.triangles_center - (0.06, 0, 0.01), axis=1) <= 0.025 + 1e-9)


def test_regions_of_one_mesh_are_not_each_others_twins(slab_dir):
    asm = load_assembly(slab_dir / "assembly.yaml")
    assert asm.twins_of(("seat_a",)) == () and asm.twins_of(("plain",)) == ("other",)
    assert asm.base_is_region(1)


def test_an_roi_beside_the_part_is_refused_naming_the_part_and_the_fix(slab_dir):
    text = SLAB_YAML.replace("center: [-60, 0, 10], size", "center: [-600, 0, 10], size")
    (slab_dir / "beside.yaml").write_text(text)
    with pytest.raises(MeshError, match=r"part .seat_a.*slab.stl.*roi holds none of the mesh.s 12 faces.*move the roi onto the surface"):
        load_parts(load_assembly(slab_dir / "beside.yaml"))


def test_the_engine_sample_puts_each_arm_round_its_seats_post():
    """Independent of roi.py: each arm's pivot bore (its origin) lies on the axis of a post of the head mesh, within
    its seat's roi, and the arm rests on the seat's pad (the head's surface 3 mm below the arm's underside)."""
    asm = load_assembly(SAMPLES / "engine_head" / "assembly.yaml")
    models = load_parts(asm)
    head = models["seat_1"].mesh
    assert len(asm.roots) == 8 and all(asm.parts[r].roi is not None for r in asm.roots)
    for k, step in enumerate(asm.steps, 1):
        assert step.base == (f"seat_{k}",)
        T = step.T_base_part
        roi = asm.parts[f"seat_{k}"].roi
        assert roi.contains(T[:3, 3][None])[0]
        # the head's vertices round the arm's bore axis are the post's (5 mm round it), whose top stands 14 - 3 mm
        # above the arm's underside
        v = np.asarray(head.vertices)
        near = np.linalg.norm(v[:, :2] - T[:2, 3], axis=1) < 0.0051
        assert near.sum() >= 16 and np.isclose(v[near, 2].max(), T[2, 3] + 0.011, atol=1e-4)


def test_a_tiny_roi_on_a_huge_face_is_cut_in_bounded_time_and_size():
    """A 1 mm box on a 2 m slab: the faces near it are split into at most about MAX_SPLIT_FACES (not the millions
    that edges of an eighth of a millimetre would make), and the region still lies round the roi."""
    import time

    from apose_studio.assembly.roi import MAX_SPLIT_FACES, Roi, region_mesh

    slab = trimesh.creation.box((2.0, 2.0, 0.01))
    roi = Roi("box", (0.3, 0.2, 0.005), size=(0.001, 0.001, 0.004))
    t = time.perf_counter()
    with pytest.raises(MeshError, match=r"smaller than the mesh's faces there .*make it at least [0-9.]+ mm across"):
        region_mesh(slab, roi)  # on the surface, but smaller than the faces it may be split into
    bigger = Roi("box", (0.3, 0.2, 0.005), size=(0.02, 0.02, 0.004))
    region = region_mesh(slab, bigger)
    assert time.perf_counter() - t < 20
    assert len(region.faces) < MAX_SPLIT_FACES and np.all(np.abs(region.triangles_center[:, :2] - (0.3, 0.2)) <= 0.01)


def test_a_small_roi_on_a_long_thin_mesh_is_cut_in_bounded_time_and_size():
    """A shaft 2 m long and 2 mm across (256 long, thin faces) with a 10 mm roi: each face would split 4-fold per
    halving of its 2 m edge; the split stops at about MAX_SPLIT_FACES faces (it had taken 6.6 GB)."""
    import time

    from apose_studio.assembly.roi import MAX_SPLIT_FACES, Roi, region_mesh

    shaft = trimesh.creation.cylinder(radius=0.001, height=2.0, sections=64)
    t = time.perf_counter()
    try:
        region = region_mesh(shaft, Roi("box", (0.0, 0.0, 0.0), size=(0.01, 0.01, 0.01)))
        assert len(region.faces) <= MAX_SPLIT_FACES
    except MeshError as e:
        assert "make it at least" in str(e)
    assert time.perf_counter() - t < 20


def test_a_plain_region_is_told_from_one_that_pins_a_pose():
    """plainness: a flat patch of the head's deck slides along itself (0); a seat's pad with its post does not."""
    from apose_studio.assembly.roi import Roi, region_mesh
    from apose_studio.registration.base import PLAIN_SHARE, plainness

    models = load_parts(load_assembly(SAMPLES / "engine_head" / "assembly.yaml"))
    head = models["seat_1"].mesh
    assert plainness(models["seat_1"].region) > 2 * PLAIN_SHARE
    assert plainness(region_mesh(head, Roi("box", (0.0, 0.0, 0.084), size=(0.07, 0.03, 0.016)))) < PLAIN_SHARE


def test_look_alike_places_are_found_where_other_rois_mark_them_whatever_their_shape():
    """region_twins: seat 3's roi cut to its top (post and pad, no deck) and seat 2's a sphere: seat 2's place is still
    found alike to seat 3's (a shift of -80 mm along x, settled onto the head's surface from the rois' centres, which
    differ in height too)."""
    from dataclasses import replace

    from apose_studio.assembly.roi import Roi
    from apose_studio.estimation import region_twins

    asm = load_assembly(SAMPLES / "engine_head" / "assembly.yaml")
    parts = dict(asm.parts)
    parts["seat_3"] = replace(parts["seat_3"], roi=Roi("box", (0.04, 0.035, 0.106), size=(0.064, 0.05, 0.024)))
    parts["seat_2"] = replace(parts["seat_2"], roi=Roi("sphere", (-0.04, 0.035, 0.098), radius=0.022))
    asm = replace(asm, parts=parts)
    twins = dict(region_twins(load_parts(asm), asm.step_view(3)))
    assert "seat_2" in twins and np.allclose(twins["seat_2"][:3, 3], (-0.08, 0, 0), atol=0.001)
    assert len(twins) == 7
