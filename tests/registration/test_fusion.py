"""Several views of one placement: a block whose only asymmetry is a small notch cut into one end
face (+x). From a camera in front (-y), both end faces face away: the block and its half turn look
the same (a boss would show in the silhouette; a notch does not). A second camera on the notch's side
settles it. Ground truth is the renderer's scene."""

import numpy as np
import pytest
import trimesh

from apose_studio.geometry import se3
from apose_studio.geometry.metrics import mssd
from apose_studio.registration import prepare_base, resolve_params
from apose_studio.registration.fusion import estimate_views
from apose_studio.registration.next_view import next_view
from apose_studio.registration.types import View

BLOCK_YAML = """\
format: apose-assembly/1
name: bossed_block
units: mm
parts:
  block: {mesh: block.stl}
  peg: {mesh: peg.stl}
steps:
  - part: peg
    base: [block]
    pose_in_base:
      translation: [25, 12, 24]
"""


@pytest.fixture(scope="module")
def bossed(tmp_path_factory):
    """(assembly, models, base, scene, grid, settings): the block (80 x 50 x 40 mm, a notch 14 x 14 mm
    and 12 mm deep in its +x face, off-centre towards +y; the estimator's tolerance here is 4 mm, so
    the notch is a feature it can see) standing at the CAD's pose, no distractors."""
    from apose_studio.assembly.mesh import base_mesh, load_parts
    from apose_studio.assembly.model import load_assembly
    from apose_studio.synth.frame import RenderSettings, sample_scene
    from apose_studio.synth.render import RayGrid

    d = tmp_path_factory.mktemp("bossed")
    block = trimesh.creation.box((80, 50, 40))
    notch = trimesh.creation.box((24, 14, 14)).apply_translation([40, 12, 0])  # 12 mm into the +x face
    block.difference(notch).export(d / "block.stl")
    trimesh.creation.cylinder(radius=5, height=8, sections=24).export(d / "peg.stl")
    (d / "assembly.yaml").write_text(BLOCK_YAML)
    asm = load_assembly(d / "assembly.yaml")
    models = load_parts(asm)
    view = asm.step_view(1)
    settings = RenderSettings(frames=1, base_pose="fixed", distractors=0)
    scene = sample_scene(models, view, settings, np.random.default_rng(0))
    base = prepare_base(base_mesh(models, view))
    return asm, models, base, scene, RayGrid(settings.camera), settings


def _look(bossed, azimuth_deg: float, elevation_deg: float = 35.0, distance: float = 0.45) -> View:
    scene = bossed[3]
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = scene.base_centre + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return _look_from(bossed, se3.look_at(eye, scene.base_centre), f"camera at {azimuth_deg:.0f} deg")


def _look_from(bossed, T_world_camera: np.ndarray, name: str = "advised camera") -> View:
    from apose_studio.synth.frame import view_of

    _, _, _, scene, grid, settings = bossed
    fr = view_of(scene, T_world_camera, grid, np.random.default_rng(1))
    block = next(i for i, o in enumerate(scene.objects) if o.part == "block")
    return View(fr.depth, fr.labels == block, settings.camera, T_world_camera, name)


def _truth(bossed):
    asm, models, _, scene, _, _ = bossed
    return scene.T_world_base @ asm.step_view(1).T_base_part, models["peg"]


def _right(T_world_part, bossed) -> bool:
    G, peg = _truth(bossed)
    return mssd(T_world_part, G, peg.samples, peg.symmetries) < 0.1 * peg.diameter


def test_the_notch_makes_the_half_turn_a_near_symmetry(bossed):
    base = bossed[2]
    assert len(base.symmetries) == 1  # no exact symmetry: the notch moves under every turn
    assert any(se3.rotation_angle_deg(S[:3, :3]) > 170 and abs(S[2, 2] - 1) < 1e-3 for S in base.near_symmetries)


