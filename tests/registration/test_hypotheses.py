"""Masks that the model checks (registration/hypotheses.py) and the new confidence terms (pose spread, the
table under the base, the outline), on synthetic scenes whose truth is built by hand; the render-based
failure kinds of real desks are in test_real_desks.py."""

from dataclasses import replace

import numpy as np
import trimesh

from apose_studio.geometry import se3
from apose_studio.geometry.sensor import quantisation_step
from apose_studio.registration import prepare_base
from apose_studio.registration.hypotheses import (
    colour_groups,
    explained,
    front_most,
    in_box,
    largest_patches,
    readings,
    too_high,
)
from apose_studio.registration.pipeline import off_table, outline_continuation
from apose_studio.registration.scoring import pose_spread
from apose_studio.registration.types import RegistrationResult, View

from .conftest import CAM, synthetic_view


def _box_base(extents=(0.1, 0.06, 0.05)):
    """A box standing on the table (z = 0), its frame at the bottom centre."""
    mesh = trimesh.creation.box(extents)
    mesh.apply_translation([0, 0, extents[2] / 2])
    return prepare_base(mesh, detect=False)


def _table_scene(base, T_world_base, T_world_camera, extra=()):
    """Depth of the table plane z = 0 with the base (and `extra` meshes, world frame) on it, exactly; the
    base's own mask."""
    from apose_studio.geometry.raycast import raycast_depth

    u, v = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    rays = np.stack([(u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u, float)], axis=-1)
    R, o = T_world_camera[:3, :3], T_world_camera[:3, 3]
    dz = rays @ R[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        table = np.where(dz < 0, -o[2] / dz, np.inf)
    z_base = raycast_depth(base.mesh, T_world_base, T_world_camera, CAM)
    depth = np.minimum(table, np.where(np.isfinite(z_base), z_base, np.inf))
    mask = np.isfinite(z_base) & (z_base <= depth)
    for m in extra:
        z = raycast_depth(m, np.eye(4), T_world_camera, CAM)
        depth = np.minimum(depth, np.where(np.isfinite(z), z, np.inf))
    mask &= np.isfinite(z_base) & (np.abs(depth - z_base) < 1e-6)
    return np.where(np.isfinite(depth), depth, 0).astype(np.float32), mask


CAMERA = se3.look_at([0.35, -0.3, 0.35], [0.0, 0.0, 0.03])


def test_what_lies_on_the_base_is_too_high_to_be_it():
    """A flat tin lying on a 50 mm box: its pixels stand higher above the table than the box reaches, the
    box's own do not; the reading below the base's height leaves out the tin and keeps the box."""
    base = _box_base()
    tin = trimesh.creation.cylinder(radius=0.02, height=0.012)
    tin.apply_translation([0.01, 0.0, 0.05 + 0.006])
    depth, box_mask = _table_scene(base, np.eye(4), CAMERA, [tin])
    from apose_studio.geometry.raycast import raycast_depth

    z_tin = raycast_depth(tin, np.eye(4), CAMERA, CAM)
    tin_mask = np.isfinite(z_tin) & (np.abs(z_tin - depth) < 1e-6)
    mask = box_mask | tin_mask  # a prompt that took the tin in
    view = View(depth, mask, CAM, CAMERA)
    high = too_high(view, base, (np.array([0.0, 0.0, 1.0]), 0.0), tol=0.004)
    assert (high & tin_mask).sum() > 0.5 * tin_mask.sum()  # the tin's top and the upper part of its side
    assert (high & box_mask).sum() == 0
    names = [n for n, _ in readings(view, base, (np.array([0.0, 0.0, 1.0]), 0.0), tol=0.004)]
    assert names[0] == "below the base's height"


def test_depth_patches_split_an_object_in_front():
    """Two boxes at different depths in one mask split at the depth jump into two patches, largest first."""
    depth = np.full((100, 120), 1.0, np.float32)
    depth[20:80, 10:60] = 0.8  # the nearer, larger
    depth[30:70, 70:110] = 0.9
    mask = np.zeros(depth.shape, bool)
    mask[20:80, 10:60] = mask[30:70, 70:110] = True
    patches = largest_patches(depth, mask, 2)
    assert len(patches) == 2
    assert patches[0][50, 30] and not patches[0][50, 90] and patches[1][50, 90] and not patches[1][50, 30]


def test_front_most_is_the_occluder_not_the_base_behind_it():
    """A chain in one mask: an occluder (0.70 m) in front of the base (0.90 m), which stands in front of
    something further back (0.95 m). Only the occluder is in front of a patch and behind none; the base,
    in front of the back one but behind the occluder, stays, as does the back one."""
    depth = np.full((100, 160), 1.2, np.float32)
    depth[20:80, 40:110] = 0.90  # the base
    depth[20:80, 110:140] = 0.95  # behind it, beside it
    depth[10:90, 10:60] = 0.70  # the occluder, over the base's left part
    mask = np.zeros(depth.shape, bool)
    mask[10:90, 10:140] = True
    mask[10:20, 60:140] = mask[80:90, 60:140] = False
    front = front_most(depth, mask)
    assert front[50, 30] and front[15, 20]  # the occluder, all of it
    assert not front[50, 80] and not front[50, 125]  # not the base, not what stands behind it
    assert (front & (depth == np.float32(0.90))).sum() <= 2 * 60  # at most the split edge's own pixels beside it
    alone = np.zeros_like(mask)
    alone[20:80, 40:110] = True
    assert not front_most(np.where(alone, np.float32(0.9), depth), alone).any()  # one patch: nothing in front
    apart = np.zeros_like(mask)  # two patches that do not meet: neither stands in front of the other
    apart[20:80, 70:100] = True
    apart[85:95, 10:30] = True
    far = depth.copy()
    far[85:95, 10:30] = 0.5
    assert not front_most(far, apart).any()
    view = View(depth, mask, CAM, se3.look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0]))
    base = _box_base()
    names = [n for n, _ in readings(view, base, None, tol=0.004)]
    assert "without what stands in front" in names


