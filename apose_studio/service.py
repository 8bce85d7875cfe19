"""`apose serve`: a warm estimation service for robot programs in any language, over HTTP and JSON.

It loads one assembly, prepares every step's base object and keeps them (and the estimator's caches)
warm, and answers:

- `GET /health`: `{"ok": true, "assembly", "steps", "busy", "queue"}`;
- `POST /estimate` with a JSON body: `rgb_png_b64` (PNG/JPEG, base64), `depth_png_b64` (16-bit PNG, depth in
  mm = value x camera.depth_scale), `camera` (as a capture's camera.json: `cam_K` or `fx, fy, cx, cy`,
  `depth_scale`, optional BOP `cam_R_w2c` / `cam_t_w2c`), `step`, `box` [x0, y0, x1, y1] or `point` [u, v],
  optional `hand_eye` (a calibration as robot/handeye.py reads it, inline), `T_robot_flange`, `grasp`,
  `pick_box` / `pick_point`, `orientation_prior`, `align_depth` (with a box or point: the depth moved back
  onto the colour image around it, as `apose estimate --align-depth`). The answer is the JSON `apose estimate --json` prints
  (with the robot targets when `hand_eye` is given).

Rules, and why:
- **Loopback by default**; on any other address every request needs the token (`Authorization: Bearer
  TOKEN`), as the studio's page does: a robot cell's network is shared.
- **Bounded**: a body over `max_body` bytes is refused from its Content-Length (413) before it is read;
  at most `queue` requests are in the service at once (one estimating, the rest waiting), the next gets 503
  with Retry-After at once; at most `MAX_CONNECTIONS` connections, each read with a timeout (a client that
  sends nothing is dropped).
- **A bad request gets a 4xx** whose `error` is the same one line the CLI prints (naming the key and the
  fix); an unexpected failure is a 500 with a short reason, logged; the service keeps answering.
- **`workers` estimates at a time** (default 2, 1 on one core): the estimator's nearest-neighbour queries
  already use both cores of a 2-core machine, but much of an estimate runs on one, so two at once answer
  waiting clients ~1.3x sooner; answers are the same bits whatever runs beside them (Open3D's seeded RANSAC,
  whose random engine is the process's, runs one at a time: registration/stages.py).
- **Bodies**: JSON with the images as base64 PNG (or .npy), or an NPZ archive (`Content-Type:
  application/x-npz`: numpy.savez of `rgb`, `depth` and `request`, the other keys as JSON text), which spares
  the base64 and PNG decoding (~8 ms of a 640x480 frame's ~13 ms overhead; benchmarks/serve.py).
"""

from __future__ import annotations

import binascii
import ctypes
import hmac
import io
import ipaddress
import json
import logging
import os
import secrets
import socket
import threading
import time
import zipfile
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np

from apose_studio import safeio
from apose_studio.api import estimate_pose, grasp_of
from apose_studio.assembly.model import Assembly, load_assembly
from apose_studio.data.dataset import check_camera_entry, checked_pose_unit, depth_metres
from apose_studio.errors import AposeError
from apose_studio.estimation import pick_base, step_context
from apose_studio.params import Params, resolve_params
from apose_studio.robot.handeye import hand_eye_from_data, matrix

log = logging.getLogger(__name__)

MAX_BODY = 64 * 2 ** 20  # a 1280 x 720 frame as PNGs in base64 is ~4 MB; 64 MB leaves room for 4K
MAX_CONNECTIONS = 32  # connections at once; beyond them a 503 at once
MAX_PER_ADDRESS = 8  # ... from one address (one remote host cannot take them all)
ARRIVAL_S = 30.0  # a request's headers and body must arrive within this of its connection (a slow client goes)
BODIES_IN_FLIGHT = 4  # bodies being read at once, at most this many times max_body bytes declared in all
DEFAULT_WORKERS = min(2, os.cpu_count() or 1)  # estimates at once (--workers): on 2 cores, two at a time answer
# 4 waiting clients ~1.3x sooner than one (benchmarks/serve.py); more only share the same cores
MAX_PIXELS = 1920 * 1200  # a frame's pixels (--max-pixels): depth cameras give at most ~1 MP aligned to colour
REQUEST_KEYS = ("rgb_png_b64", "depth_png_b64", "rgb_npy_b64", "depth_npy_b64", "camera", "step", "box", "point", "hand_eye",
                "T_robot_flange", "grasp", "pick_box", "pick_point", "orientation_prior", "align_depth")
