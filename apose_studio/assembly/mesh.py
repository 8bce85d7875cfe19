"""CAD loading and per-part geometry: diameter, bounding boxes, surface samples, symmetry sets.

Meshes are read with trimesh and scaled to metres here; nothing past this module sees file units.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import struct
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from apose_studio import safeio
from apose_studio.assembly.model import Assembly, Part, StepView, Symmetry
from apose_studio.assembly.roi import Roi, region_mesh
from apose_studio.errors import AposeError, MeshError
from apose_studio.geometry import se3
from apose_studio.geometry.units import MAX_COORDINATE_M, UNIT_TO_M, suspicious_unit

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
    t = np.subtract(vertices, lo, dtype=float)  # in place from here: two arrays of the vertices' size at most
    t *= (2 ** bits - 1) / span
    np.rint(t, out=t)
    q = t.astype(np.int64)
    t = None
    key = (q[:, 0] << (2 * bits)) | (q[:, 1] << bits) | q[:, 2]
    q = None
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
    one named solid of a STEP file (None: all of them as one part).

    What a file declares (triangles, vertices, a glTF's placed copies) is checked before it is parsed.
    The parse then runs in a child process under `safeio.run_bounded`'s limits (CPU time, memory, wall
    clock): no header bounds what OpenCASCADE's tessellation, an OBJ's text or a glTF's buffers cost,
    so the work itself is bounded; what comes back is the checked, welded mesh. A binary STL or a plain
    binary PLY costs what its checked counts say, and is read here (`_fixed_cost`)."""
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
    head = _head(path, 2 ** 20)
    _check_declared_size(path, ext, head, st.st_size)  # before a byte more is read
    if solid is not None and ext not in STEP_EXTENSIONS:
        raise MeshError(f"{path}: `solid: {solid}` names a solid of a STEP file, but this is a {ext[1:].upper()} mesh; "
                        "remove `solid`")
    key = _file_key(path, unit, solid)
    if key is not None and key in _FAILED:  # a file that ran into a limit is not parsed again until it changes
        raise MeshError(_FAILED[key])
    try:
        if ext in STEP_EXTENSIONS:
            vertices, faces = _finish(path, *_step_solid(path, solid), "m")  # counted in the child: bounded here
        elif _fixed_cost(path, ext, head, st.st_size):
            _budget_left(path)
            vertices, faces = _parse_mesh_file(path, ext, unit, fixed=True)  # its cost is its checked counts
        else:
            vertices, faces = _bounded(_parse_mesh_file, path, ext, unit, where=path,
                                       doing=f"reading this {ext[1:].upper()} file", fix=_fix_for(ext))
    except safeio.LimitExceeded as e:
        _remember_failure(key, e)
        raise MeshError(str(e)) from None
    return trimesh.Trimesh(vertices, faces, process=False)


_FAILED: dict = {}  # file identity -> the limit it ran into
_FIX_DECIMATE = "decimate the part (a few hundred thousand triangles are plenty for registration)"


def _fix_for(ext: str) -> str:
    if ext in STEP_EXTENSIONS:
        return ("export the part from CAD as a mesh (binary STL, PLY or GLB) at a coarser tolerance, or split the "
                "STEP file into its parts")
    if ext in (".obj", ".off", ".stl"):
        return (f"{_FIX_DECIMATE} if it is large; else export it again as one plain mesh: binary STL, PLY or GLB "
                "read several times faster than text")
    return f"{_FIX_DECIMATE} if it is large; else export it again as one plain mesh (one node, no materials)"


_BUDGET = threading.local()  # .deadline: when the meshes of the assembly being loaded (load_parts) must be read


def _bounded(fn, *args, where, doing: str, fix: str, **limits):
    """fn(*args) in a limited child process (safeio.run_bounded); what it returns is pickled back, at
    most the arrays of a mesh of LIMITS.mesh_triangles triangles. Inside load_parts, the limits are cut
    to the assembly's time left."""
    out = 64 * safeio.LIMITS.mesh_triangles + 2 ** 26
    left = _budget_left(where)
    if left is not None and left < safeio.LIMITS.parse_wall_seconds:
        limits["wall_s"] = left
        limits["cpu_s"] = min(safeio.LIMITS.parse_cpu_seconds, left)
    try:
        return safeio.run_bounded(fn, *args, where=str(where), doing=doing, fix=fix, output_bytes=out, **limits)
    except safeio.LimitExceeded as e:
        e.lasting = e.kind != "wall" and "wall_s" not in limits  # the file's own doing, not a busy machine's
        raise