def test_what_lies_wholly_in_the_box_is_not_the_object_running_out_of_it():
    """A box prompt drawn round the strip that is seen of a base (0.90 m) behind an object in front (0.70 m)
    that fills most of the box and runs far out of it, and a speck of something else in the box: what lies
    wholly in the box is the strip, not the object in front, not the speck, not the far wall."""
    depth = np.full((200, 260), 1.5, np.float32)  # a wall behind
    depth[40:70, 60:180] = 0.90  # the base's strip, all in the box
    depth[70:200, 20:240] = 0.70  # the object in front, running out of the box
    depth[45:52, 200:207] = 0.80  # a speck of something small, in the box
    view = View(depth, np.zeros(depth.shape, bool), CAM, se3.look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
                box=(50, 30, 195, 120))
    own = in_box(view, None, tol=0.004)
    strip = depth == np.float32(0.90)
    assert own is not None and (own & strip).sum() > 0.95 * strip.sum()
    near_strip = np.zeros_like(strip)  # the jumps round the strip (their pixels are mixed): 2 px each way
    near_strip[38:72, 58:182] = True
    assert not (own & ~near_strip).any()  # not the object in front, not the speck, not the wall
    base = _box_base()
    names = [n for n, _ in readings(replace(view, mask=depth == np.float32(0.70)), base, None, tol=0.004)]
    assert names[0] == "what lies wholly in the box"
    assert in_box(replace(view, box=None), None, tol=0.004) is None  # no box: nothing to read it off


def _screening(base, depth, mask, T_world_camera):
    """A ModelSearch's screening parts over a hand-built scene (no Task: the scene's depth and mask, the
    camera, the coarse voxel), for seen_past and unhidden."""
    from types import SimpleNamespace

    from apose_studio.registration.searches import ModelSearch
    from apose_studio.registration.types import Observation

    pb = SimpleNamespace(observation=Observation(mask, depth, np.zeros_like(mask)), cam=CAM,
                         T_world_camera=T_world_camera, vg=base.diameter / 25, cam_pos=T_world_camera[:3, 3])
    ms = object.__new__(ModelSearch)
    ms.pb = pb
    pts, nrm = base.mesh.sample(4000, return_index=True)
    ms.model_pts, ms.model_nrm = np.asarray(pts), np.asarray(base.mesh.face_normals[nrm])
    ms.model_few = np.arange(0, 4000, 20)
    return ms, pb


