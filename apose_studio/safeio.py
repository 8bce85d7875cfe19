"""Reading the files a user (or a web page, or a dataset) names, without hanging or exhausting memory.

Every read of an input file goes through here. The rules, and why:

- **Only regular files.** A FIFO blocks `open()` until a writer appears (a hang that holds the studio's
  lock), `/dev/zero` never ends, a folder is not a file. Files are opened with `O_NONBLOCK` and checked
  with `fstat` on the open descriptor, so a name swapped after the check cannot slip past it.
- **A size cap per kind of file, checked on the bytes read**, not on what a header or `stat` claims: a
  sparse file or a lying header reads at most cap + 1 bytes before it is refused.
- **Images are measured from their header before they are decoded**: a 3 MB PNG can declare
  30000 x 30000 pixels (5 GB decoded), a 66 KB TIFF 8192 x 8192 pixels of 4 x float64 (2 GB). The
  header's sides, channels, bits and sample type are checked and the decoded bytes capped; a depth
  image must say one 16-bit channel; a TIFF whose tags repeat or contradict each other is refused
  (our reader and libtiff would see different sizes). Only PNG, JPEG and TIFF (BOP's gray images).
- **Work whose cost no header bounds runs in a child process with limits** (`run_bounded`): CPU
  seconds, memory and a wall-clock deadline. A 3 KB STEP file can keep OpenCASCADE busy for minutes,
  and a 62 MB OBJ costs 2.6 GB to parse; the child is killed at its limit and the caller gets one line
  naming the file and the limit. The calling process (and the studio's lock) waits at most that long.
- **Paths are checked as text first**: a NUL byte or a name longer than the system allows gets a
  message, not a ValueError from deep inside.

The limits (`LIMITS`) are listed in docs/RELIABILITY.md; each error names the file, the
limit and the fix.
"""

from __future__ import annotations

import ctypes
import errno
import json
import logging
import os
import pickle
import resource
import select
import signal
import stat
import struct
import threading
import time
import warnings
import zlib
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from apose_studio.errors import AposeError
from apose_studio.text import escaped, unsafe_char  # the one rule for invisible characters (re-exported)

MB = 2 ** 20
GB = 2 ** 30


@dataclass(frozen=True)
class Limits:
    text_bytes: int = 5 * MB  # an assembly YAML, camera.json, a manifest
    json_bytes: int = 256 * MB  # a scene's scene_gt.json / scene_camera.json (thousands of images)
    csv_bytes: int = 256 * MB  # a BOP19 results file
    image_bytes: int = 256 * MB  # one rgb/depth/mask file
    image_side: int = 8192  # pixels, either side
    image_decoded_bytes: int = 256 * MB  # what decoding may allocate: 8192 x 8192 RGBA, 8-bit
    mesh_bytes: int = 512 * MB  # one mesh file (a 10M-triangle binary STL is 500 MB)
    mesh_triangles: int = 2_000_000  # one mesh (a 100 MB binary STL: ~1 GB and ~12 s to read and prepare)
    assembly_triangles: int = 8_000_000  # all distinct meshes of an assembly together
    parse_cpu_seconds: float = 30.0  # CPU time reading one mesh file may take (in a child process)
    parse_wall_seconds: float = 60.0  # and wall-clock time (a busy machine; a child that sleeps)
    parse_memory_bytes: int = 2 * GB  # memory reading one mesh file may map beyond what the process has
    assembly_parse_seconds: float = 120.0  # reading all the mesh files of one assembly (load_parts)
    path_chars: int = 4096  # Linux PATH_MAX


LIMITS = Limits()


def check_path_text(path: str | os.PathLike, what: str = "path", value: bool = False) -> Path:
    """`path` as a Path, or an AposeError for a NUL byte, a control or invisible character (a newline,
    ESC, a bidi override: a name that would forge or disguise output), or an over-long name. `value`: the text
    is a value, not a path (a box, a parameter): the same checks, said of a value."""
    text = os.fspath(path)
    if "\x00" in text:
        raise AposeError(f"{what} {text[:60]!r}...: contains a NUL byte; type the {'value' if value else 'path'} again")
    bad = unsafe_char(text)
    if bad is not None:
        fix = "type it again without it" if value else "rename the file (or folder) without it"
        raise AposeError(f"{what} {escaped(text[:120])}: holds the control or invisible character {bad}; {fix}")
    if len(text) > LIMITS.path_chars:
        if value:
            raise AposeError(f"{what} of {len(text)} characters: longer than the {LIMITS.path_chars} a value may have")
        raise AposeError(f"{what} of {len(text)} characters: longer than the {LIMITS.path_chars} a path may have; "
                         "use a shorter path")
    return Path(text)


