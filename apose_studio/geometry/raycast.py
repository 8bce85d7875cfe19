"""Ray casting of meshes through a pinhole camera (Open3D's RaycastingScene, one cached BVH per mesh):
what the renderer draws and what the estimator sees of a model at a pose (RCAST). Metres, OpenCV
camera axes (x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np
import trimesh

from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.sensor import depth_jump


class RayGrid:
    """Per-pixel camera-frame ray directions with z = 1, so a hit's t is its depth. Pixel (u, v) at its centre."""

    def __init__(self, cam: CameraIntrinsics):
        self.cam = cam
        u, v = np.meshgrid(np.arange(cam.width, dtype=np.float32), np.arange(cam.height, dtype=np.float32))
        self.dirs = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)

    def rays(self, T_frame_camera: np.ndarray, window=None) -> np.ndarray:
        """(h, w, 6) rays in some frame, for the whole image or a window (v0, v1, u0, u1)."""
        d = self.dirs if window is None else self.dirs[window[0]:window[1], window[2]:window[3]]
        R, t = T_frame_camera[:3, :3].astype(np.float32), T_frame_camera[:3, 3].astype(np.float32)
        out = np.empty(d.shape[:2] + (6,), np.float32)
        out[..., :3] = t
        out[..., 3:] = d @ R.T
        return out


class Body:
    """A mesh prepared once for ray casting and shading: its BVH in its own frame and plain arrays."""

    def __init__(self, mesh: trimesh.Trimesh):
        import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

        self.mesh = mesh  # keeps id(mesh) valid while cached
        v = np.asarray(mesh.vertices, dtype=np.float64)
        f = np.asarray(mesh.faces, dtype=np.int64)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
        self.normals = np.asarray(mesh.face_normals, dtype=np.float64)
        self.first = v[f[:, 0]]
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        self.n_faces = len(f)


_BODIES: dict[int, Body] = {}


def body(mesh: trimesh.Trimesh) -> Body:
    b = _BODIES.get(id(mesh))
    if b is None or b.mesh is not mesh:
        if len(_BODIES) > 256:  # bounded: a long session may see many assemblies
            _BODIES.clear()
        b = _BODIES[id(mesh)] = Body(mesh)
    return b


def pixel_window(corners: np.ndarray, T_cam_obj: np.ndarray, cam: CameraIntrinsics):
    """(v0, v1, u0, u1) pixel box holding the projection of a body's box corners; None when off-image.

    The whole image when the box reaches behind the camera.
    """
    p = se3.transform_points(T_cam_obj, corners)
    if np.any(p[:, 2] <= 1e-6):
        return 0, cam.height, 0, cam.width
    u, v = cam.project(p)
    u0, u1 = int(max(0, np.floor(u.min()))), int(min(cam.width, np.ceil(u.max()) + 1))
    v0, v1 = int(max(0, np.floor(v.min()))), int(min(cam.height, np.ceil(v.max()) + 1))
    return (v0, v1, u0, u1) if v1 > v0 and u1 > u0 else None


_GRIDS: dict[CameraIntrinsics, RayGrid] = {}


def ray_grid(cam: CameraIntrinsics) -> RayGrid:
    if cam not in _GRIDS:
        if len(_GRIDS) > 8:
            _GRIDS.clear()
        _GRIDS[cam] = RayGrid(cam)
    return _GRIDS[cam]


def raycast_points(mesh: trimesh.Trimesh, T_world_mesh: np.ndarray, T_world_camera: np.ndarray,
                   cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """What a camera sees of a mesh alone: (N, 3) points and (N, 3) unit normals facing the camera, world frame.

    One ray per pixel of `cam`, cast only over the mesh's image box, against its cached BVH.
    """
    cast = _cast(mesh, T_world_mesh, T_world_camera, cam)
    if cast is None:
        return np.zeros((0, 3)), np.zeros((0, 3))
    b, _, rays, hit = cast
    rays = rays.reshape(-1, 6)
    t = hit["t_hit"].numpy()
    ok = np.isfinite(t)
    dirs = rays[ok, 3:]
    pts = rays[0, :3] + t[ok, None] * dirs  # every ray starts at the camera
    n = facing_normals(b, hit["primitive_ids"].numpy().view(np.int32)[ok], dirs)
    return se3.transform_points(T_world_mesh, pts), n @ T_world_mesh[:3, :3].T


def facing_normals(b: "Body", primitive_ids: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N, 3) the unit normals of the triangles hit (mesh frame), turned to face the rays' (N, 3) directions' origin."""
    n = b.normals[primitive_ids]
    return n * np.where(np.einsum("ij,ij->i", n, directions) > 0, -1.0, 1.0)[:, None]


def raycast_depth(mesh: trimesh.Trimesh, T_world_mesh: np.ndarray, T_world_camera: np.ndarray,
                  cam: CameraIntrinsics) -> np.ndarray:
    """(H, W) depth (metres along the camera's axis) of a mesh alone, inf where a pixel's ray misses it:
    the renderer's ray cast, one ray per pixel centre (a ray's t is its depth: RayGrid's z = 1)."""
    z = np.full((cam.height, cam.width), np.inf)
    cast = _cast(mesh, T_world_mesh, T_world_camera, cam)
    if cast is not None:
        _, w, rays, hit = cast
        z[w[0]:w[1], w[2]:w[3]] = hit["t_hit"].numpy().reshape(rays.shape[:2])
    return z


def _cast(mesh: trimesh.Trimesh, T_world_mesh: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics):
    """(body, pixel window, (h, w, 6) rays in the mesh frame, Open3D hits) of one ray per pixel over the
    mesh's image box; None when the mesh is outside the image."""
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    b = body(mesh)
    w = pixel_window(b.corners, se3.inv(T_world_camera) @ T_world_mesh, cam)
    if w is None:
        return None
    rays = ray_grid(cam).rays(se3.inv(T_world_mesh) @ T_world_camera, w)
    return b, w, rays, b.scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6)), nthreads=0)


