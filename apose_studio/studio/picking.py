"""Picking a CAD face with a click: the ray hits a triangle, the triangle grows into the face it belongs
to, and the face is fitted as a plane (point + outward normal) or a cylinder/cone (axis point,
direction, radius). Pure functions over a part's mesh, in the part's own frame (metres).

A "face" is the set of triangles joined to the picked one across edges that bend less than
`SMOOTH_DEG`: CAD tessellations turn a round face by a few degrees per facet (5-20 deg on the
samples) and meet other faces at sharp edges (30 deg and more). The grouping is computed once per
mesh (`FacePicker.__init__`, about a second at 500,000 triangles, see benchmarks/studio.py); a pick
is then a ray cast and one fit over the face's triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from apose_studio.geometry import se3

SMOOTH_DEG = 25.0  # facets meeting at less than this belong to the same face
FIT_TRIANGLES = 20000  # a bigger face is fitted on an even spread of this many of its triangles
FLAT_DEG = 1.0  # a face whose normals all lie within this of their mean is a plane
ROUND_DEG = 2.0  # a cylinder's normals are all this close to perpendicular to its axis (else a cone)


@dataclass(frozen=True, eq=False)
class Feature:
    """A fitted face of one part, in the part's frame."""

    kind: str  # "plane" | "cylinder" | "cone" | "other" (neither: no mate takes it)
    point: np.ndarray  # plane: the picked point; cylinder/cone: the axis point nearest the picked point
    direction: np.ndarray  # plane: outward normal; cylinder/cone: axis direction (sign arbitrary)
    radius: float  # cylinder/cone: radius at the picked point (m); plane: 0
    faces: np.ndarray  # the triangles of the face (indices into the mesh)
    residual: float  # RMS distance of the face's vertices from the fitted surface (m)

    @property
    def is_axis(self) -> bool:
        return self.kind in ("cylinder", "cone")

    def describe(self) -> str:
        if self.kind == "other":
            return f"a face that is neither flat nor round, {len(self.faces)} triangles"
        if self.kind == "plane":
            n = self.direction
            return f"flat face, normal ({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f}), {len(self.faces)} triangles"
        d = self.direction
        return (f"{'round' if self.kind == 'cylinder' else 'conical'} face, {2 * self.radius * 1000:.2f} mm across, "
                f"axis ({d[0]:+.2f}, {d[1]:+.2f}, {d[2]:+.2f}), {len(self.faces)} triangles")