_READS = threading.local()  # .roots: the folders this thread may read files from (None: anywhere)


@contextmanager
def reads_within(roots):
    """Inside this block, every file this thread opens through safeio must really lie under one of
    `roots` (resolved after opening, links followed), else an AposeError names where it leads. The
    studio runs every page action inside it, so no path into the file readers (a typed path, a folder's
    listing, a link inside the workspace, a file an assembly or a dataset names) reads outside.
    `roots=None`: no limit."""
    previous = getattr(_READS, "roots", None)
    _READS.roots = None if roots is None else tuple(Path(r).resolve() for r in roots)
    try:
        yield
    finally:
        _READS.roots = previous


def read_roots() -> tuple[Path, ...] | None:
    """The folders this thread may read files from (`reads_within`), None where it may read anywhere: work handed
    to another thread takes them along (registration.side_by_side), or it would read outside the studio's
    workspace."""
    return getattr(_READS, "roots", None)


def _check_within(fd: int, path: Path) -> None:
    roots = getattr(_READS, "roots", None)
    if roots is None:
        return
    try:
        real = Path(os.readlink(f"/proc/self/fd/{fd}"))  # the file that was opened, not a name re-resolved later
    except OSError:
        real = Path(os.path.realpath(path))
    if not any(real == r or real.is_relative_to(r) for r in roots):
        os.close(fd)
        raise AposeError(f"{path}: leads outside the studio's workspace (through a link); the studio reads only "
                         "there. Move the file in, or restart with --root covering it.")  # where it leads: not the page's business


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
    _check_within(fd, path)
    return fd, st


def not_a_regular_file(path: str | os.PathLike) -> str | None:
    """What `path` is when it exists (or is a link) but is no regular file ("a pipe, device or socket",
    "a folder", "a broken link"), without opening it; None for a regular file or nothing there."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        return "a broken link" if p.is_symlink() else None
    except OSError as e:
        return f"not readable ({e.strerror})"
    if stat.S_ISREG(st.st_mode):
        return None
    return "a folder, not a file" if stat.S_ISDIR(st.st_mode) else "not a regular file (a pipe, device or socket)"


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
            try:
                chunk = os.read(fd, min(limit + 1 - total, 16 * MB))
            except OSError as e:  # /proc/self/mem (EIO), a file on a failing disk or a vanished share
                raise AposeError(f"{path}: cannot be read ({e.strerror}); choose {what} that is a plain file on a "
                                 "working disk") from None
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
    """Strict JSON (no NaN/Infinity, numbers of at most 300 digits, no key twice in an object, bounded
    nesting) or an AposeError naming `where`."""
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

    def unique(pairs):  # two values for one key: two readers would read two files (YAML refuses them too)
        out = {}
        for k, v in pairs:
            if k in out:
                raise ValueError(f"the key {escaped(k[:60])!r} is given twice; keep one")
            out[k] = v
        return out

    try:
        return json.loads(text, parse_constant=constant, parse_int=number, parse_float=real, object_pairs_hook=unique)
    except json.JSONDecodeError as e:
        raise AposeError(f"{where}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except ValueError as e:
        raise AposeError(f"{where}: not usable JSON ({e})") from None
    except RecursionError:
        raise AposeError(f"{where}: nested far too deeply to be this file") from None


def read_json(path: str | os.PathLike, what: str = "a JSON file", limit: int = LIMITS.json_bytes):
    return parse_json(read_text(path, what, limit), str(path))


# ------------------------------------------------------------------------------------- images


class ImageHeader(NamedTuple):
    """What an image file's header declares, read without decoding it."""

    format: str  # PNG, JPEG, TIFF
    width: int
    height: int
    channels: int  # samples per pixel as stored (a palette PNG: 1)
    bits: int  # per sample
    sample: str = "uint"  # uint, int or float
    decoded_channels: int = 0  # what the decoder makes of it (a palette: 3, gray + alpha: 4); 0: channels
    extra_bytes_per_pixel: int = 0  # what the decoder holds besides (a progressive JPEG's coefficients)

    def decoded_bytes(self, out_channels: int = 0) -> int:
        """The most decoding may allocate: the decoded image at its own depth, or the converted one."""
        per_sample = (self.bits + 7) // 8
        decoded = (self.decoded_channels or self.channels) * per_sample + self.extra_bytes_per_pixel
        return self.width * self.height * max(decoded, out_channels)


