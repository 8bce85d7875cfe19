"""CAD loading and per-part geometry: diameter, bounding boxes, surface samples, symmetry sets.

Meshes are read with trimesh and scaled to metres here; nothing past this module sees file units.
"""

from __future__ import annotations

import io
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from apose_studio import safeio
from apose_studio.assembly.model import Assembly, Part, StepView, Symmetry
from apose_studio.errors import AposeError, MeshError
from apose_studio.geometry import se3
from apose_studio.geometry.units import UNIT_TO_M, suspicious_unit

log = logging.getLogger(__name__)

MESH_EXTENSIONS = (".stl", ".ply", ".obj", ".off", ".glb", ".gltf")
STEP_EXTENSIONS = (".step", ".stp")
BOP_SYMMETRY_STEP = 0.01  # BOP: max surface travel per discretisation step, as a fraction of diameter


def supported_extensions() -> tuple[str, ...]:
    return MESH_EXTENSIONS + (STEP_EXTENSIONS if step_supported() else ())


def step_supported() -> bool:
    """STEP goes through trimesh's cascadio (OpenCASCADE) loader (a dependency; checked for old installs)."""
    try:
        import cascadio  # noqa: F401
    except ImportError:
        return False
    return True


def merge_vertices(vertices: np.ndarray, faces: np.ndarray, bits: int = 21) -> tuple[np.ndarray, np.ndarray]:
    """Weld coincident vertices (STL stores three per triangle) and drop triangles that collapse.

    Vertices are keyed on a grid of 2^bits cells across the largest extent (50 nm on a 10 cm part),
    one int64 per vertex, so this is one np.unique: about 5x faster than trimesh's processing at 500k
    triangles. Kept vertices keep their exact coordinates; unreferenced ones are dropped.
    """
    lo = vertices.min(axis=0)
    span = float((vertices.max(axis=0) - lo).max()) or 1.0
    q = np.round((vertices - lo) * ((2 ** bits - 1) / span)).astype(np.int64)
    key = (q[:, 0] << (2 * bits)) | (q[:, 1] << bits) | q[:, 2]
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    key = np.where(used, key, -1)
    uniq, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    keep = uniq >= 0
    remap = np.cumsum(keep) - 1
    f = remap[inverse.ravel()[faces]]
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return vertices[first[keep]], f[good]