MAX_SIDE = 8192  # pixels a side of an array frame (as safeio's images)
MAX_JSON_ITEMS = 4096  # commas, colons, brackets and braces in a JSON body (a request with hand-eye and grasp: ~150)
NPZ_TYPE = "application/x-npz"  # a body of numpy.savez(rgb=, depth=, request=json text): no base64, no PNG decoding
RGB_FLAG = getattr(cv2, "IMREAD_COLOR_RGB", cv2.IMREAD_COLOR)  # decoded as RGB (OpenCV >= 4.10); see _rgb_of


class BadRequest(AposeError):
    """A request the service cannot use: answered 4xx with its message."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


class EstimationService:
    """The warm part: one assembly, every step prepared, `workers` estimates at a time, at most `queue` requests
    in it (read, decoded and waiting for the estimator), frames of at most `max_pixels`."""

    def __init__(self, assembly: Assembly | str, preset: str = "default", overrides: dict | None = None, queue: int = 8,
                 max_pixels: int = MAX_PIXELS, workers: int = DEFAULT_WORKERS):
        self.asm = assembly if isinstance(assembly, Assembly) else load_assembly(assembly)
        if not self.asm.steps:
            raise AposeError(f"{self.asm.path}: the assembly has no steps; nothing to estimate")
        self.preset, self.overrides = preset, dict(overrides or {})
        self.params: Params = resolve_params(preset, self.asm.registration, **self.overrides)
        for k in range(1, len(self.asm.steps) + 1):  # warm: every step's base prepared now, not on the first call
            ctx = step_context(self.asm, k)[1]
            ctx.base.warm_up(self.params)
            if self.asm.parts[ctx.view.part].grasps:  # a part the robot picks: its own CAD as a base, for the pick
                pick_base(ctx.part).warm_up(self.params)
        self.workers = max(int(workers), 1)
        self.lock = threading.BoundedSemaphore(self.workers)  # estimates at once (each answer the same whatever runs beside it)
        self.queue = max(int(queue), self.workers)
        self.max_pixels = int(max_pixels)
        self._slots = threading.BoundedSemaphore(self.queue)
        self._busy = 0
        self._count = threading.Lock()
        self.served = 0

    def health(self) -> dict:
        return {"ok": True, "assembly": self.asm.name, "steps": len(self.asm.steps), "busy": self._busy,
                "queue": self.queue, "workers": self.workers, "served": self.served}

    @contextmanager
    def slot(self):
        """One of the `queue` places in the service, taken once a body has arrived and held until its answer:
        at most `queue` decoded frames are in memory at once. BadRequest 503 at once when none is free."""
        if not self._slots.acquire(blocking=False):
            raise BadRequest(f"busy: {self.queue} requests are in the service; retry in a moment", 503)
        with self._count:
            self._busy += 1
        try:
            yield
        finally:
            with self._count:
                self._busy -= 1
            self._slots.release()

    def estimate(self, body: bytes, npz: bool = False) -> dict:
        """The answer to one POST /estimate body (JSON, or an NPZ archive: parse_request) (the caller holds a
        `slot`); raises BadRequest (4xx)."""
        req = parse_request(body, len(self.asm.steps), self.max_pixels, npz)
        view = step_context(self.asm, req["step"])[1].view
        if req["hand_eye"] is not None:  # a wrong grasp name is said before the estimate, by its request key
            try:
                grasp_of(self.asm, view.part, req["grasp"], key="grasp:")
            except AposeError as e:
                raise BadRequest(str(e)) from None
        with self.lock:
            est = estimate_pose(req["rgb"], req["depth"], req["K"], self.asm, req["step"], box=req["box"],
                                point=req["point"], T_world_camera=req["T_world_camera"],
                                orientation_prior=req["orientation_prior"], hand_eye=req["hand_eye"],
                                grasp=req["grasp"], pick_box=req["pick_box"], pick_point=req["pick_point"],
                                T_robot_flange=req["T_robot_flange"], align_depth=req["align_depth"], preset=self.preset,
                                **self.overrides)
        with self._count:
            self.served += 1
        return {**est.to_json(), "step": req["step"], "part": view.part, "base": list(view.base),
                "preset": self.params.preset}


def _b64(value, key: str) -> bytes:
    if not isinstance(value, str) or not value:
        got = "an empty text" if value == "" else type(value).__name__
        raise BadRequest(f"{key}: expected the image's bytes in base64 (a non-empty string), got {got}")
    try:
        return binascii.a2b_base64(value, strict_mode=True)  # strict: a stray character is an error, not skipped
    except (binascii.Error, ValueError):
        raise BadRequest(f"{key}: not valid base64; send the PNG file's bytes base64-encoded") from None


def _npy(value, key: str, dtype, ndim: int, max_pixels: int) -> np.ndarray:
    """A base64 .npy array (no pickles) of `dtype` and `ndim` dimensions (H x W x 3 colour, H x W depth), its
    shape checked from its header before its data is read."""
    return _npy_bytes(_b64(value, key), key, dtype, ndim, max_pixels)


def _first_line(e: Exception, n: int) -> str:
    """An exception's message as one short line (numpy's and zipfile's run over lines and quote objects)."""
    lines = str(e).strip().splitlines()
    return (lines[0] if lines else type(e).__name__)[:n]