class FacePicker:
    """Ray casting and face grouping for one mesh (vertices in metres, part frame)."""

    def __init__(self, mesh):
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        self.normals = np.asarray(mesh.face_normals, dtype=np.float64)
        adj = np.asarray(mesh.face_adjacency)
        smooth = adj[np.asarray(mesh.face_adjacency_angles) < np.radians(SMOOTH_DEG)]
        n = len(self.faces)
        graph = coo_matrix((np.ones(len(smooth)), (smooth[:, 0], smooth[:, 1])), shape=(n, n))
        _, self.labels = connected_components(graph, directed=False)
        order = np.argsort(self.labels, kind="stable")
        self._order = order
        self._starts = np.searchsorted(self.labels[order], np.arange(self.labels.max() + 2))
        self._scene = None
        self.hit(self.vertices.mean(axis=0), [0.0, 0.0, 1.0])  # the ray caster builds its tree on the first ray

    def _raycaster(self):
        if self._scene is None:
            import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                o3d.core.Tensor(self.faces.astype(np.uint32)))
            self._scene = scene
        return self._scene

    def hit(self, origin, direction) -> tuple[int, np.ndarray] | None:
        """(triangle, point) where the ray first meets the mesh, or None."""
        import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        ans = self._raycaster().cast_rays(o3d.core.Tensor(np.concatenate([o, d])[None].astype(np.float32)))
        t = float(ans["t_hit"].numpy()[0])
        if not np.isfinite(t):
            return None
        tri = int(ans["primitive_ids"].numpy()[0])
        return tri, o + t * d

    def face_of(self, tri: int) -> np.ndarray:
        lab = self.labels[tri]
        return self._order[self._starts[lab]:self._starts[lab + 1]]

    def feature(self, tri: int, at: np.ndarray | None = None) -> Feature:
        """The fitted face that triangle `tri` belongs to; `at` is the picked point (default its centre)."""
        faces = self.face_of(tri)
        at = self.vertices[self.faces[tri]].mean(axis=0) if at is None else np.asarray(at, dtype=np.float64)
        some = faces[::-(-len(faces) // FIT_TRIANGLES)]  # CAD faces are exact surfaces: a spread fits them as well
        f = fit_face(self.vertices, self.faces[some], self.normals[some], some, at)
        return Feature(f.kind, f.point, f.direction, f.radius, faces, f.residual)

    def pick(self, origin, direction) -> Feature | None:
        h = self.hit(origin, direction)
        return None if h is None else self.feature(*h)


def fit_face(vertices: np.ndarray, tris: np.ndarray, normals: np.ndarray, face_ids: np.ndarray, at: np.ndarray) -> Feature:
    """Fit one face (its triangles `tris` with their normals) as a plane, a cylinder or a cone."""
    v = vertices[np.unique(tris)]
    centres = vertices[tris].mean(axis=1)
    areas = np.linalg.norm(np.cross(vertices[tris[:, 1]] - vertices[tris[:, 0]], vertices[tris[:, 2]] - vertices[tris[:, 0]]), axis=1)
    w = areas / max(areas.sum(), 1e-30)
    n_mean = (normals * w[:, None]).sum(axis=0)
    if np.linalg.norm(n_mean) > 1e-9:
        n_mean = n_mean / np.linalg.norm(n_mean)
        if np.all(normals @ n_mean > np.cos(np.radians(FLAT_DEG))):
            level = float(np.mean(v @ n_mean))  # the plane through the face's vertices (exact, unlike a ray's hit)
            off = v @ n_mean - level
            return Feature("plane", at - (at @ n_mean - level) * n_mean, n_mean, 0.0, face_ids,
                           float(np.sqrt(np.mean(off ** 2))))
    # round: the axis is the direction along which the normals vary least (perpendicular to all of them
    # on a cylinder, at a fixed angle on a cone)
    nc = normals - (normals * w[:, None]).sum(axis=0)
    _, _, Vt = np.linalg.svd(nc * np.sqrt(w)[:, None], full_matrices=False)
    axis = Vt[-1]
    along = normals @ axis
    tilt = float(np.abs((along * w).sum()))
    kind = "cylinder" if tilt < np.sin(np.radians(ROUND_DEG)) else "cone"
    if float(np.sqrt((w * (along - (along * w).sum()) ** 2).sum())) > np.sin(np.radians(ROUND_DEG)):
        kind = "other"  # the normals do not keep one angle to any axis: a torus, a fillet's blend, a freeform
    # the axis position: the circle through the vertices projected across the axis (algebraic fit, exact
    # for vertices on a circle); on a cone, the rings are concentric, so the same fit holds
    e1 = se3.perpendicular(axis)
    e2 = np.cross(axis, e1)
    pts = v if kind == "cylinder" else centres
    x, y = pts @ e1, pts @ e2
    cx, cy = _circle(x, y)
    res = np.abs(np.hypot(x - cx, y - cy) - np.hypot(x - cx, y - cy).mean())
    keep = res <= max(3.0 * float(np.median(res)), 1e-9)  # vertices cut onto a chord (a D-flat's corners) lie inside
    if 3 <= keep.sum() < len(x):
        x, y = x[keep], y[keep]
        cx, cy = _circle(x, y)
    centre = cx * e1 + cy * e2
    h = float(at @ axis)
    point = centre + h * axis  # on the axis, level with the pick
    radial = np.sqrt((x - cx) ** 2 + (y - cy) ** 2)
    if kind == "cylinder":  # the vertices lie on the surface; a picked point on a facet lies a hair inside
        r, res = float(radial.mean()), float(np.sqrt(np.mean((radial - radial.mean()) ** 2)))
    else:
        r, res = float(np.linalg.norm((at - point) - ((at - point) @ axis) * axis)), 0.0
    return Feature(kind, point, axis, r, face_ids, res)


def _circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Centre of the circle through points (x, y): the algebraic (Kasa) least-squares fit."""
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    sol = np.linalg.lstsq(A, x ** 2 + y ** 2, rcond=None)[0]
    return float(sol[0] / 2), float(sol[1] / 2)


def move_feature(f: Feature, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(point, direction) of a feature moved by T (4x4) into another frame."""
    return T[:3, :3] @ f.point + T[:3, 3], T[:3, :3] @ f.direction