def load_mesh(path: str | Path, unit: str = "m", solid: str | None = None) -> trimesh.Trimesh:
    """Read a surface mesh and scale it to metres. Raises MeshError naming the file and the fix.

    STEP files carry their own length unit and are read in metres whatever `unit` says; `solid` picks
    one named solid of a STEP file (None: all of them as one part)."""
    path = Path(path)
    ext = path.suffix.lower()
    try:
        fd, st = safeio.open_regular(path, "a mesh file")
        os.close(fd)
    except AposeError as e:
        raise MeshError(str(e)) from None
    cap = safeio.LIMITS.mesh_bytes
    if st.st_size > cap:
        raise MeshError(f"{path}: {st.st_size / 2**20:.0f} MB, over the {cap // 2**20} MB a mesh file may have; "
                        "decimate the part (a few hundred thousand triangles are plenty) or export it as binary STL/GLB")
    if ext in STEP_EXTENSIONS and not step_supported():
        raise MeshError(f"{path}: STEP needs the package cascadio (pip install cascadio), "
                        "or export the part as STL/PLY/OBJ/GLB")
    if ext not in supported_extensions():
        raise MeshError(f"{path}: unsupported file type {ext or '(none)'}; "
                        f"use one of {', '.join(supported_extensions())}")
    if st.st_size == 0:
        raise MeshError(f"{path}: the file is empty")
    wrong = _not_a(path, ext)
    if wrong:
        raise MeshError(f"{path}: {wrong}, not a {ext[1:].upper()} mesh; export the part's surface as a mesh file")
    if solid is not None and ext not in STEP_EXTENSIONS:
        raise MeshError(f"{path}: `solid: {solid}` names a solid of a STEP file, but this is a {ext[1:].upper()} mesh; "
                        "remove `solid`")
    if ext in STEP_EXTENSIONS:
        loaded, unit = _step_solid(path, solid), "m"
    else:
        try:
            data = safeio.read_bytes(path, "a mesh file", cap)  # the bytes read are what is parsed
        except AposeError as e:
            raise MeshError(str(e)) from None
        _check_declared_size(path, ext, data)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                loaded = trimesh.load(io.BytesIO(data), file_type=ext[1:], force="mesh", process=False,
                                      resolver=_ConfinedResolver(str(path), [cap - len(data)]))
        except AposeError as e:  # from the resolver: a buffer or material file that may not be read
            raise MeshError(f"{path}: {e}") from None
        except (Exception, RecursionError) as e:  # trimesh raises many types on corrupt input
            raise MeshError(f"{path}: could not be read as a {ext[1:].upper()} mesh (corrupt or truncated?): "
                            f"{type(e).__name__}: {str(e)[:200]}") from None
        finally:
            data = None
    if not isinstance(loaded, trimesh.Trimesh):
        kind = type(loaded).__name__
        raise MeshError(f"{path}: holds a {kind} with no triangles, not a surface mesh; export the part's surface")
    if len(loaded.faces) == 0:
        raise MeshError(f"{path}: has no triangles (a point cloud or empty mesh); export the part's surface")
    if len(loaded.faces) > safeio.LIMITS.mesh_triangles:
        raise MeshError(f"{path}: {len(loaded.faces)} triangles, over the {safeio.LIMITS.mesh_triangles} a part may have; "
                        "decimate it (a few hundred thousand triangles are plenty for registration)")
    faces_raw = np.asarray(loaded.faces)
    if faces_raw.min() < 0 or faces_raw.max() >= len(loaded.vertices):
        raise MeshError(f"{path}: a triangle names vertex {int(faces_raw.max()) if faces_raw.max() >= len(loaded.vertices) else int(faces_raw.min())}"
                        f" but the file has {len(loaded.vertices)} vertices (corrupt or truncated); re-export the mesh")
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(f"{path}: has NaN or infinite vertex coordinates; re-export the mesh")
    far = float(np.abs(np.asarray(loaded.vertices, float)).max()) * UNIT_TO_M[unit]
    if far > MAX_COORDINATE_M:
        raise MeshError(f"{path}: a vertex lies {far:.3g} m from the part's origin when read as {unit} (at most "
                        f"{MAX_COORDINATE_M:g} m); check the units, or re-export the part near its origin")
    vertices, faces = merge_vertices(np.asarray(loaded.vertices, dtype=float) * UNIT_TO_M[unit], np.asarray(loaded.faces))
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if len(mesh.faces) == 0 or float(np.max(mesh.extents)) <= 0 or float(mesh.area) <= 1e-18:
        raise MeshError(f"{path}: all triangles are degenerate (zero area); export the part's surface")
    if np.linalg.matrix_rank(mesh.vertices - mesh.vertices.mean(axis=0), tol=1e-9 * float(np.max(mesh.extents))) < 3:
        raise MeshError(f"{path}: the mesh is flat (all vertices in one plane); a part needs a 3D surface")
    return mesh


MAX_COORDINATE_M = 1e4  # 10 km: a vertex further out is a unit or export mistake (and overflows the geometry)


class _ConfinedResolver(trimesh.resolvers.FilePathResolver):
    """The files a glTF or OBJ names (buffers, textures, .mtl), read as every input file is: inside the
    mesh's folder, regular files only (a FIFO there would otherwise hang the load), and all of them
    together within one mesh file's byte cap: a glTF that names one big buffer a hundred times is
    refused after the cap, not read a hundred times."""

    def __init__(self, source: str, budget: list | None = None):
        super().__init__(source)

        self.budget = budget if budget is not None else [safeio.LIMITS.mesh_bytes]  # shared with namespaced copies

    def get(self, name: str):
        too_much = AposeError(f"the files it refers to add up to more than the {safeio.LIMITS.mesh_bytes // 2**20} MB "
                              f"a mesh may have (at {name[:80]!r}); is a buffer named many times?")
        try:
            data = safeio.read_bytes(self.absolute(name), "a file the mesh refers to", max(self.budget[0], 0))
        except AposeError as e:
            if "over the" in str(e) and self.budget[0] < safeio.LIMITS.mesh_bytes:
                raise too_much from None
            raise
        self.budget[0] -= len(data)
        if self.budget[0] < 0:
            raise too_much
        return data

    def namespaced(self, namespace: str):
        return _ConfinedResolver(os.path.join(self.parent, namespace), self.budget)