def _npy_header(f) -> tuple:
    """A .npy file's (shape, dtype) from its header alone (nothing allocated yet); ValueError otherwise."""
    version = np.lib.format.read_magic(f)
    read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}.get(version)
    if read_header is None:
        raise ValueError(f".npy format version {version}")
    shape, _, dt = read_header(f)
    return shape, dt


def _npy_bytes(data: bytes, key: str, dtype, ndim: int, max_pixels: int) -> np.ndarray:
    """_npy on the .npy file's bytes."""
    f = io.BytesIO(data)
    try:
        shape, dt = _npy_header(f)
    except (ValueError, OSError, SyntaxError) as e:
        raise BadRequest(f"{key}: not a .npy array ({_first_line(e, 80)}); send numpy.save's bytes") from None
    want = "H x W x 3" if ndim == 3 else "H x W"
    if np.dtype(dt) != np.dtype(dtype) or len(shape) != ndim or (ndim == 3 and shape[2] != 3) or \
            not all(0 < n <= MAX_SIDE for n in shape[:2]):
        raise BadRequest(f"{key}: a {np.dtype(dt).str} array of shape {tuple(shape)}; expected {np.dtype(dtype).str} "
                         f"(little-endian {np.dtype(dtype).name}) {want}, at most {MAX_SIDE} a side"
                         + (", depth in mm x camera.depth_scale" if ndim == 2 else ""))
    _check_pixels(shape[1], shape[0], key, max_pixels)
    f.seek(0)
    try:
        return np.load(f, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise BadRequest(f"{key}: a damaged .npy array ({_first_line(e, 80)})") from None


def _check_pixels(w: int, h: int, key: str, max_pixels: int) -> None:
    """A frame of at most `max_pixels` (`apose serve --max-pixels`): the estimate's work and memory grow with
    the frame (an 8192 x 6144 frame kept the estimator busy for minutes and took 5 GB)."""
    if w * h > max_pixels:
        raise BadRequest(f"{key}: a {w}x{h} frame, over the {max_pixels / 1e6:.1f} million pixels this service takes "
                         "(apose serve --max-pixels); send the camera's own resolution (depth aligned to colour)", 413)


def _image(data: bytes, key: str, flags: int, what: str, max_pixels: int, depth: bool = False):
    """An image's bytes decoded (safeio.decode_image), its size checked against `max_pixels` from its header first."""
    try:
        head = safeio.image_header(data)
    except ValueError as e:  # a TIFF whose tags contradict each other
        raise BadRequest(f"{key}: {e}; the image is damaged or crafted") from None
    if head is not None:
        _check_pixels(head.width, head.height, key, max_pixels)
    return safeio.decode_image(data, key, flags, what, depth=depth)


def _pixels(value, key: str, n: int):
    """A box (4) or point (2) in pixels: a list of numbers or the CLI's "x0,y0,x1,y1" text."""
    if value is None:
        return None
    if not isinstance(value, (list, str)):
        example = "10,20,200,180" if n == 4 else "120,90"
        raise BadRequest(f"{key}: expected {n} numbers in pixels (a list, or text such as '{example}')")
    if isinstance(value, str):
        value = value.split(",")
    try:
        out = tuple(int(round(float(v))) for v in value if not isinstance(v, bool))  # NaN: ValueError; inf: Overflow
    except (TypeError, ValueError, OverflowError):
        out = ()
    if len(out) != n or len(value) != n or any(abs(v) > MAX_SIDE * 4 for v in out):
        raise BadRequest(f"{key}: expected {n} numbers in pixels ({'x0, y0, x1, y1' if n == 4 else 'u, v'})")
    return out


def _depth_of(req: dict, max_pixels: int) -> tuple:
    """The request's depth image: (raw array, PNG header or None, its key)."""
    if "depth_npy_b64" in req:
        return _npy(req["depth_npy_b64"], "depth_npy_b64", np.uint16, 2, max_pixels), None, "depth_npy_b64"
    raw, head = _image(_b64(req["depth_png_b64"], "depth_png_b64"), "depth_png_b64", cv2.IMREAD_UNCHANGED,
                       "the depth image", max_pixels, depth=True)
    return raw, head, "depth_png_b64"


def _rgb_of(req: dict, max_pixels: int) -> np.ndarray:
    """The request's colour image, H x W x 3 RGB."""
    if "rgb_npy_b64" in req:
        return _npy(req["rgb_npy_b64"], "rgb_npy_b64", np.uint8, 3, max_pixels)
    img = _image(_b64(req["rgb_png_b64"], "rgb_png_b64"), "rgb_png_b64", RGB_FLAG, "the colour image", max_pixels)[0]
    return img if RGB_FLAG != cv2.IMREAD_COLOR else img[..., ::-1]


def _decode_both(req: dict, max_pixels: int) -> tuple:
    """The depth (as _depth_of) and the colour image, decoded at the same time: the colour in a second thread
    (OpenCV's decoders and base64 run without the GIL: of a 640x480 frame's ~12 ms, ~4 ms saved). Each image's
    size is checked from its own header before it is decoded; the depth's refusal is said first."""
    got: dict = {}

    def colour() -> None:
        try:
            got["rgb"] = _rgb_of(req, max_pixels)
        except BaseException as e:  # re-raised in the caller, after the depth's own refusal if it has one
            got["error"] = e

    t = threading.Thread(target=colour, name="decode colour", daemon=True)
    t.start()
    try:
        depth = _depth_of(req, max_pixels)
    finally:
        t.join()
    if "error" in got:
        raise got["error"]
    return depth, got["rgb"]


def _json_object(text: str, what: str) -> dict:
    try:
        req = safeio.parse_json(text, what)
    except AposeError as e:
        raise BadRequest(str(e)) from None
    if not isinstance(req, dict):
        raise BadRequest(f"{what} must be a JSON object (rgb_png_b64, depth_png_b64, camera, step, box)")
    return req


def _npz_request(body: bytes, max_pixels: int) -> tuple[dict, tuple]:
    """An NPZ body (numpy.savez: `rgb` H x W x 3 uint8, `depth` H x W uint16 in mm x camera.depth_scale, `request`
    the other keys as JSON text in a 0-d string array) as (request keys, ((depth, None, key), rgb)). Each member's
    size is checked from the archive's directory before it is inflated."""
    limits = {"rgb.npy": 3 * max_pixels + 4096, "depth.npy": 2 * max_pixels + 4096, "request.npy": 4 * 2 ** 20}
    end = body.rfind(b"PK\x05\x06", max(0, len(body) - 2 ** 16 - 22))  # the end record: how many members, before
    # zipfile reads them all (a 64 MB directory of empty members is a million of its objects, ~0.5 GB)
    if end >= 0 and len(body) >= end + 12 and int.from_bytes(body[end + 10:end + 12], "little") > len(limits):
        raise BadRequest(f"the NPZ holds {int.from_bytes(body[end + 10:end + 12], 'little')} members; expected exactly "
                         "rgb, depth and request")
    try:
        zf = zipfile.ZipFile(io.BytesIO(body))
        names = [i.filename for i in zf.infolist()]
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise BadRequest(f"the body is not an NPZ archive ({_first_line(e, 60)}); send numpy.savez(rgb=, depth=, request=)'s "
                         "bytes, or JSON") from None
    if sorted(names) != sorted(limits):
        raise BadRequest(f"the NPZ holds {', '.join(n[:40] for n in names[:6]) or 'nothing'}; expected exactly rgb, depth "
                         "and request (numpy.savez(buf, rgb=..., depth=..., request=json.dumps({...})))")
    data = {}
    for info in zf.infolist():
        key = f"{info.filename[:-4]} (NPZ)"
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED) or info.flag_bits & 0x1:
            how = "encrypted" if info.flag_bits & 0x1 else f"compressed by method {info.compress_type}"
            raise BadRequest(f"{key}: {how}; send members stored or deflated (numpy.savez or savez_compressed), "
                             "not encrypted")
        if info.file_size > limits[info.filename]:
            raise BadRequest(f"{key}: {info.file_size} bytes; at most {limits[info.filename]} (a frame of at most "
                             f"{max_pixels} pixels, apose serve --max-pixels)", 413)
        try:  # zipfile inflates no more than the entry's declared size, then checks its CRC: a member that lies fails
            with zf.open(info) as f:
                data[info.filename] = f.read(limits[info.filename])
        except (zipfile.BadZipFile, ValueError, OSError, EOFError, RuntimeError, NotImplementedError) as e:
            raise BadRequest(f"{key}: a damaged archive member ({_first_line(e, 60)})") from None
    f = io.BytesIO(data["request.npy"])
    try:
        shape, dt = _npy_header(f)
        if np.dtype(dt).kind != "U" or shape != () or np.dtype(dt).itemsize > limits["request.npy"]:
            raise BadRequest("request (NPZ): expected the request's JSON as one text (numpy.savez(..., "
                             "request=json.dumps(...)))")
        f.seek(0)
        text = np.load(f, allow_pickle=False)
    except (ValueError, OSError, EOFError, SyntaxError) as e:
        raise BadRequest(f"request (NPZ): not a .npy array ({_first_line(e, 60)}); put json.dumps({{...}}) there") from None
    req = _json_object(str(text[()]), "request (NPZ)")
    images = [k for k in req if k.startswith(("rgb_", "depth_"))]
    if images:
        raise BadRequest(f"{images[0][:40]}: the NPZ's rgb and depth arrays are the images; leave them out of request")
    depth = _npy_bytes(data["depth.npy"], "depth (NPZ)", np.uint16, 2, max_pixels)
    rgb = _npy_bytes(data["rgb.npy"], "rgb (NPZ)", np.uint8, 3, max_pixels)
    return req, ((depth, None, "depth (NPZ)"), rgb)


