"""The Inspect tab's pure parts: boxes, projection, clouds per registration stage, the result cache."""

from dataclasses import replace

import numpy as np

from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.registration import RegistrationResult, Stage
from apose_studio.studio import inspection

CAM = CameraIntrinsics(640, 480, 500.0, 500.0, 320.0, 240.0)


def test_box_segments_are_the_twelve_edges():
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 2) for z in (0, 3)], float)
    seg = inspection.box_segments(corners, np.eye(4))
    lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    assert sorted(lengths.round(6)) == [1.0] * 4 + [2.0] * 4 + [3.0] * 4


def test_projection_and_drawing():
    T_world_camera = se3.make_T(t=np.array([0.0, 0.0, -1.0]))  # camera 1 m behind the origin, looking along +z
    uv, front = inspection.project_points(np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.0], [0, 0, -2.0]]), T_world_camera, CAM)
    np.testing.assert_allclose(uv[:2], [[320, 240], [370, 140]])
    assert front.tolist() == [True, True, False]
    corners = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
    img = inspection.draw_boxes(np.zeros((480, 640, 3), np.uint8), CAM, T_world_camera, corners,
                                [(np.eye(4), inspection.GREEN)])
    ys, xs = np.nonzero(img[:, :, 1] > 100)
    # the front face (z = -0.05, 0.95 m away) spans 500 * 0.05 / 0.95 = 26.3 px each side of the centre
    assert abs(xs.min() - (320 - 26.3)) < 2 and abs(xs.max() - (320 + 26.3)) < 2
    assert img[:, :, 0].max() == 0 or img[:, :, 0].max() <= inspection.GREEN[0]


def test_scene_cloud_back_projects_and_thins():
    depth = np.full((480, 640), 0.5, np.float32)
    depth[0, 0] = np.nan
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[..., 2] = 200
    pts, cols = inspection.scene_cloud(depth, rgb, CAM, np.eye(4), max_points=20000)
    assert len(pts) <= 20000 * 1.1 and np.allclose(pts[:, 2], 0.5) and (cols[:, 2] == 200).all()
    assert np.isfinite(pts).all()


def test_replay_moves_the_source_by_each_stage():
    src = np.random.default_rng(0).random((50, 3))
    stages = [Stage("initial", np.eye(4), 0.1, 0.01), Stage("global", se3.make_T(t=np.array([1.0, 0, 0])), 0.8, 0.002),
              Stage("final", se3.make_T(t=np.array([1.0, 0.5, 0])), 0.9, 0.001)]
    r = RegistrationResult(ok=True, source_cloud=src, stages=stages)
    views = inspection.replay(r)
    assert [v.name for v in views] == ["initial", "global", "final"]
    np.testing.assert_allclose(views[2].source_world, src + [1.0, 0.5, 0], atol=1e-6)


def test_metrics_panel_and_cache():
    assert "Estimate frame" in inspection.metrics_markdown(None, None)
    assert "failed" in inspection.metrics_markdown(None, RegistrationResult(ok=False, reason="empty mask"))
    c = inspection.ResultCache()
    k = c.key("/d", 1, 3, "default", "gt", False)
    assert c.get(k) is None
    c.put(k, ("r", "s"))
    assert c.get(c.key("/d", 1, 3, "default", "gt", False)) == ("r", "s") and c.get(c.key("/d", 1, 3, "paper", "gt", False)) is None


def test_the_metrics_panel_says_when_the_base_s_own_turn_is_not_sure():
    """Confident about the part, with another turn of the base that places it alike and fits as well
    (base_alternatives): the panel stays confident and says the base's turn is not sure; without one it says
    nothing of the kind."""
    sure = RegistrationResult(ok=True, coverage=0.95, contradiction=0.0, spread=0.001, spread_allowed=0.01,
                              off_table=0.0, continuation=0.0)
    assert sure.confident and sure.base_confident
    assert "turn is not sure" not in inspection.metrics_markdown(None, sure)
    unsure = replace(sure, base_alternatives=[np.eye(4)])
    assert unsure.confident and not unsure.base_confident
    text = inspection.metrics_markdown(None, unsure)
    assert "ok and confident" in text and "the base's own turn is not sure: turned 1 other way(s)" in text


def test_the_metrics_panel_names_the_reading_of_the_mask_the_pose_came_from():
    """A pose read off another part of the prompt than its mask (a base mostly hidden behind an object the
    prompt took in) is named in the panel, as `apose estimate` names it; the mask as given names none."""
    r = RegistrationResult(ok=True, coverage=0.95, contradiction=0.0, spread=0.001, spread_allowed=0.01,
                           off_table=0.0, continuation=0.0)
    assert "mask read as" not in inspection.metrics_markdown(None, r)
    text = inspection.metrics_markdown(None, replace(r, reading="what lies wholly in the box"))
    assert "| mask read as | what lies wholly in the box |" in text