def _check_declared_size(path: Path, ext: str, data: bytes) -> None:
    """Refuse a PLY or binary STL whose header declares more triangles than a part may have, before
    the parser allocates for them."""
    cap = safeio.LIMITS.mesh_triangles
    n = None
    if ext == ".stl" and len(data) >= 84 and not data[:5].lower() == b"solid":
        n = int.from_bytes(data[80:84], "little")
    elif ext == ".ply":
        head = data[:4096].split(b"end_header", 1)[0]
        for line in head.splitlines():
            words = line.split()
            if len(words) == 3 and words[0] == b"element" and words[1] in (b"face", b"vertex") and words[2].isdigit():
                n = max(n or 0, int(words[2]) // (1 if words[1] == b"face" else 3))
    if n is not None and n > cap:
        raise MeshError(f"{path}: its header declares {n} triangles, over the {cap} a part may have; decimate it")


_STEP_CACHE: dict = {}


def step_solids(path: str | Path) -> dict[str, trimesh.Trimesh]:
    """The named solids of a STEP file, each a triangle mesh in metres (OpenCASCADE through cascadio).
    Cached per file and modification time: several parts of one file read it once."""
    path = Path(path)
    key = (str(path.resolve()), path.stat().st_mtime_ns, path.stat().st_size)
    if key not in _STEP_CACHE:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                scene = trimesh.load(str(path), file_type="step")
        except Exception as e:
            raise MeshError(f"{path}: could not be read as STEP (corrupt, truncated, or not a solid model?): "
                            f"{type(e).__name__}: {e}") from None
        solids = {path.stem: scene} if isinstance(scene, trimesh.Trimesh) else {}
        if isinstance(scene, trimesh.Scene):  # a node per solid, named as in the STEP file
            for node in scene.graph.nodes_geometry:
                T, name = scene.graph[node]
                g = scene.geometry[name]
                if isinstance(g, trimesh.Trimesh) and len(g.faces):
                    solids[node] = g.copy().apply_transform(T)
        if not solids:
            raise MeshError(f"{path}: the STEP file holds no solid with faces; export the parts as solids")
        if len(_STEP_CACHE) > 16:
            _STEP_CACHE.clear()
        _STEP_CACHE[key] = solids
    return _STEP_CACHE[key]


def _step_solid(path: Path, solid: str | None) -> trimesh.Trimesh:
    solids = step_solids(path)
    if solid is None:
        return next(iter(solids.values())) if len(solids) == 1 else trimesh.util.concatenate(list(solids.values()))
    if solid not in solids:
        raise MeshError(f"{path}: has no solid named {solid!r}; its solids are {', '.join(solids)} "
                        "(set the part's `solid` to one of them)")
    return solids[solid]


def _not_a(path: Path, ext: str) -> str | None:
    """What a file really is when its first bytes contradict its extension ("a text file", "a PNG image")."""
    fd, _ = safeio.open_regular(path, "a mesh file")
    try:
        head = os.read(fd, 512)
    finally:
        os.close(fd)
    magic = {b"\x89PNG": "a PNG image", b"\xff\xd8\xff": "a JPEG image", b"%PDF": "a PDF document",
             b"PK\x03\x04": "a ZIP archive", b"\x7fELF": "a program"}
    for m, what in magic.items():
        if head.startswith(m):
            return what
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is None:
        return None if ext in (".stl", ".glb", ".ply") else "a binary file"
    start = text.lstrip().lower()
    expected = {".stl": ("solid",), ".ply": ("ply",), ".off": ("off", "coff", "noff", "#"), ".gltf": ("{",),
                ".step": ("iso-10303-21",), ".stp": ("iso-10303-21",)}
    if ext == ".stl" and not start.startswith("solid") and len(head) >= 84:  # a binary STL's header may be text
        n = int.from_bytes(head[80:84], "little")
        return None if path.stat().st_size == 84 + 50 * n else "a text file"
    if ext in expected and not start.startswith(expected[ext]):
        return "a text file"
    if ext == ".obj" and not any(line.split()[:1] in (["v"], ["f"], ["#"], ["o"], ["g"], ["mtllib"])
                                 for line in text.splitlines()):
        return "a text file"
    return None


EXACT_DIAMETER_POINTS = 20000


def _fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1.0 - i / n)  # a hemisphere is enough: -d gives the other extreme
    theta = np.pi * (1.0 + 5.0 ** 0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def extreme_points(points: np.ndarray, n_directions: int = 1024) -> np.ndarray:
    """Indices of the points extreme along n_directions (both ways): a small subset that spans the hull."""
    pts = np.asarray(points, dtype=np.float32)
    pts = pts - pts.mean(axis=0)
    dirs = _fibonacci_directions(n_directions).astype(np.float32)
    hi_v = np.full(n_directions, -np.inf, np.float32)
    lo_v = np.full(n_directions, np.inf, np.float32)
    hi_i = np.zeros(n_directions, np.int64)
    lo_i = np.zeros(n_directions, np.int64)
    rows = np.arange(n_directions)
    for s in range(0, len(pts), 8192):  # (directions x 8192) at a time, reduced along its contiguous axis
        proj = dirs @ pts[s:s + 8192].T
        a, b = proj.argmax(axis=1), proj.argmin(axis=1)
        va, vb = proj[rows, a], proj[rows, b]
        up, down = va > hi_v, vb < lo_v
        hi_v[up], hi_i[up] = va[up], a[up] + s
        lo_v[down], lo_i[down] = vb[down], b[down] + s
    return np.unique(np.concatenate([hi_i, lo_i]))


def _max_pairwise(pts: np.ndarray) -> tuple[float, int, int]:
    pts = pts - pts.mean(axis=0)
    sq = np.einsum("ij,ij->i", pts, pts)
    best, pair = -1.0, (0, 0)
    for i in range(0, len(pts), 2048):  # |a-b|^2 = |a|^2 + |b|^2 - 2ab, a block of rows at a time
        d2 = sq[i:i + 2048, None] + sq[None, :] - 2.0 * pts[i:i + 2048] @ pts.T
        k = int(d2.argmax())
        if d2.flat[k] > best:
            best, pair = float(d2.flat[k]), (i + k // len(pts), k % len(pts))
    return float(np.sqrt(max(best, 0.0))), pair[0], pair[1]


def diameter(points: np.ndarray) -> float:
    """Largest distance between two points (BOP's object diameter).

    Exact (over the convex hull's vertices) up to EXACT_DIAMETER_POINTS points. Above that (fine CAD
    exports of 100k+ vertices, where the exact pairwise search takes minutes) it is the exact diameter
    of the points extreme along 2x1024 directions, then improved by farthest-point steps over all
    points. It can only under-estimate: by at most D(1 - cos a), a ~ 2.7° being how far the diameter's
    direction can lie from the nearest sampled one, so about 0.1% (in tests it comes out exact).
    """
    pts = np.asarray(points, dtype=float)
    if len(pts) > EXACT_DIAMETER_POINTS:
        sub = extreme_points(pts, 1024)
        d, i, j = _max_pairwise(pts[sub])
        a, b = sub[i], sub[j]
        for _ in range(3):  # a farthest point from either end can only lengthen the pair
            fa = int(np.einsum("ij,ij->i", pts - pts[a], pts - pts[a]).argmax())
            fb = int(np.einsum("ij,ij->i", pts - pts[b], pts - pts[b]).argmax())
            da, db = np.linalg.norm(pts[fa] - pts[a]), np.linalg.norm(pts[fb] - pts[b])
            if max(da, db) <= d + 1e-15:
                break
            a, b, d = (a, fa, da) if da >= db else (fb, b, db)
        return float(d)
    try:
        pts = pts[ConvexHull(pts).vertices]
    except Exception:  # flat or tiny sets: fall back to all points
        pass
    return _max_pairwise(pts)[0]


def oriented_box(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """(T_part_obb, full extents) of a tight oriented box. Large meshes: the box is fitted to their
    extreme points (trimesh's minimum-volume search over the full hull takes seconds at 500k
    triangles), then grown to contain every vertex."""
    if len(mesh.vertices) <= EXACT_DIAMETER_POINTS:
        obb = mesh.bounding_box_oriented
        return np.array(obb.primitive.transform, dtype=float), np.array(obb.primitive.extents, dtype=float)
    sub = mesh.vertices[extreme_points(mesh.vertices, 512)]
    T, _ = trimesh.bounds.oriented_bounds(sub)  # T moves the points into the box frame
    local = trimesh.transform_points(mesh.vertices, T)
    lo, hi = local.min(axis=0), local.max(axis=0)
    T_part_obb = np.linalg.inv(T)
    T_part_obb[:3, 3] = trimesh.transform_points([(lo + hi) / 2], T_part_obb)[0]
    return T_part_obb, hi - lo


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int | np.random.Generator = 0, return_faces: bool = False):
    """n points on the surface, area-weighted, deterministic for a seed (or drawn from a generator the
    caller owns). (n, 3) in the mesh frame, and with return_faces the (n,) index of the triangle each
    point lies on."""
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    areas = mesh.area_faces
    face = rng.choice(len(areas), size=n, p=areas / areas.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    tri = mesh.triangles[face]
    pts = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return (pts, face) if return_faces else pts


def symmetry_transforms(symmetry: Symmetry | None, max_step: float = BOP_SYMMETRY_STEP) -> np.ndarray:
    """The discrete symmetry set (n, 4, 4) of T_part_part, identity first.

    order n: the n rotations by 2*pi*k/n. order 0 (continuous): discretised as BOP does, in
    ceil(pi / max_step) steps, so no surface point moves more than max_step * diameter per step.
    """
    if symmetry is None:
        return np.eye(4)[None]
    n = symmetry.order if symmetry.order >= 2 else int(np.ceil(np.pi / max_step))
    origin = np.asarray(symmetry.origin)
    out = []
    for k in range(n):
        R = se3.axis_angle_matrix(symmetry.axis, 2.0 * np.pi * k / n)
        out.append(se3.make_T(R, origin - R @ origin))
    return np.stack(out)


@dataclass(frozen=True, eq=False)
class PartModel:
    """A part's mesh (metres, part frame) and what the pipeline derives from it once."""

    id: str
    mesh: trimesh.Trimesh
    diameter: float
    aabb: np.ndarray  # (2, 3): min and max corner in the part frame
    T_part_obb: np.ndarray  # oriented box pose in the part frame
    obb_extents: np.ndarray  # (3,) full side lengths of the oriented box
    samples: np.ndarray  # (N, 3) surface points
    symmetries: np.ndarray  # (n, 4, 4) T_part_part, identity first
    color: tuple[float, float, float]
    unit_warning: str | None = None

    @property
    def size(self) -> np.ndarray:
        return self.aabb[1] - self.aabb[0]

    def box_corners(self) -> np.ndarray:
        """(8, 3) corners of the axis-aligned box in the part frame."""
        lo, hi = self.aabb
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


# Distinct, colour-blind-friendly defaults (Okabe-Ito) for parts that set no colour.
PALETTE = [(0.90, 0.62, 0.0), (0.34, 0.71, 0.91), (0.0, 0.62, 0.45), (0.94, 0.89, 0.26),
           (0.0, 0.45, 0.70), (0.84, 0.37, 0.0), (0.80, 0.47, 0.65), (0.6, 0.6, 0.6)]


def build_part_model(part_id: str, mesh: trimesh.Trimesh, symmetry: Symmetry | None = None,
                     color=None, index: int = 0, n_samples: int = 4000, unit_warning: str | None = None,
                     diameter_m: float | None = None) -> PartModel:
    T_part_obb, obb_extents = oriented_box(mesh)
    return PartModel(
        id=part_id, mesh=mesh, diameter=diameter(mesh.vertices) if diameter_m is None else diameter_m, aabb=np.array(mesh.bounds, dtype=float),
        T_part_obb=T_part_obb, obb_extents=obb_extents,
        samples=sample_surface(mesh, n_samples, seed=index), symmetries=symmetry_transforms(symmetry),
        color=tuple(color) if color is not None else PALETTE[index % len(PALETTE)], unit_warning=unit_warning)


_MESH_CACHE: dict = {}  # (file identity, unit, solid) -> (mesh, diameter): each file is read once
_MESH_CACHE_TRIANGLES = 20_000_000  # what the cache may hold; the oldest entries go first


def _file_key(path: Path, unit: str, solid: str | None):
    try:
        st = Path(path).stat()
    except (OSError, ValueError):
        return None
    return (str(Path(path).resolve()), st.st_ino, st.st_mtime_ns, st.st_size, unit, solid)


def cached_mesh(path: Path, unit: str, solid: str | None = None) -> tuple[trimesh.Trimesh, float]:
    """(mesh in metres, diameter) of a file, read once while the file is unchanged: forty parts that share
    a 16 MB STL hold one copy. The mesh is shared: never change it in place (copy first)."""
    key = _file_key(path, unit, solid)
    if key is not None and key in _MESH_CACHE:
        _MESH_CACHE[key] = _MESH_CACHE.pop(key)  # most recently used last
        return _MESH_CACHE[key]
    mesh = load_mesh(path, unit, solid)
    entry = (mesh, diameter(mesh.vertices))
    if key is not None:
        _MESH_CACHE[key] = entry
        while len(_MESH_CACHE) > 1 and sum(len(m.faces) for m, _ in _MESH_CACHE.values()) > _MESH_CACHE_TRIANGLES:
            _MESH_CACHE.pop(next(iter(_MESH_CACHE)))
    return entry


def load_part(part: Part, unit: str, index: int = 0) -> PartModel:
    """Load one part of an assembly: mesh in metres plus derived geometry and a unit sanity check."""
    mesh, d = cached_mesh(part.mesh, unit, part.solid)
    is_step = part.mesh.suffix.lower() in STEP_EXTENSIONS  # carries its own unit: nothing to guess
    guess = None if is_step else suspicious_unit(d / UNIT_TO_M[unit], unit)
    warning = None
    if guess is not None:
        warning = (f"part {part.id!r} ({part.mesh.name}) is {d:.4g} m across when read as {unit}; "
                   f"it looks like it is in {guess} — set `units: {guess}` or rescale the mesh")
        log.warning(warning)
    return build_part_model(part.id, mesh, part.symmetry, part.color, index, unit_warning=warning, diameter_m=d)


def load_parts(asm: Assembly) -> dict[str, PartModel]:
    """Every part of an assembly, in file order. Raises MeshError naming the part on the first bad mesh."""
    out, triangles, seen = {}, 0, set()
    for i, (pid, part) in enumerate(asm.parts.items()):
        try:
            out[pid] = load_part(part, asm.units, i)
        except MeshError as e:
            raise MeshError(f"part {pid!r}: {e}") from None
        if id(out[pid].mesh) not in seen:  # a mesh shared by several parts counts once
            seen.add(id(out[pid].mesh))
            triangles += len(out[pid].mesh.faces)
        if triangles > safeio.LIMITS.assembly_triangles:
            raise MeshError(f"part {pid!r}: the assembly's meshes hold {triangles} triangles by this part, over the "
                            f"{safeio.LIMITS.assembly_triangles} an assembly may have; decimate the largest parts")
    return out


def merged_mesh(models: dict[str, PartModel], poses: dict[str, np.ndarray]) -> trimesh.Trimesh:
    """One mesh of several parts, each moved by its pose (e.g. T_base_member)."""
    meshes = []
    for pid, T in poses.items():
        m = models[pid].mesh.copy()
        m.apply_transform(T)
        meshes.append(m)
    return trimesh.util.concatenate(meshes)


def base_mesh(models: dict[str, PartModel], view: StepView) -> trimesh.Trimesh:
    """The base object of a step as one mesh in the frame of base[0]."""
    return merged_mesh(models, view.T_base_members)
