"""A part's region of interest (`roi:` in an assembly file): the base object is only this region of the
part's mesh, as a rocker-arm seat is a region of a large, only approximately modelled engine block.

An roi is a box (axis-aligned, `{box: {center: [x, y, z], size: [sx, sy, sz]}}`) or a sphere
(`{sphere: {center: [x, y, z], radius: r}}`) in the part's own frame, in the file's units. Where the
part is a step's base, the estimator registers the region alone: the faces whose centroids lie in it
(`region_mesh`). The renderer draws the whole part, and parts with an roi that share one mesh file are
regions of one body (assembly.model.Assembly.twins_of leaves them out). Metres inside, as everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from apose_studio.assembly.fileio import yaml_number as _num
from apose_studio.assembly.yamlcheck import Checker, kind
from apose_studio.errors import MeshError
from apose_studio.geometry.units import MAX_COORDINATE_M, unit_name

ROI_KINDS = ("box", "sphere")
MIN_REGION_FACES = 4  # a region holding fewer faces than this leaves nothing to register


@dataclass(frozen=True)
class Roi:
    """A region in a part's frame (metres): a box of `size` (full side lengths) about `center`, or a
    sphere of `radius` about it."""

    kind: str  # "box" | "sphere"
    center: tuple[float, float, float]
    size: tuple[float, float, float] = (0.0, 0.0, 0.0)  # box only
    radius: float = 0.0  # sphere only

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) whether each (N, 3) point of the part's frame lies in the region (its border included)."""
        d = np.asarray(points, float).reshape(-1, 3) - np.asarray(self.center)
        if self.kind == "sphere":
            return np.einsum("ij,ij->i", d, d) <= self.radius ** 2
        return np.all(np.abs(d) <= np.asarray(self.size) / 2, axis=1)

    def corners(self) -> np.ndarray:
        """(8, 3) corners of the region's box (a sphere's bounding cube), part frame: for drawing it."""
        half = np.asarray(self.size) / 2 if self.kind == "box" else np.full(3, self.radius)
        c = np.asarray(self.center)
        return np.array([c + half * np.array([x, y, z]) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])


def parse_roi(c: Checker, raw, key: str, scale: float) -> Roi | None:
    """The `roi` of a part (file units times `scale` = metres); errors go to `c`, naming the key."""
    spec = c.mapping(raw, key, ROI_KINDS, "{box: {center: [x, y, z], size: [sx, sy, sz]}} or "
                     "{sphere: {center: [x, y, z], radius: r}}")
    if spec is None:
        return None
    if len(spec) != 1:
        c.add(key, f"expected one of box or sphere, got {', '.join(map(str, spec)) or 'neither'}")
        return None
    (shape, body), = spec.items()
    if shape not in ROI_KINDS:  # named by Checker.mapping as an unknown key
        return None
    where = f"{key}.{shape}"
    allowed = ("center", "size") if shape == "box" else ("center", "radius")
    body = c.mapping(body, where, allowed, "{center: [x, y, z], size: [sx, sy, sz]}" if shape == "box"
                     else "{center: [x, y, z], radius: r}")
    if body is None:
        return None
    unit, limit = f" {unit_name(scale)}", MAX_COORDINATE_M / scale
    center = c.numbers(body.get("center"), f"{where}.center", 3, limit=limit, unit=unit)
    if shape == "box":
        size = c.numbers(body.get("size"), f"{where}.size", 3, limit=limit, unit=unit)
        if size is not None and min(size) <= 0:
            c.add(f"{where}.size", f"expected 3 lengths above 0 (the box's full sides), got {body['size']}")
            return None
        if center is None or size is None:
            return None
        return Roi("box", tuple(v * scale for v in center), size=tuple(v * scale for v in size))
    radius = body.get("radius")
    try:  # a whole number of 400 digits is an int that numpy cannot test
        ok = isinstance(radius, (int, float)) and not isinstance(radius, bool) and 0 < float(radius) <= limit
    except OverflowError:
        ok = False
    if not ok:
        c.add(f"{where}.radius", f"expected a length above 0 (at most {limit:g}{unit}), got {kind(radius)}")
        return None
    if center is None:
        return None
    return Roi("sphere", tuple(v * scale for v in center), radius=float(radius) * scale)