def parse_request(body: bytes, n_steps: int, max_pixels: int = 1920 * 1200, npz: bool = False) -> dict:
    """A POST /estimate body (JSON, or with `npz` an NPZ archive: _npz_request) as estimate_pose's arguments;
    BadRequest naming the key otherwise."""
    if npz:
        req, images = _npz_request(body, max_pixels)
    else:
        items = sum(body.count(c) for c in (b",", b":", b"[", b"{"))  # base64 has none of these characters
        if items > MAX_JSON_ITEMS:  # a 60 MB list of {} parses into ~1.5 GB of Python objects: counted before
            raise BadRequest(f"the body holds {items} JSON items; a request is two images and a few small keys (at most "
                             f"{MAX_JSON_ITEMS}): send the images as base64 strings")
        try:
            text = body.decode("utf-8")
        except UnicodeDecodeError:
            raise BadRequest("the body is not UTF-8 text; send JSON") from None
        req, images = _json_object(text, "the request body"), None
    unknown = [k for k in req if k not in REQUEST_KEYS]
    if unknown:
        raise BadRequest(f"{str(unknown[0])[:60]}: unknown key; expected {', '.join(REQUEST_KEYS)}")
    for k in ("camera", "step"):
        if k not in req:
            raise BadRequest(f"{k}: missing")
    for what in ("rgb", "depth") if images is None else ():
        given = [k for k in (f"{what}_png_b64", f"{what}_npy_b64") if k in req]
        if len(given) != 1:
            raise BadRequest(f"{what}_png_b64: missing (or {what}_npy_b64: a .npy array)" if not given else
                             f"{given[0]} and {given[1]}: give the {what} image once")
    step = req["step"]
    if isinstance(step, bool) or not isinstance(step, int) or not 1 <= step <= n_steps:
        raise BadRequest(f"step: {str(step)[:20]} does not exist; the assembly has steps 1..{n_steps}")
    try:
        (raw, head, dkey), rgb = _decode_both(req, max_pixels) if images is None else images
        h, w = raw.shape[:2]
        if rgb.shape[:2] != (h, w):
            raise BadRequest(f"the colour image is {rgb.shape[1]}x{rgb.shape[0]} but {dkey} is {w}x{h}; align depth "
                             "to colour first")
        cam, depth_scale, T_world_camera = checked_pose_unit(check_camera_entry(req["camera"], "camera", w, h), "camera")
        depth = depth_metres(raw, head, depth_scale, dkey, "the request's camera")
        hand_eye = hand_eye_from_data(req["hand_eye"], "hand_eye") if req.get("hand_eye") is not None else None
        flange = matrix(req["T_robot_flange"], "request", "T_robot_flange") if req.get("T_robot_flange") is not None else None
        if flange is not None and hand_eye is not None and hand_eye.T_robot_flange is not None:
            raise BadRequest("T_robot_flange is given twice (at the top and in hand_eye); give the arm's pose at the "
                             "capture once")
        if hand_eye is not None and hand_eye.kind == "eye_in_hand" and flange is None and hand_eye.T_robot_flange is None:
            raise BadRequest("T_robot_flange: missing: an eye-in-hand calibration (T_flange_camera) needs the arm's pose "
                             "at the capture (4x4, metres)")
    except BadRequest:
        raise
    except AposeError as e:
        raise BadRequest(str(e)) from None
    if req.get("box") is not None and req.get("point") is not None:
        raise BadRequest("box and point: give one way to find the base object")
    grasp = req.get("grasp")
    if grasp is not None and not isinstance(grasp, str):
        raise BadRequest("grasp: expected a grasp's name")
    prior, align = (False if req.get(k) is None else req.get(k) for k in ("orientation_prior", "align_depth"))  # null is
    # absent, as for the other optional keys
    for key, value in (("orientation_prior", prior), ("align_depth", align)):
        if not isinstance(value, bool):
            raise BadRequest(f"{key}: expected true or false")
    if align and req.get("box") is None and req.get("point") is None:
        raise BadRequest("align_depth: the depth is compared with the colour image around a prompt; give box or point")
    return {"rgb": np.ascontiguousarray(rgb), "depth": depth,
            "K": cam.K, "step": step, "box": _pixels(req.get("box"), "box", 4), "point": _pixels(req.get("point"), "point", 2),
            "T_world_camera": T_world_camera, "hand_eye": hand_eye, "T_robot_flange": flange, "grasp": grasp,
            "pick_box": _pixels(req.get("pick_box"), "pick_box", 4), "pick_point": _pixels(req.get("pick_point"), "pick_point", 2),
            "orientation_prior": prior, "align_depth": align}


