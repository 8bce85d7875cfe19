"""Reading the files a user (or a web page, or a dataset) names, without hanging or exhausting memory.

Every read of an input file goes through here. The rules, and why:

- **Only regular files.** A FIFO blocks `open()` until a writer appears (a hang that holds the studio's
  lock), `/dev/zero` never ends, a folder is not a file. Files are opened with `O_NONBLOCK` and checked
  with `fstat` on the open descriptor, so a name swapped after the check cannot slip past it.
- **A size cap per kind of file, checked on the bytes read**, not on what a header or `stat` claims: a
  sparse file or a lying header reads at most cap + 1 bytes before it is refused.
- **Images are measured from their header before they are decoded**: a 3 MB PNG can declare
  30000 x 30000 pixels (5 GB decoded). Only PNG, JPEG and TIFF (BOP's gray images) are read.
- **Paths are checked as text first**: a NUL byte or a name longer than the system allows gets a
  message, not a ValueError from deep inside.

The limits (`LIMITS`) are listed in docs/RELIABILITY.md; each error names the file, the
limit and the fix.
"""

from __future__ import annotations

import errno
import json
import os
import stat
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from apose_studio.errors import AposeError

MB = 2 ** 20


@dataclass(frozen=True)
class Limits:
    text_bytes: int = 5 * MB  # an assembly YAML, camera.json, a manifest
    json_bytes: int = 256 * MB  # a scene's scene_gt.json / scene_camera.json (thousands of images)
    csv_bytes: int = 256 * MB  # a BOP19 results file
    image_bytes: int = 256 * MB  # one rgb/depth/mask file
    image_side: int = 8192  # pixels, either side
    mesh_bytes: int = 512 * MB  # one mesh file (a 10M-triangle binary STL is 500 MB)
    mesh_triangles: int = 10_000_000  # one mesh
    assembly_triangles: int = 40_000_000  # all distinct meshes of an assembly together
    path_chars: int = 4096  # Linux PATH_MAX


LIMITS = Limits()


def check_path_text(path: str | os.PathLike, what: str = "path") -> Path:
    """`path` as a Path, or an AposeError for a NUL byte or an over-long name."""
    text = os.fspath(path)
    if "\x00" in text:
        raise AposeError(f"{what} {text[:60]!r}...: contains a NUL byte; type the path again")
    if len(text) > LIMITS.path_chars:
        raise AposeError(f"{what} of {len(text)} characters: longer than the {LIMITS.path_chars} a path may have; "
                         "use a shorter path")
    return Path(text)


