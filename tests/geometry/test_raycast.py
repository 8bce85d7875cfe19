"""Ray casting: a mesh's depth image, checked against a box whose faces are known by hand."""

import numpy as np
import trimesh

from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.raycast import own_edges, raycast_depth, raycast_points

CAM = CameraIntrinsics(640, 480, 615.0, 615.0, 320.0, 240.0)


def test_depth_of_a_box_facing_the_camera():
    """A 100 mm cube centred 1 m in front of the camera (OpenCV axes: z forward): its front face is at
    0.95 m; it covers the pixels whose rays pass within 50 mm of the axis at that depth, about
    +-32.4 px around the principal point; elsewhere the depth is inf. The depth image and the points
    agree pixel for pixel."""
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    T_world_mesh = se3.make_T(None, np.array([0.0, 0.0, 1.0]))
    z = raycast_depth(box, T_world_mesh, np.eye(4), CAM)
    assert z.shape == (480, 640)
    assert abs(z[240, 320] - 0.95) < 1e-6 and abs(z[240, 350] - 0.95) < 1e-6
    assert np.isinf(z[240, 355]) and np.isinf(z[0, 0]) and np.isinf(z[210, 320 + 40])
    half = 0.05 / 0.95 * 615.0
    u = np.arange(640) + 0.0
    expected = np.abs(u - 320.0) < half  # pixel centres inside the face's image along the middle row
    assert np.array_equal(np.isfinite(z[240]), expected)
    pts, _ = raycast_points(box, T_world_mesh, np.eye(4), CAM)
    assert len(pts) == int(np.isfinite(z).sum())
    assert np.allclose(np.sort(pts[:, 2]), np.sort(z[np.isfinite(z)]), atol=1e-6)


def test_depth_of_a_mesh_outside_the_image_is_inf_everywhere():
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    z = raycast_depth(box, se3.make_T(None, np.array([0.0, 0.0, -1.0])), np.eye(4), CAM)  # behind the camera
    assert np.isinf(z).all()
    z = raycast_depth(box, se3.make_T(None, np.array([5.0, 0.0, 1.0])), np.eye(4), CAM)  # far to the side
    assert np.isinf(z).all()


def test_own_edges_of_a_cube_seen_from_a_corner_are_its_three_inner_edges_not_its_outline():
    """A 100 mm cube seen along its diagonal shows three faces meeting at its nearest corner: the edges it
    shows of its own are the three edges from that corner (projected here by hand, with the pinhole model),
    not its outline against the background."""
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    T_world_camera = se3.look_at([0.35, 0.3, 0.4], [0.0, 0.0, 0.0])
    edges = own_edges(box, np.eye(4), T_world_camera, CAM)
    z = raycast_depth(box, np.eye(4), T_world_camera, CAM)
    seen = np.isfinite(z)

    def project(p):
        x = se3.transform_points(se3.inv(T_world_camera), np.atleast_2d(p))
        return np.stack([CAM.fx * x[:, 0] / x[:, 2] + CAM.cx, CAM.fy * x[:, 1] / x[:, 2] + CAM.cy], axis=1)

    corner = np.array([0.05, 0.05, 0.05])
    segments = [project(corner + (np.array(end) - corner) * np.linspace(0, 1, 200)[:, None])
                for end in ([-0.05, 0.05, 0.05], [0.05, -0.05, 0.05], [0.05, 0.05, -0.05])]
    line = np.concatenate(segments)
    vs, us = np.nonzero(edges)
    assert len(vs) > 100
    d = np.min(np.hypot(us[:, None] - line[None, :, 0], vs[:, None] - line[None, :, 1]), axis=1)
    assert d.max() < 2.0, d.max()  # every mark lies on an inner edge (pixel centres: within 2 px)
    for seg in segments:  # and each inner edge is marked along its length (its far end meets the outline)
        mid = seg[20:160]
        near = np.min(np.hypot(mid[:, None, 0] - us[None], mid[:, None, 1] - vs[None]), axis=1)
        assert near.max() < 1.5, near.max()
    outline = seen & ~(np.roll(seen, 1, 0) & np.roll(seen, -1, 0) & np.roll(seen, 1, 1) & np.roll(seen, -1, 1))
    ov, ou = np.nonzero(outline)
    d_out = np.min(np.hypot(ou[:, None] - line[None, :, 0], ov[:, None] - line[None, :, 1]), axis=1)
    assert not edges[ov[d_out > 3], ou[d_out > 3]].any()  # the outline, away from where the inner edges meet it