def roi_to_dict(roi: Roi, scale: float) -> dict:
    """The `roi` mapping as a file writes it (file units)."""
    centre = [_num(v / scale) for v in roi.center]
    if roi.kind == "box":
        return {"box": {"center": centre, "size": [_num(v / scale) for v in roi.size]}}
    return {"sphere": {"center": centre, "radius": _num(roi.radius / scale)}}


def region_mesh(mesh: trimesh.Trimesh, roi: Roi, what: str = "the part") -> trimesh.Trimesh:
    """The faces of `mesh` (part frame, metres) whose centroids lie in `roi`, as a mesh of their own; faces
    reaching into the roi's box are first split to edges of at most SPLIT_SHARE of its shortest side, so that
    the region follows the roi's outline and not the CAD's triangles (a deck drawn as two long triangles).
    Raises MeshError naming `what` when the region holds (almost) none of the surface: an roi drawn beside
    the part, or in other units than the file's."""
    n_file = len(mesh.faces)
    mesh = _split_near(mesh, roi)
    inside = roi.contains(np.asarray(mesh.triangles_center))
    if int(inside.sum()) < MIN_REGION_FACES:
        lo, hi = np.asarray(mesh.bounds)
        corners = roi.corners()
        tri = np.asarray(mesh.triangles)
        touching = np.all(tri.max(axis=1) >= corners.min(axis=0), axis=1) & np.all(tri.min(axis=1) <= corners.max(axis=0), axis=1)
        if touching.any():  # on the surface, but smaller than the faces there (split as far as MAX_SPLIT_FACES lets)
            edge = float(np.median(np.max(np.linalg.norm(tri[touching] - np.roll(tri[touching], 1, axis=1), axis=2), axis=1)))
            raise MeshError(f"{what}: its roi holds {int(inside.sum())} face centres: it is smaller than the mesh's faces "
                            f"there (edges of {edge * 1000:.3g} mm once split); make it at least {2 * edge * 1000:.3g} mm "
                            "across, in the file's units")
        raise MeshError(f"{what}: its roi holds none of the mesh's {n_file} faces (the mesh spans "
                        f"{np.round(lo * 1000, 1).tolist()} to {np.round(hi * 1000, 1).tolist()} mm in its own frame); "
                        "move the roi onto the surface to register, in the file's units")
    return mesh.submesh([np.nonzero(inside)[0]], append=True, repair=False)


SPLIT_SHARE = 1 / 8  # region_mesh: faces reaching into the roi are split to edges at most this share of its shortest side
MAX_SPLIT_FACES = 200_000  # ... but into at most about this many faces: a 1 mm roi on a face a metre long would
# otherwise become millions of faces (the edges stay longer then, and the region's border follows them)


def split_faces(longest: np.ndarray, edge: float) -> int:
    """How many faces splitting faces whose longest edges are `longest` to edges of at most `edge` makes (at most:
    subdivide_to_size halves every edge of a face per round, four faces for one)."""
    rounds = np.ceil(np.log2(np.maximum(np.asarray(longest, float) / edge, 1.0)))
    return int(np.sum(4.0 ** np.minimum(rounds, 30)))


def _split_near(mesh: trimesh.Trimesh, roi: Roi) -> trimesh.Trimesh:
    """`mesh` with the faces whose boxes overlap the roi's box split (trimesh.remesh.subdivide_to_size) to edges of
    SPLIT_SHARE of the roi's shortest side, or longer where that would make more than MAX_SPLIT_FACES faces
    (split_faces counts them before any is made)."""
    corners = roi.corners()
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    tri = np.asarray(mesh.triangles)
    near = np.all(tri.max(axis=1) >= lo, axis=1) & np.all(tri.min(axis=1) <= hi, axis=1)
    if not near.any():
        return mesh
    longest = np.max(np.linalg.norm(tri[near] - np.roll(tri[near], 1, axis=1), axis=2), axis=1)
    edge = float(np.min(hi - lo)) * SPLIT_SHARE
    while split_faces(longest, edge) > MAX_SPLIT_FACES:  # a long, thin face splits 4-fold per halving of its longest
        edge *= 2.0  # edge, whatever its area: a 2 m shaft of 256 faces had become millions
    rounds = int(np.max(np.ceil(np.log2(np.maximum(longest / edge, 1.0))))) + 1
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces[near], edge, max_iter=rounds)
    rest = mesh.faces[~near]
    return trimesh.Trimesh(np.vstack([mesh.vertices, v]), np.vstack([rest, f + len(mesh.vertices)]), process=False)