def test_screening_charges_a_pose_where_the_camera_sees_past_it_not_one_hidden_behind_something():
    """A box on the table with a wall-like object in front of its left half. At the truth the camera sees
    past none of it; slid onto bare table it sees past most of what faces it; slid behind the object in
    front, nothing (it hides there, and the screening must not charge it). The ICP's source leaves out what
    the object in front hides (scoring.unhidden), not what the base's own mask shows nearer."""
    from apose_studio.registration.scoring import unhidden

    base = _box_base()
    camera = se3.look_at([0.0, -0.5, 0.25], [0.0, 0.0, 0.03])  # looking along +y
    wall = trimesh.creation.box((0.2, 0.01, 0.2))
    wall.apply_translation([-0.1, -0.08, 0.1])  # between the camera and the box's left half (x < 0)
    depth, mask = _table_scene(base, np.eye(4), camera, [wall])
    ms, pb = _screening(base, depth, mask, camera)
    at = lambda x, y: se3.make_T(np.eye(3), [x, y, 0.0])  # noqa: E731
    past = ms.seen_past([np.eye(4), at(0.2, 0.0), at(-0.12, 0.0)])
    assert past[0] < 0.05 and past[1] > 0.5, past
    assert past[2] < 0.2, past  # mostly behind the object in front
    pts = se3.transform_points(np.eye(4), ms.model_pts)
    shown = unhidden(pb, pts)
    left, right = pts[:, 0] < -0.005, pts[:, 0] > 0.005
    facing_front = ms.model_nrm[:, 1] < -0.9  # the box's face towards the camera and the wall
    assert shown[right & facing_front].all()  # nothing stands in front of its right half
    assert not shown[left & facing_front & (pts[:, 2] < 0.04)].any()  # the wall hides its left half's front
    behind = se3.transform_points(at(0.0, 0.05), ms.model_pts)  # slid back: its own mask's pixels lie nearer
    u, v = CAM.project(se3.transform_points(se3.inv(camera), behind))
    on_mask = mask[np.round(v).astype(int), np.round(u).astype(int)]
    assert on_mask.sum() > 100 and unhidden(pb, behind)[on_mask].all()


def test_colour_groups_split_two_colours_not_one_objects_shading():
    rgb = np.zeros((60, 80, 3), np.uint8)
    rgb[:, :40] = (200, 40, 40)  # a red tin
    rgb[:, 40:] = (120, 120, 125)  # on a grey box
    mask = np.ones((60, 80), bool)
    groups = colour_groups(rgb, mask)
    assert len(groups) == 2 and {bool(g[30, 10]) for g in groups} == {True, False}
    assert all(g[30, 10] != g[30, 70] for g in groups)
    shaded = np.zeros_like(rgb)
    shaded[:, :40] = (90, 90, 95)  # one grey object, one face lit, one in shade
    shaded[:, 40:] = (160, 160, 168)
    assert colour_groups(shaded, mask) == []


def test_explained_prefers_the_true_pose_and_counts_what_the_camera_sees_past():
    base = _box_base()
    depth, mask = _table_scene(base, np.eye(4), CAMERA)
    view = View(depth, mask, CAM, CAMERA)

    def result(T):
        return RegistrationResult(ok=True, T_world_base=T, voxel=base.diameter / 50, depth_noise=0.0)

    right = explained(result(np.eye(4)), view, base)
    assert right > 0.8 * mask.sum()
    lifted = explained(result(se3.make_T(np.eye(3), [0.0, 0.0, 0.03])), view, base)  # floating 30 mm up
    assert lifted < 0.5 * right
    beside = explained(result(se3.make_T(np.eye(3), [0.2, 0.0, 0.0])), view, base)  # on bare table: seen past
    assert beside < 0
    boxed = View(depth, mask, CAM, CAMERA, box=(0, 0, 5, 5))  # a prompt box that holds none of it
    assert explained(result(np.eye(4)), boxed, base) < 0
    assert explained(RegistrationResult(ok=False), view, base) == float("-inf")