class _Crafted(ValueError):
    """A header that contradicts itself: refused whatever the decoder would make of it."""


def image_header(data: bytes) -> ImageHeader | None:
    """What a PNG's IHDR, a JPEG's SOF marker or a TIFF's first directory declare, without decoding;
    None when the bytes are none of them. Raises _Crafted for a TIFF whose tags repeat or disagree."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 26 and data[12:16] == b"IHDR":
        w, h, bits, colour = struct.unpack(">IIBB", data[16:26])
        channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour, 0)
        decoded = {3: 4, 4: 4}.get(colour, channels)  # OpenCV expands a palette (with tRNS: BGRA) and gray + alpha
        return ImageHeader("PNG", w, h, channels, bits, "uint", decoded)
    if data[:4] in (b"II*\x00", b"MM\x00*") and len(data) >= 8:
        return _tiff_header(data)
    if data[:2] == b"\xff\xd8":
        return _jpeg_header(data)
    return None


def _jpeg_header(data: bytes) -> ImageHeader | None:
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
            progressive = marker in (0xC2, 0xC6, 0xCA, 0xCE)  # libjpeg keeps every coefficient (2 bytes) in memory
            return ImageHeader("JPEG", w, h, channels, bits, "uint", max(channels, 3),
                               2 * channels if progressive else 0)
        if seg < 2:
            return None
        i += seg
    return None


_TIFF_TAG_NAMES = {256: "width", 257: "height", 258: "bits per sample", 259: "compression", 262: "photometric",
                   273: "strip offsets", 277: "samples per pixel", 278: "rows per strip", 279: "strip byte counts",
                   284: "planar configuration", 322: "tile width", 323: "tile length", 339: "sample format"}


def _tiff_header(data: bytes) -> ImageHeader | None:
    """The first directory of a TIFF: width, height, samples per pixel, bits and sample format. A tag
    that appears twice is refused: libtiff keeps the first, a reader that keeps the last sees another size."""
    end = "<" if data[:2] == b"II" else ">"
    sizes = {1: 1, 3: 2, 4: 4, 8: 2, 9: 4}  # BYTE, SHORT, LONG, SSHORT, SLONG

    def values(typ: int, count: int, at: int) -> list[int]:
        size = sizes.get(typ)
        if size is None or count < 1 or count > 64:
            raise _Crafted(f"a TIFF tag of type {typ} with {count} values")
        if size * count > 4:
            (at,) = struct.unpack(end + "I", data[at:at + 4])
        code = {1: "B", 3: "H", 4: "I", 8: "h", 9: "i"}[typ]
        return list(struct.unpack(end + code * count, data[at:at + size * count]))

    try:
        (ifd,) = struct.unpack(end + "I", data[4:8])
        (n,) = struct.unpack(end + "H", data[ifd:ifd + 2])
        if n == 0 or n > 1000:
            return None
        seen: dict[int, list[int]] = {}
        for k in range(n):
            e = ifd + 2 + 12 * k
            tag, typ, count = struct.unpack(end + "HHI", data[e:e + 8])
            if tag in seen:
                raise _Crafted(f"its TIFF header gives tag {tag} ({_TIFF_TAG_NAMES.get(tag, 'tag')}) twice")
            seen[tag] = values(typ, count, e + 8) if tag in _TIFF_TAG_NAMES and tag not in (273, 279) else []
    except struct.error:
        return None
    if 256 not in seen or 257 not in seen:
        return None
    for tag in (256, 257, 277, 262, 284):
        if tag in seen and len(seen[tag]) != 1:
            raise _Crafted(f"its TIFF header gives {len(seen[tag])} values for the {_TIFF_TAG_NAMES[tag]}")
    spp = seen.get(277, [1])[0]
    bits, fmt = seen.get(258, [1]), seen.get(339, [1])
    if len(set(bits)) != 1 or len(set(fmt)) != 1 or len(bits) not in (1, spp) or len(fmt) not in (1, spp):
        raise _Crafted(f"its TIFF header's bits per sample {bits} and sample format {fmt} disagree with its "
                       f"{spp} samples per pixel")
    sample = {1: "uint", 2: "int", 3: "float"}.get(fmt[0], "unknown")
    # libtiff's RGBA path (palette, YCbCr, CMYK, odd bit depths) decodes into 4 bytes per pixel
    return ImageHeader("TIFF", seen[256][0], seen[257][0], spp, bits[0], sample, max(spp, 4 if spp > 1 else 1))


def check_image_header(path, head: ImageHeader | None, what: str, depth: bool = False, out_channels: int = 0) -> None:
    """Refuse from the header alone what decoding would make too large or wrong: a side over
    LIMITS.image_side, more decoded bytes than LIMITS.image_decoded_bytes, float or deep samples, and for
    a depth image anything but one 16-bit unsigned channel."""
    if head is None:
        raise AposeError(f"{path}: not a PNG, JPEG or TIFF image (or its header is damaged); save {what} as PNG")
    fmt, w, h = head.format, head.width, head.height
    side = LIMITS.image_side
    if w == 0 or h == 0:
        raise AposeError(f"{path}: its {fmt} header says {w} x {h} pixels; the image is empty or damaged")
    if w > side or h > side:
        raise AposeError(f"{path}: its {fmt} header says {w} x {h} pixels, over the {side} x {side} an image may "
                         "have; is it the right file? (depth cameras give at most a few thousand pixels a side)")
    kind = f"{head.bits}-bit {'' if head.sample == 'uint' else head.sample + ' '}{fmt} with {head.channels} channels"
    dtype = {"uint": "uint", "int": "int", "float": "float"}.get(head.sample, "?") + str(head.bits)
    if depth and head.channels != 1:  # said from the header: nothing is decoded
        raise AposeError(f"{path}: a {kind}; depth is one channel of 16-bit integers (depth in mm = value x "
                         "depth_scale), as RealSense, Kinect and BOP write it")
    if depth and (head.bits != 16 or head.sample != "uint"):
        raise AposeError(f"{path}: a {dtype} depth image; expected 16-bit integers (depth in mm = value x "
                         "depth_scale), as RealSense, Kinect and BOP write them")
    if not depth and (head.channels not in (1, 2, 3, 4) or head.bits not in (1, 2, 4, 8, 16) or head.sample != "uint"):
        raise AposeError(f"{path}: a {kind} ({dtype}); {what} must have 1 to 4 channels of 8-bit (or 16-bit) "
                         "integers: save it as an 8-bit PNG")
    need, cap = head.decoded_bytes(out_channels), LIMITS.image_decoded_bytes
    if need > cap:
        raise AposeError(f"{path}: a {w} x {h} {kind}, {_size_text(need)} once decoded, over the "
                         f"{_size_text(cap)} an image may take; save {what} smaller, or as an 8-bit PNG")


def read_image(path: str | os.PathLike, flags: int, what: str = "an image", depth: bool = False):
    """A PNG, JPEG or TIFF decoded by OpenCV (`flags` as cv2.imread), after its header has been checked
    (`check_image_header`; `depth`: one 16-bit channel); returns (array, header)."""
    return decode_image(read_bytes(path, what, LIMITS.image_bytes), path, flags, what, depth)


PNG_CHUNKS = 65536  # damaged: more chunks than this in a PNG is refused (a 64 MB PNG written in 8 KB chunks has 8192)


def damaged(data: bytes, fmt: str) -> str:
    """Why the bytes of a PNG or JPEG are damaged ("" when they look whole), checked before decoding: libpng prints
    its own complaint on stderr before OpenCV gives up ("PNG input buffer is incomplete", "IDAT: CRC error"), and
    libjpeg decodes what it has and paints the rest grey. A PNG's chunks are walked, each checked against its CRC,
    up to IEND; a JPEG must end with its end-of-image marker (FF D9; one inside the data, a thumbnail's, can hide a
    cut, and a JPEG's scan data has no checksum: damage inside it is decoded as it is)."""
    if fmt == "PNG":
        i, chunks = 8, 0
        while i + 12 <= len(data):
            chunks += 1
            if chunks > PNG_CHUNKS:  # a writer's chunks hold kilobytes; millions of empty ones only make work
                return f"over {PNG_CHUNKS} chunks"
            n, kind = struct.unpack(">I4s", data[i:i + 8])
            end = i + 12 + n
            if end > len(data):
                return f"truncated: its {kind.decode('latin-1')} chunk runs past the file's end"
            if zlib.crc32(data[i + 4:end - 4]) != struct.unpack(">I", data[end - 4:end])[0]:
                return f"its {kind.decode('latin-1')} chunk fails its checksum (CRC)"
            if kind == b"IEND":
                return ""
            i = end
        return "truncated: it stops before its IEND chunk"
    if fmt == "JPEG" and data.rfind(b"\xff\xd9") < 2:
        return "truncated: it stops before its end-of-image marker"
    return ""


def decode_image(data: bytes, path, flags: int, what: str = "an image", depth: bool = False):
    """read_image on bytes already in memory (a request's image): `path` names them in errors."""
    try:
        head = image_header(data)
    except _Crafted as e:
        raise AposeError(f"{path}: {e}; the file is damaged or crafted: save {what} again as PNG") from None
    out = {cv2.IMREAD_COLOR: 3, getattr(cv2, "IMREAD_COLOR_RGB", cv2.IMREAD_COLOR): 3, cv2.IMREAD_GRAYSCALE: 1}.get(flags, 0)
    check_image_header(path, head, what, depth, out)
    fmt, w, h = head.format, head.width, head.height
    why = damaged(data, fmt)  # refused here: the decoder would print its own complaint on stderr, or decode half
    if why:
        raise AposeError(f"{path}: not a readable {fmt} image ({why}); save {what} again, or copy it whole")
    if flags >= 0:  # pixels as stored: an RGB-D image is registered to its depth pixel by pixel, and a JPEG's EXIF
        # orientation (a phone's tag) would turn the colour against the depth (a "portrait" tag read as damaged)
        flags |= cv2.IMREAD_IGNORE_ORIENTATION
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)  # OpenCV's own pixel cap: set in __init__.py
    except cv2.error as e:  # a decoder's own refusal (e.g. its pixel cap) is bad input, not a bug
        raise AposeError(f"{path}: not a readable {fmt} image ({str(e).strip().splitlines()[-1][:120]}); "
                         f"save {what} again as PNG") from None
    if img is None:
        raise AposeError(f"{path}: not a readable {fmt} image (corrupt, truncated, or over "
                         f"{LIMITS.image_side} x {LIMITS.image_side} pixels)")
    if img.shape[0] != h or img.shape[1] != w:  # the header read here and the decoder's disagree: refuse
        raise AposeError(f"{path}: its {fmt} header says {w} x {h} pixels but it decodes to {img.shape[1]} x "
                         f"{img.shape[0]}; the file is damaged or crafted: save {what} again")
    return img, head


