"""Live cameras: an Intel RealSense through Intel's `pyrealsense2` (an optional extra:
`pip install 'apose_studio[realsense]'`), as a stream of `Frame`s.

Each frame is the newest colour + depth pair the SDK matched (`rs.syncer` or the pipeline's), the depth
aligned to the colour camera by the SDK's own `rs.align`, in metres by the depth sensor's depth unit
(`RS2_OPTION_DEPTH_UNITS`: 1 mm on D400 by default); the intrinsics are the colour stream's, read from
the device. The world is the camera's frame (T_world_camera the identity) unless the caller sets the
camera's pose (`LiveCamera.T_world_camera`, e.g. from the robot's kinematics).

`software_camera(frames)` builds the same stream from frames in memory through the SDK's `software_device`
(a depth and a colour sensor with the frames' intrinsics, the depth in the device's 16-bit units): the
tests and the benchmark drive the live path, syncer, alignment and all, without hardware.

A colour stream with lens distortion (non-zero Brown-Conrady coefficients: some L500 and D405 modes) is
used as a pinhole and said in `LiveCamera.notes`: the estimator's ray casts are pinhole."""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from apose_studio.data.dataset import DatasetError, Frame
from apose_studio.errors import AposeError
from apose_studio.geometry.camera import CameraIntrinsics

LIVE = re.compile(r"^realsense(?::(.*))?$", re.IGNORECASE | re.DOTALL)  # a live camera, named where a path could go
SERIAL = re.compile(r"^[A-Za-z0-9._-]{1,64}$")  # a RealSense serial number as rs-enumerate-devices lists it
INSTALL = "pip install 'apose_studio[realsense]' (Intel's pyrealsense2 wheels: Linux x86_64/aarch64, Windows, macOS)"
DEFAULT_SIZE = (640, 480)
DEFAULT_FPS = 30
SOFTWARE_DEPTH_UNIT = 0.001  # metres per depth unit of the software camera (a D400's default)


def live_serial(text: str) -> tuple[bool, str | None]:
    """(whether `text` names a live RealSense, its serial or None): `realsense` or `realsense:SERIAL` (any case,
    spaces around ignored). A serial that is not letters, digits, '.', '_' or '-' (at most 64) is refused by
    name, shown escaped."""
    m = LIVE.match(text.strip())
    if m is None:
        return False, None
    serial = m.group(1)
    if serial is None:
        return True, None
    if not SERIAL.match(serial):
        raise AposeError(f"realsense:{ascii(serial)[1:-1][:40]}: not a serial number (letters and digits, as "
                         "`rs-enumerate-devices` lists them; `realsense` alone opens the first camera; a folder named "
                         "realsense opens as ./realsense)")
    return True, serial


def rs_module():
    """pyrealsense2, imported when a live camera is first asked for (it is an optional extra)."""
    try:
        import pyrealsense2 as rs
    except ImportError:
        raise AposeError(f"a RealSense camera needs Intel's pyrealsense2, which is not installed: {INSTALL}") from None
    return rs


def intrinsics_of(profile) -> tuple[CameraIntrinsics, tuple[float, ...]]:
    """A video stream profile's pinhole intrinsics and its distortion coefficients."""
    i = profile.as_video_stream_profile().get_intrinsics()
    return CameraIntrinsics(i.width, i.height, i.fx, i.fy, i.ppx, i.ppy), tuple(float(c) for c in i.coeffs)