def peer_of(address: str) -> str:
    """Who a connection comes from, as the per-address cap counts it: every loopback address (127.0.0.0/8, ::1,
    ::ffff:127.x) is this machine, one peer (a local process could otherwise take all the connections from
    127.0.0.2, .3, ...); an IPv6 address by its /64 (one host holds a whole /64); else the address."""
    try:
        ip = ipaddress.ip_address(address.split("%")[0])
    except ValueError:
        return address
    if ip.version == 6 and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    if ip.is_loopback:
        return "loopback"
    if ip.version == 6:
        return str(ipaddress.ip_network(f"{ip}/64", strict=False))
    return str(ip)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _AnyHost:
    """Every Host header (a service on all interfaces is reached by many names; its token guards it)."""

    def __contains__(self, _) -> bool:
        return True


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, service: EstimationService, token: str | None, max_body: int):
        self.service, self.token, self.max_body = service, token, max_body
        if ":" in address[0]:  # an IPv6 address
            self.address_family = socket.AF_INET6
        super().__init__(address, _Handler)
        host, port = address[0], self.server_address[1]
        names = {host if ":" not in host else f"[{host}]", "localhost"} | ({"127.0.0.1"} if ":" not in host else set())
        # on loopback (no token) only this address's own names: a page that rebinds its name to 127.0.0.1
        # still sends its name; beyond loopback the token guards every name the machine is reached by
        self.hosts = {f"{h}:{port}" for h in names} if is_loopback(host) else _AnyHost()
        self._open: dict[str, int] = {}  # connections open per client address
        self._open_lock = threading.Lock()
        self._declared = 0  # body bytes declared by the requests being read
        self._arrivals: dict[int, threading.Timer] = {}  # id(socket) -> the timer that closes it if it dawdles

    def process_request(self, request, client_address):
        who = peer_of(client_address[0])
        with self._open_lock:
            total = sum(self._open.values())
            full = total >= MAX_CONNECTIONS or self._open.get(who, 0) >= MAX_PER_ADDRESS
            if not full:
                self._open[who] = self._open.get(who, 0) + 1
        if full:  # told at once, before a thread is started or anything is read
            try:
                body = json.dumps({"error": "too many connections; retry in a moment"}).encode()
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: application/json\r\nRetry-After: 1\r\n"
                                b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body)
            except OSError:
                pass
            self.shutdown_request(request)
            return
        timer = threading.Timer(ARRIVAL_S, _cut, (request,))
        timer.daemon = True
        self._arrivals[id(request)] = timer
        timer.start()
        try:
            super().process_request(request, client_address)
        except Exception:
            self._done(request, who)
            raise

    def arrived(self, request) -> None:
        """The request has arrived whole: its connection is no longer cut at ARRIVAL_S."""
        timer = self._arrivals.pop(id(request), None)
        if timer is not None:
            timer.cancel()

    def _done(self, request, who: str) -> None:
        self.arrived(request)
        with self._open_lock:
            self._open[who] -= 1
            if not self._open[who]:
                del self._open[who]

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._done(request, peer_of(client_address[0]))

    @contextmanager
    def declared(self, n: int):
        """Room for a body of n bytes among those being read (at most BODIES_IN_FLIGHT x max_body declared in
        all); BadRequest 503 when there is none."""
        with self._open_lock:
            if self._declared + n > BODIES_IN_FLIGHT * self.max_body:
                raise BadRequest("busy: too many request bodies are arriving; retry in a moment", 503)
            self._declared += n
        try:
            yield
        finally:
            with self._open_lock:
                self._declared -= n