def test_explained_counts_the_whole_image_also_where_the_base_runs_off_it():
    """`explained` counts in the window the model shows; the same counts over the whole image (computed here from
    the model's points splatted into a full-size buffer), with a prompt's box, and with the base half off the
    image's edge (the window clipped there)."""
    from apose_studio.registration.base import raycast_source
    from apose_studio.registration.hypotheses import CONTRADICTION_WEIGHT
    from apose_studio.registration.scoring import agreement_tolerance, mask_edge, pixels

    base = _box_base()

    def whole_image(r, view):
        seen, _ = raycast_source(base, r.T_world_base, view.T_world_camera, view.camera)
        v, u, z, inside = pixels(seen, view.T_world_camera, view.camera)
        zbuf = np.full(view.depth.shape, np.inf)
        for vv, uu, zz in zip(v[inside], u[inside], z[inside]):
            zbuf[vv, uu] = min(zbuf[vv, uu], zz)
        shown, d = np.isfinite(zbuf), view.depth
        valid = shown & (d > 0)
        tol = agreement_tolerance(r.voxel, r.depth_noise)
        confirmed = valid & view.mask & (np.abs(d - zbuf) < tol)
        past = valid & (d > zbuf + tol) & ~mask_edge(shown)
        if view.box is not None:
            past |= shown & view.outside_box() & ~(valid & (d < zbuf - tol))
        return float(confirmed.sum()) - CONTRADICTION_WEIGHT * float(past.sum())

    edge_camera = se3.look_at([0.35, -0.3, 0.35], [0.2, 0.3, 0.03])  # the base at the image's left edge
    for camera in (CAMERA, edge_camera):
        depth, mask = _table_scene(base, np.eye(4), camera)
        for box in (None, (0, 0, 200, 200)):
            view = View(depth, mask, CAM, camera, box=box)
            for T in (np.eye(4), se3.make_T(np.eye(3), [0.01, 0.005, 0.0]), se3.make_T(np.eye(3), [0.0, 0.0, 0.02])):
                r = RegistrationResult(ok=True, T_world_base=T, voxel=base.diameter / 50, depth_noise=0.0)
                assert explained(r, view, base) == whole_image(r, view)
    v, u, _, inside = pixels(base.samples, edge_camera, CAM)
    assert (~inside).mean() > 0.2 and (u[inside] < 3).any()  # the edge case is one: part of the base off the image


def test_the_model_cut_mask_is_the_whole_images_also_where_the_base_runs_off_it():
    """pipeline.model_cut_mask cuts in the window the model shows; here the same cut over the whole image: the mask
    where the model's depth (2 px wider, the nearer winning, nothing beyond the image) is not in front of it, and
    the result's mask (the silhouette exactly, what the mask missed added where the depth lies on the model)."""
    from apose_studio.registration.base import raycast_source
    from apose_studio.registration.pipeline import like_nearest_depth, mask_reach, model_cut_mask
    from apose_studio.registration.scoring import agreement_tolerance, pixels

    base = _box_base()
    edge_camera = se3.look_at([0.35, -0.3, 0.35], [0.2, 0.3, 0.03])  # the base half off the image's left edge
    for camera in (CAMERA, edge_camera):
        depth, mask = _table_scene(base, np.eye(4), camera)
        mask[::7] = False  # a mask that missed rows of the base: the result's mask adds them back
        depth[:, :2] = 0  # no depth in the image's first two columns (a sensor's edge)
        mask[:, :2] = True  # ... where the mask runs on: only the model may say what there is the base
        for T in (np.eye(4), se3.make_T(np.eye(3), [0.004, -0.003, 0.0])):
            r = RegistrationResult(ok=True, T_world_base=T, voxel=base.diameter / 50, depth_noise=0.0)
            view = View(depth, mask, CAM, camera)
            seen, _ = raycast_source(base, T, camera, CAM)
            v, u, z, inside = pixels(seen, camera, CAM)
            zbuf = np.full(depth.shape, np.inf)
            np.minimum.at(zbuf, (v[inside], u[inside]), z[inside])
            zbuf = zbuf.astype(np.float32)
            padded = np.pad(zbuf, 2, constant_values=np.inf)
            wider = np.min([padded[i:i + depth.shape[0], j:j + depth.shape[1]] for i in range(5) for j in range(5)], axis=0)
            tol = agreement_tolerance(r.voxel, 0.0)
            want = mask & np.isfinite(wider) & ~((depth > 0) & (depth < wider - tol))
            np.testing.assert_array_equal(model_cut_mask(r, view, base), want)
            reach = mask_reach(view)
            on = np.abs(depth - zbuf) < tol
            want = (mask & np.isfinite(zbuf) & ~((depth > 0) & (depth < zbuf - tol))) | (reach & on) | \
                like_nearest_depth(depth, on, reach & np.isfinite(zbuf))
            np.testing.assert_array_equal(model_cut_mask(r, view, base, reach=reach), want)