def open_regular(path: str | os.PathLike, what: str = "a file") -> tuple[int, os.stat_result]:
    """A read-only descriptor of the regular file at `path` and its stat, or an AposeError that says what
    the path is instead (missing, a folder, a pipe or device) and what to choose."""
    path = check_path_text(path, "path")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise AposeError(f"{path}: file not found; type the path of {what}") from None
    except IsADirectoryError:
        raise AposeError(f"{path}: a folder, not a file; choose {what} inside it") from None
    except PermissionError:
        raise AposeError(f"{path}: permission denied; make it readable, or choose {what} you may read") from None
    except OSError as e:
        if e.errno == errno.ENAMETOOLONG:
            raise AposeError(f"{path}: the name is too long for this system; use a shorter path") from None
        if e.errno == errno.ELOOP:
            raise AposeError(f"{path}: a loop of symbolic links; point it at {what}") from None
        raise AposeError(f"{path}: cannot be opened ({e.strerror}); choose {what}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        if stat.S_ISDIR(st.st_mode):
            raise AposeError(f"{path}: a folder, not a file; choose {what} inside it")
        raise AposeError(f"{path}: not a regular file (a pipe, device or socket); choose {what}")
    return fd, st


def _size_text(n: int) -> str:
    return f"{n / MB:.1f} MB" if n >= MB // 10 else f"{n} bytes"


def read_bytes(path: str | os.PathLike, what: str = "a file", limit: int = LIMITS.text_bytes) -> bytes:
    """The whole file, refused (without reading more than limit + 1 bytes) when larger than `limit`."""
    fd, st = open_regular(path, what)
    try:
        if st.st_size > limit:
            raise AposeError(f"{path}: {_size_text(st.st_size)}, over the {_size_text(limit)} that {what} may have; "
                             "is it the right file?")
        chunks, total = [], 0
        while total <= limit:
            chunk = os.read(fd, min(limit + 1 - total, 16 * MB))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
        if total > limit:
            raise AposeError(f"{path}: grew past the {_size_text(limit)} that {what} may have while being read")
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_text(path: str | os.PathLike, what: str = "a text file", limit: int = LIMITS.text_bytes) -> str:
    """UTF-8 text (a leading byte-order mark is dropped), capped as `read_bytes`."""
    data = read_bytes(path, what, limit)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise AposeError(f"{path}: not UTF-8 text (byte {e.start}); save it as UTF-8") from None


def parse_json(text: str, where: str):
    """Strict JSON (no NaN/Infinity, numbers of at most 300 digits, bounded nesting) or an AposeError
    naming `where`."""
    def constant(name):
        raise ValueError(f"{name} is not JSON; write a number")

    def number(s: str):
        if len(s) > 300:
            raise ValueError(f"a number of {len(s)} digits")
        return int(s)

    def real(s: str):
        if len(s) > 300:
            raise ValueError(f"a number of {len(s)} characters")
        v = float(s)
        if v in (float("inf"), float("-inf")):
            raise ValueError(f"{s} is too large for a number")
        return v

    try:
        return json.loads(text, parse_constant=constant, parse_int=number, parse_float=real)
    except json.JSONDecodeError as e:
        raise AposeError(f"{where}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except ValueError as e:
        raise AposeError(f"{where}: not usable JSON ({e})") from None
    except RecursionError:
        raise AposeError(f"{where}: nested far too deeply to be this file") from None


def read_json(path: str | os.PathLike, what: str = "a JSON file", limit: int = LIMITS.json_bytes):
    return parse_json(read_text(path, what, limit), str(path))


# ------------------------------------------------------------------------------------- images


def image_header(data: bytes) -> tuple[str, int, int, int, int] | None:
    """(format, width, height, channels, bits per channel) from a PNG's IHDR or a JPEG's SOF marker,
    without decoding; None when the bytes are neither."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 26 and data[12:16] == b"IHDR":
        w, h, bits, colour = struct.unpack(">IIBB", data[16:26])
        channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour, 0)
        return "PNG", w, h, channels, bits
    if data[:4] in (b"II*\x00", b"MM\x00*") and len(data) >= 8:
        return _tiff_header(data)
    if data[:2] == b"\xff\xd8":
        return _jpeg_header(data)
    return None


def _jpeg_header(data: bytes):
    """The first frame header (SOFn) of a JPEG, walked as libjpeg walks it: markers start with one or
    more 0xFF fill bytes; a scan (SOS) or the end before any frame header means no size (refused)."""
    i = 2
    while i < len(data):
        if data[i] != 0xFF:
            return None
        while i < len(data) and data[i] == 0xFF:  # fill bytes before the marker code
            i += 1
        if i >= len(data):
            return None
        marker = data[i]
        i += 1
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            continue
        if marker in (0xD9, 0xDA) or i + 2 > len(data):  # end of image, or a scan before any frame header
            return None
        (seg,) = struct.unpack(">H", data[i:i + 2])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 8 > len(data):
                return None
            bits, h, w, channels = struct.unpack(">BHHB", data[i + 2:i + 8])
            return "JPEG", w, h, channels, bits
        if seg < 2:
            return None
        i += seg
    return None


def _tiff_header(data: bytes):
    """(TIFF, width, height, channels, bits) from the first IFD (tags 256, 257, 258, 277)."""
    end = "<" if data[:2] == b"II" else ">"
    try:
        (ifd,) = struct.unpack(end + "I", data[4:8])
        (n,) = struct.unpack(end + "H", data[ifd:ifd + 2])
        tags = {}
        for k in range(min(n, 512)):
            e = ifd + 2 + 12 * k
            tag, typ, _count = struct.unpack(end + "HHI", data[e:e + 8])
            value = struct.unpack(end + ("H" if typ == 3 else "I"), data[e + 8:e + (10 if typ == 3 else 12)])[0]
            tags[tag] = value
    except struct.error:
        return None
    if 256 not in tags or 257 not in tags:
        return None
    return "TIFF", tags[256], tags[257], tags.get(277, 1), tags.get(258, 8) if tags.get(277, 1) == 1 else 8


def read_image(path: str | os.PathLike, flags: int, what: str = "an image"):
    """A PNG, JPEG or TIFF decoded by OpenCV (`flags` as cv2.imread), after its header has been checked against
    `LIMITS.image_side`; returns (array, header)."""
    data = read_bytes(path, what, LIMITS.image_bytes)
    head = image_header(data)
    if head is None:
        raise AposeError(f"{path}: not a PNG, JPEG or TIFF image (or its header is damaged); save {what} as PNG")
    fmt, w, h, _, _ = head
    side = LIMITS.image_side
    if w == 0 or h == 0:
        raise AposeError(f"{path}: its {fmt} header says {w} x {h} pixels; the image is empty or damaged")
    if w > side or h > side:
        raise AposeError(f"{path}: its {fmt} header says {w} x {h} pixels, over the {side} x {side} an image may "
                         "have; is it the right file? (depth cameras give at most a few thousand pixels a side)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)  # OpenCV's own pixel cap: set in __init__.py
    if img is None:
        raise AposeError(f"{path}: not a readable {fmt} image (corrupt, truncated, or over {side} x {side} pixels)")
    if img.shape[0] != h or img.shape[1] != w:  # the header read here and the decoder's disagree: refuse
        raise AposeError(f"{path}: its {fmt} header says {w} x {h} pixels but it decodes to {img.shape[1]} x "
                         f"{img.shape[0]}; the file is damaged or crafted: save {what} again")
    return img, head