def _budget_left(where) -> float | None:
    """Seconds left to the assembly being loaded (None outside load_parts); a MeshError when none are."""
    deadline = getattr(_BUDGET, "deadline", None)
    if deadline is None:
        return None
    left = deadline - time.monotonic()
    if left <= 0:
        raise MeshError(f"{where}: not read: the assembly's mesh files took more than "
                        f"{safeio.LIMITS.assembly_parse_seconds:g} s in all (the most they may take); {_FIX_DECIMATE}, "
                        "or export the slow ones as binary STL/PLY/GLB")
    return left


def _remember_failure(key, e: safeio.LimitExceeded) -> None:
    """A file that ran into its own CPU, memory or output limit is not parsed again until it changes (the
    studio opens an assembly again and again)."""
    if key is not None and getattr(e, "lasting", False):
        if len(_FAILED) > 256:
            _FAILED.clear()
        _FAILED[key] = str(e)


def _parse_mesh_file(path: Path, ext: str, unit: str, fixed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """In the child: the bytes read through safeio, what the file declares counted before it is parsed,
    trimesh's parse (geometry only: no materials, textures or .mtl files), then `_finish`. `fixed`: in
    this process, for a file `_fixed_cost` accepted; the bytes read must still be such a file."""
    cap = safeio.LIMITS.mesh_bytes
    try:
        data = safeio.read_bytes(path, "a mesh file", cap)  # the bytes read are what is parsed
    except AposeError as e:
        raise MeshError(str(e)) from None
    _check_declared_size(path, ext, data)
    if fixed and not _fixed_cost(path, ext, data[:2 ** 20], len(data)):
        raise MeshError(f"{path}: changed while it was being read; save it again, then open it")
    if ext == ".stl" and _binary_stl_count(data) is not None:  # the common big format: read here, without copies
        vertices, faces = _read_binary_stl(path, data)
        data = None
        return _finish(path, vertices, faces, unit)
    kwargs = {}
    if ext in (".gltf", ".glb"):
        data = _gltf_geometry_only(path, ext, data)
    elif ext == ".obj":
        kwargs["skip_materials"] = True  # colours come from the assembly; a .mtl or texture is never read
        # nor are material switches: one `usemtl` per face (some CAD exporters write it) split the parse
        # into 150 000 groups and spent 30 s of CPU on a 10 MB file
        data = _OBJ_MATERIAL_LINE.sub(b"", data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(io.BytesIO(data), file_type=ext[1:], force="mesh", process=False,
                                  resolver=_ConfinedResolver(str(path), [cap - len(data)]), **kwargs)
    except MemoryError:
        raise
    except AposeError as e:  # from the resolver: a buffer that may not be read
        raise MeshError(f"{path}: {e}") from None
    except (Exception, RecursionError) as e:  # trimesh raises many types on corrupt input
        raise MeshError(f"{path}: could not be read as a {ext[1:].upper()} mesh (corrupt or truncated?): "
                        f"{type(e).__name__}: {str(e)[:200]}") from None
    finally:
        data = None
    if not isinstance(loaded, trimesh.Trimesh):
        kind = type(loaded).__name__
        raise MeshError(f"{path}: holds a {kind} with no triangles, not a surface mesh; export the part's surface")
    return _finish(path, loaded.vertices, loaded.faces, unit)


def _finish(path: Path, vertices, faces, unit: str) -> tuple[np.ndarray, np.ndarray]:
    """The checks every mesh passes, then its vertices welded: (vertices in metres, faces as int32)."""
    cap = safeio.LIMITS.mesh_triangles
    faces_raw = np.asarray(faces)
    vertices = np.asarray(vertices, dtype=float)
    if len(faces_raw) == 0:
        raise MeshError(f"{path}: has no triangles (a point cloud or empty mesh); export the part's surface")
    if len(faces_raw) > cap:
        raise MeshError(f"{path}: {len(faces_raw)} triangles, over the {cap} a part may have; {_FIX_DECIMATE}")
    if faces_raw.min() < 0 or faces_raw.max() >= len(vertices):
        raise MeshError(f"{path}: a triangle names vertex {int(faces_raw.max()) if faces_raw.max() >= len(vertices) else int(faces_raw.min())}"
                        f" but the file has {len(vertices)} vertices (corrupt or truncated); re-export the mesh")
    if not np.all(np.isfinite(vertices)):
        raise MeshError(f"{path}: has NaN or infinite vertex coordinates; re-export the mesh")
    far = float(np.abs(vertices).max()) * UNIT_TO_M[unit]
    if far > MAX_COORDINATE_M:
        raise MeshError(f"{path}: a vertex lies {far:.3g} m from the part's origin when read as {unit} (at most "
                        f"{MAX_COORDINATE_M:g} m); check the units, or re-export the part near its origin")
    v, f = merge_vertices(vertices * UNIT_TO_M[unit], faces_raw)
    vertices = faces_raw = None
    mesh = trimesh.Trimesh(v, f, process=False)
    if len(mesh.faces) == 0 or float(np.max(mesh.extents)) <= 0 or float(mesh.area) <= 1e-18:
        raise MeshError(f"{path}: all triangles are degenerate (zero area); export the part's surface")
    if np.linalg.matrix_rank(mesh.vertices - mesh.vertices.mean(axis=0), tol=1e-9 * float(np.max(mesh.extents))) < 3:
        raise MeshError(f"{path}: the mesh is flat (all vertices in one plane); a part needs a 3D surface")
    return np.ascontiguousarray(v, dtype=float), np.ascontiguousarray(f, dtype=np.int32)


class _ConfinedResolver(trimesh.resolvers.FilePathResolver):
    """The files a glTF names (its buffers), read as every input file is: inside the mesh's folder,
    regular files only (a FIFO there would otherwise hang the load), and all of them together within
    one mesh file's byte cap: a glTF that names one big buffer a hundred times is refused after the
    cap, not read a hundred times. A refusal says, in our words, what was refused and why."""

    def __init__(self, source: str, budget: list | None = None):
        super().__init__(source)

        self.budget = budget if budget is not None else [safeio.LIMITS.mesh_bytes]  # shared with namespaced copies

    def keys(self):  # never walk the folder (trimesh may, to guess a texture's name)
        return iter(())

    def get(self, name: str):
        too_much = AposeError(f"the files it refers to add up to more than the {safeio.LIMITS.mesh_bytes // 2**20} MB "
                              f"a mesh may have (at {name[:80]!r}); is a buffer named many times?")
        folder = Path(self.parent).resolve()
        target = (folder / name.strip()).resolve()  # links followed: a link inside pointing out is outside
        if not target.is_relative_to(folder):
            raise AposeError(f"it names the file {name[:120]!r}, which lies outside the mesh's folder {folder}; a "
                             "glTF's buffers are read only from its own folder: copy them beside it (or export a GLB)")
        try:
            data = safeio.read_bytes(target, "a file the mesh refers to", max(self.budget[0], 0))
        except AposeError as e:
            if "over the" in str(e) and self.budget[0] < safeio.LIMITS.mesh_bytes:
                raise too_much from None
            raise AposeError(f"it names the file {name[:120]!r}, which cannot be used: {e}") from None
        self.budget[0] -= len(data)
        if self.budget[0] < 0:
            raise too_much
        return data

    def namespaced(self, namespace: str):
        return _ConfinedResolver(os.path.join(self.parent, namespace), self.budget)


def _binary_stl_count(data: bytes, size: int | None = None) -> int | None:
    """A binary STL's triangle count, or None for an ASCII STL (a binary header may start with `solid`
    too: then the file's size tells). `data`: the file, or its first bytes and `size` the file's."""
    size = len(data) if size is None else size
    if len(data) < 84:
        return None
    n = int.from_bytes(data[80:84], "little")
    return n if data[:5].lower() != b"solid" or size == 84 + 50 * n else None


def _fixed_cost(path: Path, ext: str, head: bytes, size: int) -> bool:
    """Whether reading the file costs what its (already checked) counts say, so that it may be read in
    this process (a child costs ~20 ms to fork and exit; the samples are STL and PLY): a binary STL whose
    size is its header's count (one numpy view, welded in time and memory linear in it), a binary PLY of
    vertices and triangles whose size says every face is one. Anything else is read in a child."""
    if ext == ".stl":
        n = _binary_stl_count(head, size)
        return n is not None and 84 + 50 * n <= size <= 84 + 50 * n + 4096
    return ext == ".ply" and _ply_triangles(path, head, size)[2]


_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])