def _cast_depths(mesh: trimesh.Trimesh, T_world_mesh: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics):
    """_cast's (scene, window, rays, hits) and each ray's distance to its hit ((h, w) of the window, inf: none), or
    None where the mesh is not in view."""
    cast = _cast(mesh, T_world_mesh, T_world_camera, cam)
    if cast is None:
        return None
    b, w, rays, hit = cast
    return b, w, rays, hit, hit["t_hit"].numpy().reshape(rays.shape[:2])


CREASE_DEG = 25.0  # own_edges: neighbouring pixels whose surface normals lie farther apart than this show a crease


def own_edges(mesh: trimesh.Trimesh, T_world_mesh: np.ndarray, T_world_camera: np.ndarray,
              cam: CameraIntrinsics) -> np.ndarray:
    """(H, W) bool: the pixels where a mesh alone, at a pose, shows an edge inside its own image: a crease
    (neighbouring pixels' normals more than CREASE_DEG apart: a box's top face against its side) or a jump in
    depth (an inner outline: a rim over a cavity, a boss over a face), marked on both sides. Its shading or
    colour may change there in any image, so colour edges there say nothing about how the depth lies against
    the colour image (geometry.sensor.shift_evidence). The outline against what lies behind is not marked."""
    out = np.zeros((cam.height, cam.width), bool)
    cast = _cast_depths(mesh, T_world_mesh, T_world_camera, cam)
    if cast is None:
        return out
    b, w, rays, hit, t = cast
    h, wd = t.shape
    ok = np.isfinite(t)
    n = np.zeros((h, wd, 3))
    n[ok] = facing_normals(b, hit["primitive_ids"].numpy().view(np.int32).reshape(h, wd)[ok], rays[ok][:, 3:])
    z = np.where(ok, t, 0.0)
    cos = np.cos(np.radians(CREASE_DEG))
    edges = np.zeros((h, wd), bool)
    for dv, du in ((0, 1), (1, 0)):  # each pixel against its right and its lower neighbour
        a, c = (slice(0, h - dv), slice(0, wd - du)), (slice(dv, h), slice(du, wd))
        e = ok[a] & ok[c] & ((np.einsum("hwi,hwi->hw", n[a], n[c]) < cos) | depth_jump(z[a], z[c]))
        edges[a] |= e
        edges[c] |= e
    out[w[0]:w[1], w[2]:w[3]] = edges
    return out


def silhouette_outline(mesh: trimesh.Trimesh, T_world_mesh: np.ndarray, T_world_camera: np.ndarray,
                       cam: CameraIntrinsics) -> np.ndarray:
    """(H, W) bool: the pixels of a mesh's silhouette at a pose, alone in the image, that border a pixel it does not
    cover (its outline against whatever lies behind). Where the pose is right, the colour image's edges run there
    (geometry.sensor.outline_shift_ratio); where it was fitted to depth lying off the colour image, they run that
    far off."""
    out = np.zeros((cam.height, cam.width), bool)
    cast = _cast_depths(mesh, T_world_mesh, T_world_camera, cam)
    if cast is None:
        return out
    w, ok = cast[1], np.isfinite(cast[4])
    inner = ok.copy()
    inner[1:] &= ok[:-1]
    inner[:-1] &= ok[1:]
    inner[:, 1:] &= ok[:, :-1]
    inner[:, :-1] &= ok[:, 1:]
    out[w[0]:w[1], w[2]:w[3]] = ok & ~inner
    return out