def test_the_metrics_panel_says_when_the_depth_lies_off_the_colour_image():
    """A result whose depth's edges lie off the colour image's (estimation.colour_checked) says by how much and
    what that may cost, and names the studio's remedy; one without says nothing."""
    r = RegistrationResult(ok=True, coverage=0.95, contradiction=0.0, spread=0.001, spread_allowed=0.01,
                           off_table=0.0, continuation=0.0)
    assert "depth vs colour" not in inspection.metrics_markdown(None, r)
    text = inspection.metrics_markdown(None, replace(r, colour_offset=0.0042, colour_offset_px=(3, -2)))
    assert "| depth vs colour | edges +3, -2 px apart (right, down): up to 4.2 mm off; tick Align depth to colour" in text
    assert "bleed" not in text
    text = inspection.metrics_markdown(None, replace(r, colour_offset=0.0042, colour_offset_px=(3, -2),
                                                     colour_offset_bleed=True))  # a bleed explains the edges as well
    assert ("| depth vs colour | edges +3, -2 px apart (right, down), or the depth's outlines bleed past the colour's by "
            "as much (the edges cannot tell which: the depth was not moved): up to 4.2 mm off") in text
    text = inspection.metrics_markdown(None, replace(r, depth_moved_px=(-2, 3)))  # estimation.estimate_view moved it
    assert "| depth vs colour | the depth's edges lay -2, +3 px (right, down) off the colour image's: moved back" in text


def test_point_on_ray_takes_the_nearest_hit():
    pts = np.array([[0, 0, 2.0], [0, 0, 1.0], [0.5, 0, 0.5], [0, 0, -1.0]])
    np.testing.assert_allclose(inspection.point_on_ray(pts, np.zeros(3), np.array([0, 0, 3.0]), 0.01), [0, 0, 1.0])
    assert inspection.point_on_ray(pts, np.zeros(3), np.array([0, 1.0, 0]), 0.01) is None


def test_the_mssd_shown_forgives_the_base_s_exact_symmetry_and_says_so():
    """A right estimate of a part on a base with an exact half-turn symmetry (the fidget's casing) is the
    same assembly as the truth turned half round; the panel, the step summary and the exported caption
    showed the strict 48 mm and read as wrong. They show the placement's MSSD, and the strict one beside it."""
    from types import SimpleNamespace

    from apose_studio.studio.inspection import mssd_text, placement_mssd

    twin = SimpleNamespace(mssd=0.04808, mssd_mod_base_sym=0.000048)
    assert placement_mssd(twin) == 0.000048
    assert mssd_text(twin).startswith("0.05 mm (48.08 mm to the truth's own orientation")
    plain = SimpleNamespace(mssd=0.0012, mssd_mod_base_sym=0.0012)
    assert placement_mssd(plain) == 0.0012 and mssd_text(plain) == "1.20 mm"
    assert placement_mssd(None) is None and placement_mssd(SimpleNamespace(mssd=None)) is None


def test_the_base_at_the_estimate_is_drawn_by_its_folds_and_borders():
    import trimesh

    box = trimesh.creation.box((0.1, 0.2, 0.3))  # 12 triangles: 12 folds of 90 degrees, 6 flat diagonals
    seg = inspection.feature_edges(box, 30.0)
    assert seg.shape == (12, 2, 3)
    lengths = sorted(np.round(np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1), 6))
    assert lengths == [0.1] * 4 + [0.2] * 4 + [0.3] * 4  # the box's edges, no diagonal
    square = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    seg = inspection.feature_edges(square, 30.0)  # flat and open: its four borders only
    assert sorted(np.round(np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1), 6)) == [1.0] * 4
    # a smooth sphere folds nowhere by 30 degrees; capped, the sharpest folds come first
    assert len(inspection.feature_edges(trimesh.creation.icosphere(3), 30.0)) == 0
    assert len(inspection.feature_edges(box, 30.0, max_segments=5)) == 5
    assert len(inspection.feature_edges(box, angle_deg=95.0)) == 0


def test_the_metrics_panel_names_its_errors_against_the_truth():
    from types import SimpleNamespace

    score = SimpleNamespace(adi=0.0002, mssd=0.0003, mssd_mod_base_sym=0.0003, te=0.0004, re_deg=0.5, mask_iou=None)
    r = RegistrationResult(ok=True, fitness=0.9, inlier_rmse=0.001, coverage=0.95, spread=0.0)
    text = inspection.metrics_markdown(score, r)
    assert "| te (translation error) | 0.40 mm |" in text and "| re (rotation error) | 0.50° |" in text


def test_an_inset_outline_runs_inside_the_one_drawn_on_the_edge():
    """The estimate's mask is the model's silhouette less what hides it: its outline drawn on its own edge lay under
    the model's outline, drawn after it, and showed only as dots where the two differ (a newcomer's report). With
    inset=1 it runs one pixel inside, so both show side by side."""
    from apose_studio.studio.inspection import CYAN, GREEN, draw_outline

    mask = np.zeros((40, 40), bool)
    mask[10:30, 8:32] = True
    image = np.zeros((40, 40, 3), np.uint8)
    draw_outline(image, mask, CYAN, inset=1)
    draw_outline(image, mask, GREEN)
    cyan = (image == np.array(CYAN, np.uint8)).all(axis=-1)
    green = (image == np.array(GREEN, np.uint8)).all(axis=-1)
    assert green[10, 8:32].all() and green[10:30, 8].all()  # the edge's own outline
    assert cyan[11, 9:31].all() and cyan[11:29, 9].all() and not cyan[10].any() and not cyan[:, 8].any()
    plain = draw_outline(np.zeros((40, 40, 3), np.uint8), mask, CYAN)
    assert (plain == np.array(CYAN, np.uint8)).all(axis=-1)[10, 8:32].all()  # without the inset: on the edge