def _read_binary_stl(path: Path, data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a binary STL: three corners per triangle, welded later (`merge_vertices`)."""
    n = _binary_stl_count(data)
    if len(data) < 84 + 50 * n:
        raise MeshError(f"{path}: its header declares {n} triangles but it holds {(len(data) - 84) // 50} "
                        "(truncated?); re-export the mesh")
    records = np.frombuffer(data, _STL_RECORD, count=n, offset=84)
    return records["corners"].reshape(-1, 3), np.arange(3 * n, dtype=np.int32).reshape(-1, 3)


# --------------------------------------------------------------- what a file declares, before parsing


def _check_declared_size(path: Path, ext: str, data: bytes, size: int | None = None) -> None:
    """Refuse a mesh whose file declares (or plainly holds) more triangles than a part may have, before
    the parser allocates for them: a binary STL's count (also behind a header that starts with `solid`),
    an ASCII STL's facets, a PLY's or OFF's element counts and a binary PLY's polygon corners, an OBJ's
    face corners (a polygon of n corners is n - 2 triangles). glTF: `_gltf_geometry_only`.
    `data`: the whole file, or its first bytes and `size` the file's (what headers declare is checked
    before the file is read; what only the whole text tells, when it is read)."""
    cap = safeio.LIMITS.mesh_triangles
    size = len(data) if size is None else size
    whole = len(data) == size
    n, vertices, how = None, 0, "its header declares"
    if ext == ".stl":
        n = _binary_stl_count(data, size)
        if n is not None and n > cap and size < 84 + 50 * n:  # random bytes, or cut short: not a big part
            raise MeshError(f"{path}: its header declares {n} triangles but the file is {size} bytes, not the "
                            f"{84 + 50 * n} that many take; the file is corrupt or truncated: export it again")
        if n is None and whole:
            n, how = data.count(b"endloop"), "it holds"
    elif ext == ".ply":
        n, vertices, _ = _ply_triangles(path, data, size)
    elif ext == ".off":
        words = b" ".join(line.split(b"#")[0] for line in data[:4096].splitlines()[:8]).split()
        counts = [int(w) for w in words[1:3] if w.isdigit()] if words[:1] and words[0].upper().endswith(b"OFF") else []
        if len(counts) == 2:
            vertices, n = counts
    elif ext == ".obj" and whole:
        vertices = data.count(b"\nv ") + data.count(b"\nv\t") + (data[:2] in (b"v ", b"v\t"))
        if vertices > 3 * cap:
            raise MeshError(f"{path}: its vertex lines hold {vertices} vertices, over the {3 * cap} a part's mesh may "
                            f"have; {_FIX_DECIMATE}")
        for tag, what in ((b"vt", "texture coordinates"), (b"vn", "normals"), (b"vp", "parameter-space vertices")):
            extra = sum(data.count(b"\n" + tag + sep) + (data[:3] == tag + sep) for sep in (b" ", b"\t"))
            if extra > 3 * cap:  # parsed and stored though never used: 30 M `vt` lines took 2 GB for 4 triangles
                raise MeshError(f"{path}: it holds {extra} {what} ({tag.decode()} lines), over the {3 * cap} a part's "
                                "mesh may have; export it again with geometry only (no texture coordinates or normals)")
        n, how = _obj_triangles(data), "its face lines hold"
    if vertices > 3 * cap:
        raise MeshError(f"{path}: its header declares {vertices} vertices, over the {3 * cap} a part's mesh may have; "
                        f"{_FIX_DECIMATE}")
    if n is not None and n > cap:
        raise MeshError(f"{path}: {how} {n} triangles, over the {cap} a part may have; {_FIX_DECIMATE}")


_PLY_SIZES = {b"char": 1, b"uchar": 1, b"int8": 1, b"uint8": 1, b"short": 2, b"ushort": 2, b"int16": 2,
              b"uint16": 2, b"int": 4, b"uint": 4, b"int32": 4, b"uint32": 4, b"float": 4, b"float32": 4,
              b"double": 8, b"float64": 8}


def _ply_triangles(path: Path, data: bytes, size: int) -> tuple[int | None, int, bool]:
    """(triangles, vertices, plain) as a PLY's header and size say: its face count, and for a binary PLY
    of vertices then faces (one list each) the corners its bytes hold, fan-triangulated (n - 2 each);
    `plain`: such a PLY whose every face is a triangle (its size says so), parsed in time linear in its counts."""
    end = data.find(b"end_header", 0, 2 ** 20)
    if end < 0:
        if len(data) >= 2 ** 20:
            raise MeshError(f"{path}: no end_header in its first MB; a PLY header is a few hundred bytes: the file is "
                            "damaged or crafted, re-export it")
        return None, 0, False
    lines = data[:end].splitlines()
    elements: list[list] = []  # [name, count, [property sizes or ("list", count size, item size)]]
    binary = any(line.startswith(b"format binary") for line in lines)
    for line in lines:
        w = line.split()
        if len(w) == 3 and w[0] == b"element":
            elements.append([w[1], int(w[2]) if w[2].isdigit() else -1, []])
        elif len(w) >= 3 and w[0] == b"property" and elements:
            if w[1] == b"list" and len(w) >= 5:
                elements[-1][2].append(("list", _PLY_SIZES.get(w[2], 0), _PLY_SIZES.get(w[3], 0)))
            else:
                elements[-1][2].append(_PLY_SIZES.get(w[1], 0))
    counts = {e[0]: e[1] for e in elements}
    n, plain = counts.get(b"face", 0), False
    if binary and [e[0] for e in elements] == [b"vertex", b"face"] and all(isinstance(p, int) and p for p in elements[0][2]):
        (_, nv, vprops), (_, nf, fprops) = elements
        if len(fprops) == 1 and isinstance(fprops[0], tuple) and fprops[0][1] and fprops[0][2] and nf >= 0 and nv >= 0:
            body = size - (data.find(b"\n", end) + 1) - nv * sum(vprops)
            corners = (body - nf * fprops[0][1]) // fprops[0][2]
            n = max(n, corners - 2 * nf)
            plain = corners == 3 * nf and body == nf * (fprops[0][1] + 3 * fprops[0][2]) and len(vprops) <= 12
    return n, counts.get(b"vertex", 0), plain


_OBJ_MATERIAL_LINE = re.compile(rb"(?m)^[ \t]*(?:usemtl|mtllib)\b[^\n]*")
GLTF_MAX_NODES = 10_000  # nodes in a part's glTF scene (a CAD assembly exported whole has hundreds)
GLTF_MAX_DEPTH = 64  # nesting of its node tree


def _obj_triangles(data: bytes, chunk: int = 2 ** 24) -> int:
    """The triangles an OBJ's `f` lines make (corners - 2 per line), counted with numpy a chunk of whole
    lines at a time (16 MB of text: about 100 MB of arrays)."""
    arr = np.frombuffer(data, np.uint8)
    total, start = 0, 0
    while start < len(arr):
        stop = min(start + chunk, len(arr))
        if stop < len(arr):
            nl = data.find(b"\n", stop)
            stop = len(arr) if nl < 0 else nl + 1
        a = arr[start:stop]
        start = stop
        space = (a == 32) | (a == 9) | (a == 13) | (a == 10) | (a == 11) | (a == 12)
        token = ~space
        token[1:] &= space[:-1]  # a token starts where a non-space follows a space
        line_end = np.flatnonzero(a == 10)
        if len(line_end) == 0 or line_end[-1] != len(a) - 1:
            line_end = np.append(line_end, len(a) - 1)
        line_start = np.concatenate([[0], line_end[:-1] + 1])
        nxt = np.minimum(line_start + 1, len(a) - 1)
        is_face = (a[line_start] == ord("f")) & space[nxt]
        if not is_face.any():
            continue
        c = np.cumsum(token, dtype=np.int32)
        tokens = c[line_end] - np.where(line_start > 0, c[line_start - 1], 0)
        total += int(np.maximum(tokens[is_face] - 3, 0).sum())  # "f" and n corners: n - 2 triangles
    return total


def _gltf_document(path: Path, ext: str, data: bytes) -> tuple[dict, bytes | None]:
    """(the glTF JSON, a GLB's binary chunk or None)."""
    if ext == ".glb":
        try:
            magic, _version, _length, json_len, json_type = struct.unpack("<4sIIII", data[:20])
        except struct.error:
            raise MeshError(f"{path}: too short for a GLB file (corrupt or truncated?); re-export it") from None
        if magic != b"glTF" or json_type != 0x4E4F534A or 20 + json_len > len(data):
            raise MeshError(f"{path}: not a GLB file (no glTF header and JSON chunk); re-export it")
        text, rest = data[20:20 + json_len], data[20 + json_len:]
        binary = None
        if len(rest) >= 8:
            bin_len, bin_type = struct.unpack("<II", rest[:8])
            if bin_type == 0x004E4942:
                binary = rest[8:8 + bin_len]
    else:
        text, binary = data, None
    try:
        doc = safeio.parse_json(text.decode("utf-8-sig"), str(path))
    except UnicodeDecodeError:
        raise MeshError(f"{path}: its glTF JSON is not UTF-8 text; re-export it") from None
    except AposeError as e:
        raise MeshError(str(e)) from None
    if not isinstance(doc, dict):
        raise MeshError(f"{path}: its glTF JSON is a {type(doc).__name__}, not an object; re-export it")
    return doc, binary


def _gltf_geometry_only(path: Path, ext: str, data: bytes) -> bytes:
    """The glTF (or GLB) checked against the triangle cap as its JSON declares it, every node that shows a
    mesh counted (a 1 MB file can place one mesh 3000 times: 61 M triangles once copied into one mesh),
    and re-written without materials, textures and images: only geometry is read."""
    doc, binary = _gltf_document(path, ext, data)
    try:
        _gltf_count(path, doc)
    except (TypeError, KeyError, IndexError, AttributeError, ValueError) as e:
        raise MeshError(f"{path}: its glTF JSON is malformed ({type(e).__name__}: {str(e)[:80]}); re-export it") from None
    prims = [p for m in doc.get("meshes") or [] for p in (m.get("primitives") or []) if isinstance(p, dict)]
    if not any(key in doc for key in ("materials", "textures", "images", "samplers")) and not any(
            "material" in p for p in prims):
        return data  # geometry only already: parsed as read
    for key in ("materials", "textures", "images", "samplers"):
        doc.pop(key, None)
    for prim in prims:
        prim.pop("material", None)
    text = json.dumps(doc).encode()
    if ext != ".glb":
        return text
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if binary is not None:
        binary += b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def _gltf_count(path: Path, doc: dict) -> None:
    cap = safeio.LIMITS.mesh_triangles
    accessors = doc.get("accessors") or []
    for i, acc in enumerate(accessors):
        count = acc.get("count", 0)
        if not isinstance(count, int) or count < 0 or count > 3 * cap:
            raise MeshError(f"{path}: its glTF accessor {i} declares {count} elements, over the {3 * cap} a part's mesh "
                            f"may have; {_FIX_DECIMATE}")

    def triangles(prim: dict) -> int:
        if "indices" in prim:
            n = accessors[prim["indices"]].get("count", 0)
        else:
            n = accessors[prim["attributes"]["POSITION"]].get("count", 0)
        mode = prim.get("mode", 4)
        return n // 3 if mode == 4 else max(n - 2, 0) if mode in (5, 6) else 0

    per_mesh = [sum(triangles(p) for p in m.get("primitives") or []) for m in doc.get("meshes") or []]
    nodes = doc.get("nodes") or []
    if len(nodes) > GLTF_MAX_NODES:
        raise MeshError(f"{path}: its glTF scene has {len(nodes)} nodes, over the {GLTF_MAX_NODES} a part's file may "
                        "have (walking them costs more than its triangles); export the part as one mesh")
    roots = [r for sc in doc.get("scenes") or [] for r in (sc.get("nodes") or [])]
    seen, stack, shown, copies = set(), [(r, 1) for r in roots], 0, 0
    while stack:  # every node reachable from a scene, once (trimesh keys its graph by node)
        k, depth = stack.pop()
        if not isinstance(k, int) or k in seen:
            continue
        if depth > GLTF_MAX_DEPTH:
            raise MeshError(f"{path}: its glTF node tree is nested over {GLTF_MAX_DEPTH} deep; export the part as "
                            "one mesh")
        seen.add(k)
        node = nodes[k]
        if "mesh" in node:
            shown += per_mesh[node["mesh"]]
            copies += 1
        stack.extend((c, depth + 1) for c in node.get("children") or [])
    if not roots:
        shown = sum(per_mesh)
    stored = sum(per_mesh)
    if max(shown, stored) > cap:
        what = (f"places its meshes {copies} times, {shown} triangles in all" if shown > stored else
                f"declares {stored} triangles")
        raise MeshError(f"{path}: its glTF scene {what}, over the {cap} a part may have (each placed copy becomes "
                        f"triangles of its own); {_FIX_DECIMATE}, or export the part as one mesh")


# --------------------------------------------------------------------------------------- STEP


STEP_TOLERANCE_MM = 0.01  # OpenCASCADE's linear deflection (cascadio's default) for parts up to 10 cm
STEP_TOLERANCE_FRACTION = 1e-4  # of the part's size above that: the tessellation's cost no longer grows with it
_STEP_CACHE: dict = {}


def step_solids(path: str | Path) -> dict[str, trimesh.Trimesh]:
    """The named solids of a STEP file, each a triangle mesh in metres (OpenCASCADE through cascadio),
    tessellated in a limited child process (`safeio.run_bounded`). Cached per file and modification
    time: several parts of one file read it once."""
    path = Path(path)
    try:
        fd, _ = safeio.open_regular(path, "a STEP file")
        os.close(fd)
    except AposeError as e:
        raise MeshError(str(e)) from None
    key = _file_key(path, "m", None)
    if key is not None and key in _FAILED:
        raise MeshError(_FAILED[key])
    if key is None or key not in _STEP_CACHE:
        with tempfile.TemporaryDirectory(prefix="apose-step-") as folder:  # removed even when the child is killed
            try:
                raw = _bounded(_read_step, path, folder, where=path, doing="tessellating this STEP file "
                               "(OpenCASCADE)", fix=_fix_for(".step"), file_bytes=safeio.LIMITS.mesh_bytes)
            except safeio.LimitExceeded as e:
                _remember_failure(key, e)
                raise MeshError(str(e)) from None
        solids = {name: trimesh.Trimesh(v, f, process=False) for name, (v, f) in raw.items()}
        if len(_STEP_CACHE) > 16:
            _STEP_CACHE.clear()
        if key is None:
            return solids
        _STEP_CACHE[key] = solids
    return _STEP_CACHE[key]


def _read_step(path: Path, folder: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """In the child: the STEP file read through safeio, tessellated twice: coarsely (relative to each
    edge, fast whatever the size) to measure the part, then at STEP_TOLERANCE_MM or, for a part over
    10 cm, STEP_TOLERANCE_FRACTION of its size (a 2 km disc at 0.01 mm took OpenCASCADE 8 minutes)."""
    import cascadio

    try:
        data = safeio.read_bytes(path, "a STEP file", safeio.LIMITS.mesh_bytes)
    except AposeError as e:
        raise MeshError(str(e)) from None
    src, glb = os.path.join(folder, "part.step"), os.path.join(folder, "part.glb")
    with open(src, "wb") as f:
        f.write(data)
    data = None

    def tessellate(**tolerance) -> trimesh.Scene:
        if os.path.exists(glb):
            os.unlink(glb)
        try:
            cascadio.step_to_glb(src, glb, tol_angular=0.5, **tolerance)
            with safeio.reads_within([folder]):  # our own temporary file, wherever the workspace is
                blob = safeio.read_bytes(glb, "the tessellated STEP file", safeio.LIMITS.mesh_bytes)
            blob = _gltf_geometry_only(path, ".glb", blob)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return trimesh.load(io.BytesIO(blob), file_type="glb")
        except MemoryError:
            raise
        except MeshError as e:
            raise MeshError(f"{e}".replace("its glTF scene", "its tessellation")) from None
        except (Exception, RecursionError) as e:
            raise MeshError(f"{path}: could not be read as STEP (corrupt, truncated, or not a solid model?): "
                            f"{type(e).__name__}: {str(e)[:200]}") from None

    coarse = tessellate(tol_linear=0.1, tol_relative=True)
    bounds = getattr(coarse, "bounds", None)
    size_mm = float(np.max(bounds[1] - bounds[0])) * 1000.0 if bounds is not None else 0.0
    scene = tessellate(tol_linear=max(STEP_TOLERANCE_MM, STEP_TOLERANCE_FRACTION * size_mm))
    solids = {path.stem: scene} if isinstance(scene, trimesh.Trimesh) else {}
    if isinstance(scene, trimesh.Scene):  # a node per solid, named as in the STEP file
        for node in scene.graph.nodes_geometry:
            T, name = scene.graph[node]
            g = scene.geometry[name]
            if isinstance(g, trimesh.Trimesh) and len(g.faces):
                solids[node] = g.copy().apply_transform(T)
    if not solids:
        raise MeshError(f"{path}: the STEP file holds no solid with faces; export the parts as solids")
    return {name: (np.asarray(m.vertices, dtype=float), np.asarray(m.faces, dtype=np.int32)) for name, m in solids.items()}


def _step_solid(path: Path, solid: str | None) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of one named solid of a STEP file, or of all of them together."""
    solids = step_solids(path)
    if solid is None:
        meshes = list(solids.values())
        if len(meshes) == 1:
            return meshes[0].vertices, meshes[0].faces
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return (np.concatenate([m.vertices for m in meshes]),
                np.concatenate([np.asarray(m.faces) + o for m, o in zip(meshes, offsets)]))
    if solid not in solids:
        raise MeshError(f"{path}: has no solid named {solid!r}; its solids are {', '.join(solids)} "
                        "(set the part's `solid` to one of them)")
    return solids[solid].vertices, solids[solid].faces


def _head(path: Path, n: int) -> bytes:
    """The first n bytes of a (regular) file."""
    try:
        fd, _ = safeio.open_regular(path, "a mesh file")
    except AposeError as e:
        raise MeshError(str(e)) from None
    try:
        return os.read(fd, n)
    except OSError as e:
        raise MeshError(f"{path}: cannot be read ({e.strerror}); choose a mesh file on a working disk") from None
    finally:
        os.close(fd)


def _not_a(path: Path, ext: str) -> str | None:
    """What a file really is when its first bytes contradict its extension ("a text file", "a PNG image")."""
    head = _head(path, 512)
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
    rows = max(1, 2 ** 22 // len(pts))  # blocks of 4 M distances (32 MB each; 2048 rows of 20 000 took 1 GB)
    for i in range(0, len(pts), rows):  # |a-b|^2 = |a|^2 + |b|^2 - 2ab, a block of rows at a time
        d2 = sq[i:i + rows, None] + sq[None, :] - 2.0 * pts[i:i + rows] @ pts.T
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
    return np.stack([se3.turn_about(symmetry.axis, 2.0 * np.pi * k / n, origin) for k in range(n)])


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
    roi: Roi | None = None  # as a base, only this region is registered (`region`)
    region: trimesh.Trimesh | None = None  # the faces in `roi` (part frame), cut once at load

    @property
    def registered_mesh(self) -> trimesh.Trimesh:
        """What registration matches when this part is a base: its region where it has an roi, else its mesh."""
        return self.region if self.region is not None else self.mesh

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
                     diameter_m: float | None = None, roi: Roi | None = None) -> PartModel:
    region = region_mesh(mesh, roi, f"part {part_id!r}") if roi is not None else None
    T_part_obb, obb_extents = oriented_box(mesh)
    return PartModel(
        id=part_id, mesh=mesh, diameter=diameter(mesh.vertices) if diameter_m is None else diameter_m, aabb=np.array(mesh.bounds, dtype=float),
        T_part_obb=T_part_obb, obb_extents=obb_extents,
        samples=sample_surface(mesh, n_samples, seed=index), symmetries=symmetry_transforms(symmetry),
        color=tuple(color) if color is not None else PALETTE[index % len(PALETTE)], unit_warning=unit_warning,
        roi=roi, region=region)


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
    try:
        return build_part_model(part.id, mesh, part.symmetry, part.color, index, unit_warning=warning, diameter_m=d,
                                roi=part.roi)
    except MeshError as e:  # the roi holds none of the surface: said as the part's, with the file
        raise MeshError(f"{part.mesh.name}: {str(e).removeprefix(f'part {part.id!r}: ')}") from None


def load_parts(asm: Assembly) -> dict[str, PartModel]:
    """Every part of an assembly, in file order. Raises MeshError naming the part on the first bad mesh.
    Reading all of its mesh files may take LIMITS.assembly_parse_seconds in all (each file's own limits
    are cut to what is left): fifty files that each take just under the limit cannot hold a caller for
    fifty times as long."""
    out, triangles, seen = {}, 0, set()
    total = safeio.LIMITS.assembly_parse_seconds
    outer = getattr(_BUDGET, "deadline", None)
    _BUDGET.deadline = time.monotonic() + total if outer is None else outer
    try:
        for i, (pid, part) in enumerate(asm.parts.items()):
            try:
                out[pid] = load_part(part, asm.units, i)
            except MeshError as e:
                raise MeshError(f"part {pid!r}: {e}") from None
            triangles = _count_new(out[pid], seen, triangles, pid)
    finally:
        _BUDGET.deadline = outer
    return out


def _count_new(model: PartModel, seen: set, triangles: int, pid: str) -> int:
    if id(model.mesh) not in seen:  # a mesh shared by several parts counts once
        seen.add(id(model.mesh))
        triangles += len(model.mesh.faces)
    if triangles > safeio.LIMITS.assembly_triangles:
        raise MeshError(f"part {pid!r}: the assembly's meshes hold {triangles} triangles by this part, over the "
                        f"{safeio.LIMITS.assembly_triangles} an assembly may have; decimate the largest parts")
    return triangles


def merged_mesh(models: dict[str, PartModel], poses: dict[str, np.ndarray], regions: bool = False) -> trimesh.Trimesh:
    """One mesh of several parts, each moved by its pose (e.g. T_base_member); with `regions`, a part with
    an roi only as its region."""
    meshes = []
    for pid, T in poses.items():
        m = (models[pid].registered_mesh if regions else models[pid].mesh).copy()
        m.apply_transform(T)
        meshes.append(m)
    return trimesh.util.concatenate(meshes)


def base_mesh(models: dict[str, PartModel], view: StepView) -> trimesh.Trimesh:
    """The base object of a step as registration matches it, one mesh in the frame of base[0]: a member
    with an roi is only its region (assembly/roi.py)."""
    return merged_mesh(models, view.T_base_members, regions=True)


def base_body_mesh(models: dict[str, PartModel], view: StepView) -> trimesh.Trimesh:
    """The base object of a step as the camera sees it, whole parts (regions uncut), frame of base[0]: what
    the renderer stands on the table."""
    return merged_mesh(models, view.T_base_members)