def _cut(sock) -> None:
    """Close a connection whose request did not arrive in time (a slow or silent client)."""
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    timeout = ARRIVAL_S
    protocol_version = "HTTP/1.0"  # one request per connection: each connection's arrival is timed once
    server_version = "apose-serve"
    sys_version = ""
    error_content_type = "application/json"
    error_message_format = '{"error": "%(code)d %(message)s: %(explain)s"}'  # http.server's own errors, as JSON

    def log_message(self, fmt, *args):  # one line per request on the service's log, not stderr noise
        log.info("%s %s", self.address_string(), fmt % args)

    def _reply(self, status: int, doc: dict, headers: dict | None = None) -> None:
        data = json.dumps(doc).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(data)

    def _unauthorised(self):
        """(status, doc) unless the request comes from a robot program: no web page (a request with an Origin
        header: browsers send one on every cross-site POST and fetch), only this service's own address in
        Host (a page that rebinds its own name to 127.0.0.1 sends that name), and the token where one is set.
        A header these rules read may appear once."""
        for name in ("Host", "Origin", "Authorization", "Content-Type", "Content-Length", "Transfer-Encoding"):
            if len(self.headers.get_all(name) or ()) > 1:
                return 400, {"error": f"{name} is given twice; send it once"}
        if self.headers.get("Origin") is not None:
            return 403, {"error": "a request from a web page (Origin header) is refused: the service answers programs, "
                                  "not pages"}
        host = (self.headers.get("Host") or "").strip().lower()
        if host not in self.server.hosts:
            return 403, {"error": f"Host {host[:60]!r} is not this service's address; call it by "
                                  f"{sorted(self.server.hosts)[0]}"}
        token = self.server.token
        if token is not None and not hmac.compare_digest((self.headers.get("Authorization") or "").encode(),
                                                         f"Bearer {token}".encode()):
            return 401, {"error": "missing or wrong token: send the header 'Authorization: Bearer TOKEN' with the token "
                                  "`apose serve` printed"}
        return None

    def do_GET(self):
        self.server.arrived(self.request)
        why = self._unauthorised()
        if why is not None:
            return self._reply(*why)
        if self.path.split("?")[0] == "/health":
            return self._reply(200, self.server.service.health())
        self._reply(404, {"error": f"{self.path[:80]}: not found; GET /health or POST /estimate"})

    def _length(self) -> int | None:
        length = (self.headers.get("Content-Length") or "").strip()
        return int(length) if length.isascii() and length.isdigit() and len(length) <= 12 else None

    def do_POST(self):
        n = self._length()
        # a refused request's body is read past (the client sends it whole before it reads the answer), in
        # chunks and only up to max_body; the connection then closes
        refused = self._refusal(n)
        if refused is not None:
            self.server.arrived(self.request)
            if n is not None and n <= self.server.max_body and refused[0] != 400:
                self._drain(n)
            return self._reply(*refused)
        t0 = time.perf_counter()
        try:
            with self.server.declared(n):
                body = self.rfile.read(n)
            self.server.arrived(self.request)
            if len(body) != n:
                return self._reply(400, {"error": f"the body ended after {len(body)} of {n} bytes"})
            with self.server.service.slot():
                doc = self.server.service.estimate(body, npz=self._content_type() == NPZ_TYPE)
            doc.setdefault("timings_s", {})["service"] = round(time.perf_counter() - t0, 4)
            self._reply(200, doc)
        except BadRequest as e:
            self._reply(e.status, {"error": str(e)}, {"Retry-After": "1"} if e.status == 503 else None)
        except AposeError as e:
            self._reply(400, {"error": str(e)})
        except (TimeoutError, ConnectionError, OSError):
            self.close_connection = True
        except Exception as e:  # noqa: BLE001 - the service outlives any one request
            log.exception("POST /estimate failed")
            self._reply(500, {"error": f"internal error ({type(e).__name__}); the service goes on. Please report it "
                                       "with the request"})

    def _refusal(self, n: int | None):
        """(status, doc) when the request is refused before its body is read, else None."""
        why = self._unauthorised()
        if why is not None:
            return why
        if self.path.split("?")[0] != "/estimate":
            return 404, {"error": f"{self.path[:80]}: not found; POST /estimate"}
        if self.headers.get("Transfer-Encoding") is not None:
            return 400, {"error": "Transfer-Encoding is not taken (a body with its Content-Length only)"}
        if n is None:
            return 411, {"error": "Content-Length: missing or not a number; send the body with its length"}
        if n > self.server.max_body:
            return 413, {"error": f"the body is {n} bytes, over the {self.server.max_body} the service takes; send PNG "
                                  "images of the frame (not raw arrays), or crop it"}
        ctype = self._content_type()
        if ctype not in ("application/json", NPZ_TYPE):  # a browser's form or text/plain post (no CORS preflight)
            return 415, {"error": f"Content-Type {ctype[:40] or 'missing'}: send application/json (or {NPZ_TYPE}: "
                                  "numpy.savez's bytes)"}
        return None

    def _content_type(self) -> str:
        return self.headers.get("Content-Type", "").split(";")[0].strip().lower()

    def _drain(self, n: int) -> None:
        try:
            while n > 0:
                chunk = self.rfile.read(min(n, 2 ** 20))
                if not chunk:
                    break
                n -= len(chunk)
        except OSError:
            self.close_connection = True

    def do_PUT(self):
        self.server.arrived(self.request)
        self._reply(405, {"error": "method not allowed; GET /health or POST /estimate"})

    do_DELETE = do_PATCH = do_PUT


M_ARENA_MAX = -8  # glibc's mallopt parameter


def fewer_malloc_arenas(n: int = 2) -> bool:
    """At most `n` glibc malloc arenas in this process. glibc gives each new thread an arena of its own (up
    to 8 per core) and keeps what was freed in it: with a thread per connection the service grew 63 MB
    over its first 1,000 requests, none of it leaked (benchmarks/serve.py; with two arenas, +2 MB over 120
    requests where the default grew 22 MB). False where the C library is not glibc."""
    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(M_ARENA_MAX, n))
    except (OSError, AttributeError):
        return False


def make_server(service: EstimationService, host: str = "127.0.0.1", port: int = 8765, token: str | None = None,
                max_body: int = MAX_BODY) -> _Server:
    """The HTTP server of a service (not yet serving: call serve_forever). Beyond loopback a token is required
    (one is made when none is given)."""
    if token is None and not is_loopback(host):
        token = secrets.token_urlsafe(18)
    fewer_malloc_arenas()
    return _Server((host, port), service, token, max_body)