@dataclass
class LiveCamera:
    """Frames from a RealSense (or the SDK's software device): `next_frame()` waits for the next one; its im_id
    is the device's colour frame number (gaps: frames the SDK dropped or nobody read in time).

    `T_world_camera`: the camera's pose given to every frame (identity: the world is the camera's frame)."""

    name: str
    camera: CameraIntrinsics
    depth_unit_m: float  # metres per 16-bit depth unit
    _wait: object  # () -> a frameset (blocking, timeout in ms)
    _close: object  # () -> None
    _align: object
    notes: list[str] = field(default_factory=list)
    T_world_camera: np.ndarray = field(default_factory=lambda: np.eye(4))
    last: Frame | None = None
    closed: bool = False
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def next_frame(self, timeout_s: float = 5.0) -> Frame:
        """The next colour + aligned depth pair as a Frame; waits up to timeout_s."""
        t_end = time.monotonic() + timeout_s
        with self._lock:
            while True:
                if self.closed:
                    raise AposeError(f"{self.name}: closed (other data was opened); open it again to stream")
                left = t_end - time.monotonic()
                try:
                    if left <= 0:
                        raise RuntimeError("timed out")
                    fs = self._wait(max(int(left * 1000), 1))
                except RuntimeError:  # the SDK's "Frame didn't arrive within N"
                    raise AposeError(f"{self.name}: no colour and depth frame pair came in {timeout_s:g} s; is the "
                                     "camera streaming (a USB 3 port, no other program holding it)?") from None
                frame = self._to_frame(fs)
                if frame is not None:
                    self.last = frame
                    return frame

    def _to_frame(self, fs) -> Frame | None:
        if fs.size() < 2:  # the syncer hands over a lone frame while it matches
            return None
        aligned = self._align.process(fs.as_frameset())
        c, d = aligned.get_color_frame(), aligned.get_depth_frame()
        if not c or not d:
            return None
        rgb = np.array(c.get_data(), copy=True)
        raw = np.asanyarray(d.get_data())
        if rgb.shape[:2] != (self.camera.height, self.camera.width) or raw.shape != rgb.shape[:2]:
            raise DatasetError(f"{self.name}: a {rgb.shape[1]}x{rgb.shape[0]} colour frame with a {raw.shape[1]}x"
                               f"{raw.shape[0]} depth frame; the stream's intrinsics are {self.camera.width}x"
                               f"{self.camera.height}")
        depth = raw.astype(np.float32) * np.float32(self.depth_unit_m)
        k = int(c.get_frame_number())
        return Frame(rgb=rgb, depth=depth, camera=self.camera, T_world_camera=self.T_world_camera.copy(), im_id=k,
                     source=f"{self.name}#{k}")

    def close(self) -> None:
        """Stop streaming (once); a next_frame after it is refused."""
        if not self.closed:
            self.closed = True
            self._close()


def open_realsense(serial: str | None = None, size: tuple[int, int] = DEFAULT_SIZE, fps: int = DEFAULT_FPS) -> LiveCamera:
    """The RealSense with `serial` (or the first one found), streaming colour (rgb8) and depth (z16) at
    `size` and `fps`, depth aligned to colour. Refused with the reason when none is plugged in or the mode is
    not offered."""
    rs = rs_module()
    devices = list(rs.context().query_devices())
    if not devices:
        raise AposeError("no RealSense camera found: plug one into a USB 3 port (`rs-enumerate-devices` lists what the "
                         "SDK sees; on Linux, Intel's udev rules let a user open it)")
    serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
    if serial is not None and serial not in serials:
        raise AposeError(f"no RealSense with serial {serial}; connected: {', '.join(serials)}")
    pipe, cfg = rs.pipeline(), rs.config()
    cfg.enable_device(serial or serials[0])
    w, h = size
    cfg.enable_stream(rs.stream.depth, w, h, rs.format.z16, fps)
    cfg.enable_stream(rs.stream.color, w, h, rs.format.rgb8, fps)
    try:
        profile = pipe.start(cfg)
    except RuntimeError as e:
        raise AposeError(f"RealSense {serial or serials[0]}: {w}x{h} at {fps} fps could not start ({e}); try "
                         "another size or rate (`rs-enumerate-devices -c` lists the modes)") from None
    dev = profile.get_device()
    cam, coeffs = intrinsics_of(profile.get_stream(rs.stream.color))
    name = f"RealSense {dev.get_info(rs.camera_info.name)} {dev.get_info(rs.camera_info.serial_number)}"
    unit = float(dev.first_depth_sensor().get_depth_scale())
    return _live(name, cam, coeffs, unit, pipe.wait_for_frames, pipe.stop, rs.align(rs.stream.color))