def test_one_view_that_hides_the_boss_is_never_a_silent_miss(bossed):
    """From -y the notch (in +x) and its twin's (in -x) are both out of sight: the two placements
    are the same to the camera. The result is right and confident only if it can be; otherwise it says
    ambiguous (or not confident), and the truth is among its placements."""
    base = bossed[2]
    v = _look(bossed, -90.0)
    r = estimate_views([v], base, bossed[0].step_view(1).T_base_part, resolve_params("default"))
    assert r.ok
    if not _right(r.T_world_part, bossed):
        assert r.ambiguous or not r.confident
    assert r.ambiguous and not r.confident  # the view cannot tell; it says so
    assert _right(r.T_world_part, bossed) or any(_right(c.T_world_part, bossed) for c in r.alternatives)


def test_a_second_view_on_the_boss_settles_the_twin(bossed):
    base = bossed[2]
    T_base_part = bossed[0].step_view(1).T_base_part
    views = [_look(bossed, -90.0), _look(bossed, 10.0)]  # the second sees the +x face and its notch
    r = estimate_views(views, base, T_base_part, resolve_params("default"))
    assert r.ok and r.views == 2 and not r.ambiguous and r.confident, (r.reason, r.ambiguous, r.coverage)
    assert _right(r.T_world_part, bossed)


def test_the_advice_gives_views_that_settle_it_and_a_fused_result_is_never_confident_and_wrong(bossed):
    """Advice from looks that cannot settle the placement alone (the notch out of sight or at a grazing angle): each
    advised camera sees the rival placements differ on more pixels than the current one, and the scene rendered
    from there and fused with the first look gives the right placement confidently in most looks, and in every look
    either that or an ambiguous result with the right placement among its alternatives, never a confident wrong one.
    From 80 degrees up 25 the fused result was confident and wrong: the true placement entered the weighing as the
    chosen pose turned by a close twin, unfitted, scored 0.966 against 0.993 in the first look and was dropped there
    (refine.refine_and_polish). From -90 degrees (up 35) and 80 degrees (up 25), the advice stays open here: two cameras tie in
    how well they tell the rivals apart, and the one a pixel's rounding puts first faces the wrong placement's notch
    (on another CPU the same test's single look had been settled)."""
    base = bossed[2]
    T_base_part = bossed[0].step_view(1).T_base_part
    looks = [(-120, 25), (-90, 35), (80, 25), (80, 35), (120, 35), (150, 25), (-150, 35)]
    settled = 0
    for az, el in looks:
        v = _look(bossed, az, el)
        r = estimate_views([v], base, T_base_part, resolve_params("default"))
        assert r.ok and not (r.confident and not r.ambiguous), (az, el)  # the look alone does not settle it
        advice = next_view(r, base, [v.T_world_camera], v.camera)
        assert advice is not None and advice.pixels > 2 * max(advice.pixels_now, 1), (az, el, advice)
        fused = estimate_views([v, _look_from(bossed, advice.T_world_camera)], base, T_base_part, resolve_params("default"))
        assert fused.ok, (az, el, fused.reason)
        if fused.confident and not fused.ambiguous:
            assert _right(fused.T_world_part, bossed), (az, el)  # never confident and wrong
            settled += 1
        else:
            assert _right(fused.T_world_part, bossed) or any(_right(c.T_world_part, bossed) for c in fused.alternatives)
    assert settled >= 4, settled  # 5 of the 7 here


def test_views_whose_camera_poses_disagree_are_not_fused(bossed):
    base = bossed[2]
    T_base_part = bossed[0].step_view(1).T_base_part
    a, b = _look(bossed, -90.0), _look(bossed, 10.0)
    shifted = se3.make_T(np.eye(3), np.array([0.015, 0.0, 0.0])) @ b.T_world_camera  # the robot's pose 15 mm off
    r = estimate_views([a, View(b.depth, b.mask, b.camera, shifted, "camera B")], base, T_base_part,
                       resolve_params("default"))
    assert not r.ok and "camera B disagrees" in r.reason and "not fused" in r.reason, r.reason