def test_what_the_depth_cannot_place_joins_the_result_mask_by_its_colour():
    """A grey box with a dark object standing in front of part of it, the dark object's depth mostly missing (a
    Kinect reads nothing off dark surfaces) and the box's own dark-free face with holes too; the prompt's mask
    took in all of it. The result's mask keeps the box's holes (their colour is that of the box's surface) and
    leaves out the dark object's (their colour is that of what stands in front); without a colour image, both
    stay, as the depth alone cannot tell them apart. The truth here is built by hand, pixel by pixel."""
    from apose_studio.registration.base import raycast_source
    from apose_studio.registration.pipeline import mask_reach, model_cut_mask
    from apose_studio.registration.scoring import pixels

    base = _box_base()
    depth, mask = _table_scene(base, np.eye(4), CAMERA)
    seen, _ = raycast_source(base, np.eye(4), CAMERA, CAM)
    v, u, z, inside = pixels(seen, CAMERA, CAM)
    zbuf = np.full(depth.shape, np.inf)
    np.minimum.at(zbuf, (v[inside], u[inside]), z[inside])
    silhouette = np.isfinite(zbuf)
    vs, us = np.nonzero(silhouette)
    rgb = np.full(depth.shape + (3,), 150, np.uint8)  # the box and the table: grey
    # the dark object: the silhouette's left third, 5 cm in front of the box; 85 % of its pixels without depth
    dark = silhouette & (np.arange(depth.shape[1])[None, :] < us.min() + (us.max() - us.min()) // 3)
    rgb[dark] = (20, 20, 30)
    rng = np.random.default_rng(0)
    depth[dark] = zbuf[dark] - 0.05
    dark_holes = dark & (rng.random(depth.shape) < 0.85)
    depth[dark_holes] = 0
    box_holes = silhouette & ~dark & (rng.random(depth.shape) < 0.1)  # the box's own holes, grey
    depth[box_holes] = 0
    mask = silhouette.copy()  # the prompt took in the box and the dark object
    r = RegistrationResult(ok=True, T_world_base=np.eye(4), voxel=base.diameter / 50, depth_noise=0.0)
    box = (int(us.min()) - 10, int(vs.min()) - 10, int(us.max()) + 11, int(vs.max()) + 11)
    for with_colour in (True, False):
        view = View(depth, mask, CAM, CAMERA, rgb=rgb if with_colour else None, box=box)
        got = model_cut_mask(r, view, base, reach=mask_reach(view))
        assert got[box_holes].all()  # the box's holes stay either way
        assert not got[dark & (depth > 0)].any()  # what the depth puts in front is cut either way
        if with_colour:
            assert not got[dark_holes].any(), int(got[dark_holes].sum())
            assert (got == (silhouette & ~dark)).all()  # exactly the box's pixels
        else:
            assert got[dark_holes].all()  # the depth alone keeps the mask's holes


def test_as_common_in_tells_colours_by_their_share_and_keeps_all_on_too_little():
    from apose_studio.registration.pipeline import COLOUR_MIN_PX, as_common_in

    rgb = np.zeros((10, 40, 3), np.uint8)
    rgb[:, :20] = (200, 30, 30)  # red on the left, blue on the right
    rgb[:, 20:] = (30, 30, 200)
    a = np.zeros((10, 40), bool)
    b = np.zeros((10, 40), bool)
    a[:, :18] = True  # a: mostly red, a little blue
    a[:, 20:22] = True
    b[:, 25:] = True  # b: blue
    got = as_common_in(rgb, a, b)
    assert got[:, :20].all() and not got[:, 20:].any()
    few = np.zeros_like(b)
    few.flat[:COLOUR_MIN_PX - 1] = True
    assert as_common_in(rgb, a, few).all()  # too few pixels to tell a colour by


def test_pose_spread_is_small_for_a_corner_and_large_for_a_plane():
    base = _box_base()
    rng = np.random.default_rng(0)
    # three faces of the box meeting at a corner pin every motion down
    pts = np.concatenate([np.c_[rng.uniform(-0.05, 0.05, 300), np.full(300, -0.03), rng.uniform(0, 0.05, 300)],
                          np.c_[np.full(300, 0.05), rng.uniform(-0.03, 0.03, 300), rng.uniform(0, 0.05, 300)],
                          np.c_[rng.uniform(-0.05, 0.05, 300), rng.uniform(-0.03, 0.03, 300), np.full(300, 0.05)]])
    corner = pose_spread(pts, np.eye(4), base, sigma=0.001, tol=0.003)
    top = pose_spread(pts[600:], np.eye(4), base, sigma=0.001, tol=0.003)  # the top face alone: it slides freely
    assert corner < 0.001 and top > 100 * corner
    assert pose_spread(pts[:5], np.eye(4), base, 0.001, 0.003) == float("inf")  # too few points to say


def test_a_pose_that_floats_or_sinks_is_off_the_table():
    base = _box_base()
    view = View(np.zeros((480, 640), np.float32), np.zeros((480, 640), bool), CAM, CAMERA)
    table = (np.array([0.0, 0.0, 1.0]), 0.0)

    def result(z):
        return RegistrationResult(ok=True, T_world_base=se3.make_T(np.eye(3), [0, 0, z]))

    assert off_table(result(0.002), view, base, 0.002, table) == 0.0  # within the slack (5 % of 0.122 m)
    assert abs(off_table(result(0.05), view, base, 0.002, table) - (0.05 - 0.05 * base.diameter)) < 1e-9
    assert off_table(result(-0.03), view, base, 0.002, table) < 0
    assert np.isnan(off_table(result(0.05), view, base, 0.002, None))


def test_a_model_laid_onto_a_larger_surface_has_it_running_past_its_outline():
    """The base's true outline on the table is a depth step but for its foot; the same box laid against a
    wall that goes on past it has the wall running past its outline all round."""
    base = _box_base()
    from apose_studio.geometry.raycast import raycast_points

    depth, mask = _table_scene(base, np.eye(4), CAMERA)
    seen, _ = raycast_points(base.mesh, np.eye(4), CAMERA, CAM)
    view = View(depth, mask, CAM, CAMERA)
    slack = 0.05 * base.diameter
    on_table = outline_continuation(seen, view, 0.004, (np.array([0.0, 0.0, 1.0]), 0.0), slack)
    assert on_table < 0.2
    # a wall: the box's front face extended far beyond it, at the face's depth
    T = se3.make_T(np.eye(3), [0.0, 0.0, 0.0])
    _, wall_mask = synthetic_view(base, T, CAMERA)
    z_face = np.where(wall_mask, depth, 0)
    wall = np.full(depth.shape, float(np.median(z_face[wall_mask])), np.float32)
    wall[wall_mask] = depth[wall_mask]
    seen_w, _ = raycast_points(base.mesh, T, CAMERA, CAM)
    laid = outline_continuation(seen_w, View(wall, wall_mask, CAM, CAMERA), 0.02, None, slack)
    assert laid > 0.5


def test_quantisation_step_is_read_off_the_depth():
    rng = np.random.default_rng(0)
    z = 1.0 + rng.normal(0, 0.002, (100, 100))
    region = np.ones(z.shape, bool)
    steps = np.round(z / 0.003) * 0.003  # a Kinect-like 3 mm step at 1 m
    assert abs(quantisation_step(steps.astype(np.float32), region) - 0.003) < 2e-4
    assert quantisation_step((np.round(z / 0.0001) * 0.0001).astype(np.float32), region) < 3e-4  # 0.1 mm PNG steps
    assert quantisation_step(np.zeros((100, 100), np.float32), region) == 0.0


def test_both_out_pairs_the_readings_that_are_parts_of_the_mask():
    """Each pair of readings (parts of one mask) gives what both keep, named by both; the box's own patches
    (not a part of the mask) are not paired, a pair like a reading already there is dropped, and a pair with
    too few pixels to hold the base is not offered."""
    from apose_studio.registration.hypotheses import IN_BOX_NAME, MAX_READINGS, both_out
    from apose_studio.registration.types import MIN_POINTS

    mask = np.zeros((40, 60), bool)
    mask[5:35, 5:55] = True
    top, left, thin = mask.copy(), mask.copy(), mask.copy()
    top[5:12] = False  # leaves out a tin lying on top
    left[:, 5:15] = False  # leaves out a box in front
    thin[:, 6:] = False  # keeps a sliver: with either of the others, too little
    box = mask.copy()
    pairs = both_out([(IN_BOX_NAME, box), ("below the base's height", top), ("without what stands in front", left),
                      ("sliver", thin)])
    assert [n for n, _ in pairs] == ["below the base's height, without what stands in front"]
    np.testing.assert_array_equal(pairs[0][1], top & left)
    assert (top & left).sum() >= MIN_POINTS > (top & thin).sum()
    same = both_out([("a", top), ("b", top.copy())])  # what both keep is the reading itself: nothing new
    assert same == []
    many = []
    for k in range(5):  # five readings, each leaving out its own 8 columns: ten distinct pairs
        r = mask.copy()
        r[:, 5 + 8 * k:13 + 8 * k] = False
        many.append((f"r{k}", r))
    assert [n for n, _ in both_out(many)] == ["r0, r1", "r0, r2", "r0, r3", "r0, r4"][:MAX_READINGS]