def _live(name, cam, coeffs, unit, wait, close, align) -> LiveCamera:
    notes = []
    if any(abs(c) > 1e-6 for c in coeffs):
        notes.append(f"the colour stream's lens distortion ({', '.join(f'{c:.3g}' for c in coeffs)}) is ignored: the "
                     "estimator uses it as a pinhole")
    if not unit > 0:
        raise DatasetError(f"{name}: the depth unit is {unit}; expected metres per unit, e.g. 0.001")
    return LiveCamera(name=name, camera=cam, depth_unit_m=unit, _wait=wait, _close=close, _align=align, notes=notes)


def software_camera(frames: Sequence[Frame], fps: float = DEFAULT_FPS, loop: bool = False,
                    name: str = "software RealSense") -> LiveCamera:
    """A LiveCamera fed by the SDK's software_device: `frames` (one camera, depth and colour registered)
    injected as a depth (z16 in SOFTWARE_DEPTH_UNIT) and a colour (rgb8) sensor at `fps` by a feeder thread,
    matched by the SDK's syncer and aligned by rs.align, as a device's are. `loop`: start again at the end."""
    rs = rs_module()
    if not frames:
        raise DatasetError("a software camera needs at least one frame")
    cam = frames[0].camera
    w, h = cam.width, cam.height
    dev = rs.software_device()
    depth_s, colour_s = dev.add_sensor("Depth"), dev.add_sensor("Color")

    def stream(kind, uid, fmt, bpp):
        i = rs.intrinsics()
        i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = w, h, cam.fx, cam.fy, cam.cx, cam.cy
        i.model, i.coeffs = rs.distortion.none, [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp, vs.fmt, vs.intrinsics = \
            kind, 0, uid, w, h, int(round(fps)), bpp, fmt, i
        return vs

    depth_p = depth_s.add_video_stream(stream(rs.stream.depth, 0, rs.format.z16, 2))
    colour_p = colour_s.add_video_stream(stream(rs.stream.color, 1, rs.format.rgb8, 3))
    depth_s.add_read_only_option(rs.option.depth_units, SOFTWARE_DEPTH_UNIT)
    ex = rs.extrinsics()
    ex.rotation, ex.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    depth_p.register_extrinsics_to(colour_p, ex)
    dev.create_matcher(rs.matchers.default)
    sync = rs.syncer()
    depth_s.open(depth_p)
    colour_s.open(colour_p)
    depth_s.start(sync)
    colour_s.start(sync)
    stop = threading.Event()
    keep: list = []  # the SDK reads the pixels after on_video_frame returns: the arrays live while it streams

    def feed():
        k, t0 = -1, time.monotonic()  # -1: a warm-up pair, which the syncer hands over unmatched (never a Frame)
        while not stop.is_set():
            fr = frames[max(k, 0) % len(frames)]
            if (fr.camera.width, fr.camera.height) != (w, h):
                return
            raw = np.clip(np.round(np.nan_to_num(fr.depth) / SOFTWARE_DEPTH_UNIT), 0, 65535).astype(np.uint16)
            rgb = np.ascontiguousarray(fr.rgb, np.uint8)
            keep[:] = keep[-8:] + [raw, rgb]
            for sensor, prof, arr, bpp in ((depth_s, depth_p, raw, 2), (colour_s, colour_p, rgb, 3)):
                f = rs.software_video_frame()
                f.pixels, f.stride, f.bpp = arr, w * bpp, bpp
                f.timestamp, f.domain = k * 1000.0 / fps, rs.timestamp_domain.hardware_clock
                f.frame_number = k  # the warm-up: -1
                f.profile = prof.as_video_stream_profile()
                sensor.on_video_frame(f)
            k += 1
            if k >= len(frames) and not loop:
                return
            stop.wait(max(t0 + (k + 1) / fps - time.monotonic(), 0.0))

    feeder = threading.Thread(target=feed, daemon=True, name="software RealSense")
    feeder.start()

    def close():
        stop.set()
        feeder.join(2.0)
        for s in (depth_s, colour_s):
            try:
                s.stop()
                s.close()
            except RuntimeError:
                pass

    return _live(name, cam, (0.0,) * 5, float(depth_s.get_option(rs.option.depth_units)), sync.wait_for_frames, close,
                 rs.align(rs.stream.color))