# ------------------------------------------------------------------------- bounded work in a child


class LimitExceeded(AposeError):
    """Work run by `run_bounded` passed one of its limits (or its process died); `kind` says which:
    "cpu", "wall", "memory", "output", "crashed"."""

    def __init__(self, message: str, kind: str):
        super().__init__(message)
        self.kind = kind


try:  # loaded here, never in a child (an import there could wait on a lock a thread of the parent held)
    _prctl = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):
    _prctl = None


def _vm_size() -> int:
    try:
        with open("/proc/self/status", "rb") as f:
            for line in f:
                if line.startswith(b"VmSize:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _limit_child(cpu_s: float, memory: int, file_bytes: int) -> None:
    """In the child, before any work: die on Ctrl-C as the parent does, no core dumps, and the limits."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if _prctl is not None:  # die with the thread that forked us, should it be killed while we work
        _prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    cpu = max(1, int(np.ceil(cpu_s)))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 2))  # SIGXCPU at the soft limit, SIGKILL 2 s later
    mapped = _vm_size()  # what the fork already maps is shared with the parent, not new
    if memory and mapped:  # (without /proc the CPU and wall-clock limits still hold)
        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        want = mapped + memory
        resource.setrlimit(resource.RLIMIT_AS, (want if hard == resource.RLIM_INFINITY else min(want, hard), hard))
    if file_bytes:
        resource.setrlimit(resource.RLIMIT_FSIZE, (file_bytes, file_bytes))
    logging.disable(logging.CRITICAL)  # never take a handler's lock another thread of the parent may hold
    warnings.simplefilter("ignore")


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def run_bounded(fn, *args, where: str, doing: str, fix: str, cpu_s: float | None = None,
                wall_s: float | None = None, memory: int | None = None, output_bytes: int = GB,
                file_bytes: int = 0):
    """`fn(*args)` run in a forked child under limits: `cpu_s` of CPU time, `memory` bytes of new
    address space, `wall_s` seconds in all (defaults: LIMITS.parse_*), `file_bytes` per file written.
    Returns what fn returns (pickled back, at most `output_bytes`). An AposeError raised in the child is
    raised here as the same kind with its message; a limit passed is a LimitExceeded, one line:
    "{where}: {doing} took more than 30 s of CPU time ...; {fix}".

    Why a fork: it costs milliseconds (the child has every module the parent imported and sees its
    state), works in the worker processes of `apose eval --workers` (which may not start processes
    of their own through multiprocessing), and the child touches no lock another thread may hold:
    it logs nothing and only parses. Any hang is cut by the wall-clock deadline all the same."""
    cpu_s = LIMITS.parse_cpu_seconds if cpu_s is None else cpu_s
    wall_s = LIMITS.parse_wall_seconds if wall_s is None else wall_s
    memory = LIMITS.parse_memory_bytes if memory is None else memory
    r, w = os.pipe()
    try:
        pid = os.fork()
    except OSError as e:  # out of processes or memory: the machine's state, said as such
        os.close(r)
        os.close(w)
        raise AposeError(f"{where}: cannot start the process that reads it ({e.strerror}); close other programs "
                         "and try again") from None
    if pid == 0:  # the child: never returns, never runs the parent's exit handlers
        code = 0
        try:
            os.close(r)
            _limit_child(cpu_s, memory, file_bytes)
            try:
                result = ("ok", fn(*args))
            except AposeError as e:
                result = ("error", type(e), str(e))
            except MemoryError:
                result = ("memory",)
            blob = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
            _write_all(w, struct.pack("<Q", len(blob)))
            _write_all(w, blob)
        except MemoryError:
            try:
                blob = pickle.dumps(("memory",))
                _write_all(w, struct.pack("<Q", len(blob)) + blob)
            except BaseException:
                code = 3
        except BaseException as e:  # a bug in fn: say what it was
            try:
                blob = pickle.dumps(("bug", f"{type(e).__name__}: {str(e)[:300]}"))
                _write_all(w, struct.pack("<Q", len(blob)) + blob)
            except BaseException:
                code = 4
        finally:
            os._exit(code)
    os.close(w)
    reaped, status, usage = False, 0, None
    buf, too_much, timed_out = bytearray(), False, False
    deadline = time.monotonic() + wall_s
    poller = select.poll()  # not select(): a studio may hold more than 1024 descriptors
    poller.register(r, select.POLLIN | select.POLLHUP)
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                timed_out = True
                break
            if not poller.poll(min(left, 3600.0) * 1000):
                continue
            chunk = os.read(r, 4 * MB)
            if not chunk:
                break
            buf += chunk
            if len(buf) > output_bytes + 8:
                too_much = True
                break
        if timed_out or too_much:
            os.kill(pid, signal.SIGKILL)
        _, status, usage = os.wait4(pid, 0)
        reaped = True
    finally:
        os.close(r)
        if not reaped:  # interrupted (Ctrl-C) while waiting: the child goes too
            try:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
            except ChildProcessError:
                pass
    cpu_used = usage.ru_utime + usage.ru_stime if usage is not None else 0.0
    mem_text = f"{memory / GB:g} GB" if memory >= GB else _size_text(memory)

    def limit(kind: str, text: str) -> LimitExceeded:
        return LimitExceeded(f"{where}: {doing} {text}; {fix}", kind)

    if timed_out:
        raise limit("wall", f"took more than {wall_s:g} s (the most it may take)")
    if too_much:
        raise limit("output", f"made more than {_size_text(output_bytes)} of data (the most it may)")
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        if sig == signal.SIGXCPU or (sig == signal.SIGKILL and cpu_used >= cpu_s - 0.5):
            raise limit("cpu", f"took more than {cpu_s:g} s of CPU time (the most it may take)")
        if sig == signal.SIGXFSZ:
            raise limit("output", f"wrote a file of more than {_size_text(file_bytes)} (the most it may)")
        name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else str(sig)
        raise limit("crashed", f"stopped with {name} (out of the {mem_text} of memory it may use, or a crash "
                               "in the reader)")
    if len(buf) < 8 or len(buf) != 8 + struct.unpack("<Q", bytes(buf[:8]))[0]:
        raise limit("crashed", f"stopped without an answer (exit status {os.WEXITSTATUS(status)}; out of the "
                               f"{mem_text} of memory it may use?)")
    result = pickle.loads(memoryview(buf)[8:])
    buf = None
    if result[0] == "ok":
        return result[1]
    if result[0] == "memory":
        raise limit("memory", f"needed more than {mem_text} of memory (the most it may use)")
    if result[0] == "error":
        cls, message = result[1], result[2]  # the same kind, where it takes just a message (MeshError, ...)
        raise cls(message) if cls.__init__ is AposeError.__init__ else AposeError(message)
    raise RuntimeError(f"{where}: {doing} failed in its child process: {result[1]}")
