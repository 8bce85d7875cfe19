"""Recorded cameras: ROS 2 recordings in MCAP (`ros2 bag record -s mcap`, the default storage since Iron; a
RealSense's `/camera/color/image_raw`, `/camera/aligned_depth_to_color/image_raw` and `camera_info`), read
with the MCAP project's own libraries (`mcap`, `mcap-ros2-support`: the schemas travel in the file, so no ROS
install is needed), as a sequence of `Frame`s; and the writer that makes such a recording from frames
(`apose export-mcap`, and the tests' recordings).

What a recording must hold: a colour `sensor_msgs/msg/Image` topic (rgb8, bgr8, rgba8 or bgra8), a depth one
registered to it (16UC1 / mono16 in millimetres, or 32FC1 in metres), and a `sensor_msgs/msg/CameraInfo` (its
`k` is the colour camera's K). Optional: a `geometry_msgs/msg/PoseStamped` topic with the camera's pose in the
world (`T_world_camera`, e.g. from the robot's kinematics; default topic `/apose/camera_pose`); without it
every frame's T_world_camera is the identity (the world is the camera's frame: a tracker then expects the
base where it was in the camera's frame). Frames are the colour images in time order, each paired with
the depth image nearest in time (within `max_gap_s`); a colour image without one is left out and counted.

A rosbag2 folder (metadata.yaml beside the .mcap) is read through its .mcap file. A .db3 (sqlite3) bag is
refused with the fix: `ros2 bag convert` it to MCAP, or record with `-s mcap`.
"""

from __future__ import annotations

import bisect
import contextlib
import os
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from apose_studio.assembly.fileio import current_umask
from apose_studio.data.dataset import DatasetError, Frame
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.robot.ros2 import HEADER_DEF, POSE_STAMPED, TIME_DEF, msgdef
from apose_studio.safeio import open_regular

IMAGE = msgdef("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\n"
               "uint8[] data", HEADER_DEF, TIME_DEF)
CAMERA_INFO = msgdef("std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
                     "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
                     "sensor_msgs/RegionOfInterest roi", HEADER_DEF, TIME_DEF,
                     "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\n"
                     "bool do_rectify")
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
DEPTH_ENCODINGS = {"16UC1": 0.001, "mono16": 0.001, "32FC1": 1.0}  # -> metres per unit
POSE_TOPIC = "/apose/camera_pose"
MAX_SIDE = 8192  # pixels a side of a recorded image (a depth camera's are at most a few thousand)
MAX_CHUNK_BYTES = 512 * 2 ** 20  # an MCAP chunk's uncompressed size (a 4K RGB frame is 25 MB)
TOPICS = {"color": "/camera/color/image_raw", "depth": "/camera/aligned_depth_to_color/image_raw",
          "info": "/camera/color/camera_info", "pose": POSE_TOPIC}  # what `write_recording` writes (a RealSense's names)


def mcap_file(path: str | Path) -> Path:
    """The .mcap file of `path`: the file itself, or the one .mcap in a rosbag2 folder."""
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*.mcap"))
        if not found:
            db3 = sorted(path.glob("*.db3"))
            if db3:
                raise DatasetError(f"{path}: a sqlite3 rosbag2 ({db3[0].name}); convert it to MCAP (`ros2 bag convert`) "
                                   "or record with `ros2 bag record -s mcap`")
            raise DatasetError(f"{path}: no .mcap file in this folder")
        if len(found) > 1:
            raise DatasetError(f"{path}: {len(found)} .mcap files; give the one to read")
        return found[0]
    if not path.exists():
        raise DatasetError(f"{path}: no such file")
    if not path.is_file():
        raise DatasetError(f"{path}: not a regular file (a FIFO or a device?); give the recording's .mcap file")
    return path


def open_mcap(path: Path):
    """The recording's file opened for reading through safeio.open_regular: a regular file (a FIFO or device is
    refused without blocking), and inside the studio's workspace when reads are confined there (safeio
    .reads_within: checked on the file opened, so a link swapped in later or a rosbag2 folder's .mcap that
    leads outside is refused at every read)."""
    fd, _ = open_regular(path, "a ROS 2 recording (.mcap)")
    return os.fdopen(fd, "rb")


def check_chunks(summary, file: Path) -> None:
    """Refuse a recording whose chunks would decompress to more than MAX_CHUNK_BYTES each (a few kB of zstd can
    claim gigabytes: the reader would allocate them before any image is checked)."""
    for ci in (summary.chunk_indexes if summary is not None else []):
        if ci.uncompressed_size > MAX_CHUNK_BYTES:
            raise DatasetError(f"{file}: a chunk of {ci.uncompressed_size / 2 ** 20:.0f} MB uncompressed; at most "
                               f"{MAX_CHUNK_BYTES // 2 ** 20} MB are read (a camera's frame is a few MB; record with a "
                               "smaller chunk size)")


def is_recording(path: str | Path) -> bool:
    """Whether `path` is an MCAP file or a rosbag2 folder (what `open_recording` reads)."""
    path = Path(path)
    return (path.suffix == ".mcap" and not path.is_dir()) or (path.is_dir() and (path / "metadata.yaml").is_file())


@dataclass
class Recording:
    """An MCAP recording as frames: `len(rec)`, `rec.frame(i)` (0-based, colour images in time order)."""

    path: Path
    topics: dict[str, str | None]  # color, depth, info, pose
    camera: CameraIntrinsics
    color_times: list[int]  # log times (ns) of the frames' colour images
    depth_times: list[int]  # ... and of their depth images
    unpaired: int = 0  # colour images left out: no depth image within max_gap_s
    _poses: tuple[list[int], list[np.ndarray]] = field(default_factory=lambda: ([], []))

    def __len__(self) -> int:
        return len(self.color_times)

    @property
    def seconds(self) -> float:
        return (self.color_times[-1] - self.color_times[0]) / 1e9 if len(self) > 1 else 0.0

    def frame(self, i: int) -> Frame:
        if not 0 <= i < len(self):
            raise DatasetError(f"{self.path}: frame {i} does not exist; the recording has frames 0..{len(self) - 1}")
        return self.make_frame(i, self._image(self.topics["color"], self.color_times[i]),
                               self._image(self.topics["depth"], self.depth_times[i]))

    def make_frame(self, i: int, rgb: np.ndarray, depth: np.ndarray) -> Frame:
        """Frame i from its colour and depth images (checked to be one size: the depth aligned to colour)."""
        if depth.shape != rgb.shape[:2]:
            raise DatasetError(f"{self.path}: frame {i}: depth is {depth.shape[1]}x{depth.shape[0]} but colour is "
                               f"{rgb.shape[1]}x{rgb.shape[0]}; record the depth aligned to colour")
        return Frame(rgb=rgb, depth=depth, camera=self.camera, T_world_camera=self._pose_at(self.color_times[i]),
                     im_id=i, source=f"{self.path}#{i}")

    def player(self) -> "RecordingPlayer":
        """A reader for frames asked for in increasing order (a player's): one pass over the file instead of
        a search per image (22 -> a few ms a frame on a 20 s, 30 Hz recording)."""
        return RecordingPlayer(self)

    def _image(self, topic: str, t: int) -> np.ndarray:
        with open_mcap(self.path) as f:
            for _, _, _, msg in _reader(f).iter_decoded_messages(topics=[topic], start_time=t, end_time=t + 1):
                return image_array(msg, f"{self.path}: {topic}")
        raise DatasetError(f"{self.path}: {topic} has no message at {t} ns (a damaged file?)")

    def _pose_at(self, t: int) -> np.ndarray:
        times, poses = self._poses
        if not times:
            return np.eye(4)
        k = bisect.bisect_left(times, t)
        k = min(range(max(k - 1, 0), min(k + 1, len(times))), key=lambda j: abs(times[j] - t))
        return poses[k]


class RecordingPlayer:
    """`frame(i)` of a Recording for i increasing (a jump back starts a new pass); `close()` when done."""

    def __init__(self, rec: Recording):
        self.rec = rec
        self._file = None
        self._it = None
        self._at = -1  # log time of the last message read in this pass
        self._kept: dict[tuple[str, int], np.ndarray] = {}  # images read but not yet used (a depth two frames share)

    def frame(self, i: int) -> Frame:
        rec = self.rec
        if not 0 <= i < len(rec):
            return rec.frame(i)  # its refusal
        want = {(rec.topics["color"], rec.color_times[i]), (rec.topics["depth"], rec.depth_times[i])}
        if min(t for _, t in want) <= self._at and not want <= self._kept.keys():
            self.close()  # behind this pass: a new one
        if self._it is None:
            self._file = open_mcap(rec.path)
            self._it = iter(_reader(self._file).iter_decoded_messages(
                topics=[rec.topics["color"], rec.topics["depth"]], start_time=min(t for _, t in want),
                log_time_order=True))
            self._at, self._kept = -1, {}
        while not want <= self._kept.keys():
            try:
                _, channel, message, msg = next(self._it)
            except StopIteration:
                raise DatasetError(f"{rec.path}: frame {i}'s images are missing (a damaged file?)") from None
            self._at = message.log_time
            if (channel.topic, message.log_time) in want:
                self._kept[(channel.topic, message.log_time)] = image_array(msg, f"{rec.path}: {channel.topic}")
        rgb, depth = self._kept[(rec.topics["color"], rec.color_times[i])], self._kept[(rec.topics["depth"], rec.depth_times[i])]
        self._kept = {k: v for k, v in self._kept.items() if k[1] >= min(t for _, t in want)}
        return rec.make_frame(i, rgb, depth)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        self._file = self._it = None


def _reader(f):
    from mcap.reader import make_reader  # loaded where it is used
    from mcap_ros2.decoder import DecoderFactory

    return make_reader(f, decoder_factories=[DecoderFactory()])


def image_array(msg, what: str) -> np.ndarray:
    """A sensor_msgs/Image as an array: colour as (H, W, 3) uint8 RGB, depth as (H, W) float32 metres (0: none)."""
    h, w, enc = int(msg.height), int(msg.width), str(msg.encoding)
    if not (0 < h <= MAX_SIDE and 0 < w <= MAX_SIDE):
        raise DatasetError(f"{what}: a {w}x{h} image; expected 1 to {MAX_SIDE} pixels a side")
    data = bytes(msg.data)
    if enc in COLOUR_ENCODINGS:
        c = 4 if enc.endswith("a8") else 3
        if len(data) != h * int(msg.step) or not w * c <= int(msg.step) <= w * c + 64:
            raise DatasetError(f"{what}: a {w}x{h} {enc} image with {len(data)} bytes and rows of {msg.step}; expected "
                               f"{h} rows of at least {w * c} bytes: a damaged message (re-record, or `mcap recover` it)")
        a = np.frombuffer(data, np.uint8).reshape(h, int(msg.step))[:, :w * c].reshape(h, w, c)[..., :3]
        return np.ascontiguousarray(a[..., ::-1] if enc.startswith("bgr") else a)
    if enc in DEPTH_ENCODINGS:
        dtype = np.dtype(">u2" if msg.is_bigendian else "<u2") if enc != "32FC1" else np.dtype(">f4" if msg.is_bigendian else "<f4")
        if len(data) != h * int(msg.step) or not w * dtype.itemsize <= int(msg.step) <= w * dtype.itemsize + 64:
            raise DatasetError(f"{what}: a {w}x{h} {enc} image with {len(data)} bytes and rows of {msg.step}; expected "
                               f"{h} rows of at least {w * dtype.itemsize} bytes: a damaged message (re-record, or "
                               "`mcap recover` it)")
        rows = np.frombuffer(data, np.uint8).reshape(h, int(msg.step))[:, :w * dtype.itemsize]
        d = rows.copy().view(dtype).reshape(h, w).astype(np.float32) * np.float32(DEPTH_ENCODINGS[enc])
        d[~np.isfinite(d) | (d < 0)] = 0.0
        return d
    raise DatasetError(f"{what}: image encoding {enc!r}; colour must be one of {', '.join(COLOUR_ENCODINGS)}, depth one "
                       f"of {', '.join(DEPTH_ENCODINGS)}")


def open_recording(path: str | Path, topics: dict[str, str | None] | None = None, max_gap_s: float = 0.02) -> Recording:
    """The frames of an MCAP recording (see the module docstring). `topics`: color, depth, info, pose to use
    (any left out or None is found: the Image topics by their first message's encoding, CameraInfo by the
    colour topic's namespace)."""
    file = mcap_file(path)
    chosen = dict(topics or {})
    with open_mcap(file) as f:
        try:
            reader = _reader(f)
            summary = reader.get_summary()
        except Exception as e:  # not an MCAP file, or cut short
            raise DatasetError(f"{file}: not a readable MCAP file ({type(e).__name__}: {str(e)[:120]}); a recording cut "
                               "short while it was written can be mended with `mcap recover`") from None
        if summary is None:
            raise DatasetError(f"{file}: an MCAP file without a summary (cut short while recording?); "
                               "re-index it with `mcap recover`")
        check_chunks(summary, file)
        by_type: dict[str, list[str]] = {}
        for ch in summary.channels.values():
            schema = summary.schemas.get(ch.schema_id)
            by_type.setdefault(schema.name if schema else "", []).append(ch.topic)
        images = sorted(by_type.get("sensor_msgs/msg/Image", []))
        kinds = {}
        for topic in images:
            for _, _, _, msg in reader.iter_decoded_messages(topics=[topic]):
                kinds[topic] = "color" if msg.encoding in COLOUR_ENCODINGS else "depth" if msg.encoding in DEPTH_ENCODINGS \
                    else msg.encoding
                break
        for kind in ("color", "depth"):
            if not chosen.get(kind):
                found = [t for t in images if kinds.get(t) == kind]
                if not found:
                    raise DatasetError(f"{file}: no {kind} image topic (sensor_msgs/msg/Image with "
                                       f"{'an rgb8/bgr8' if kind == 'color' else 'a 16UC1/32FC1'} encoding); image topics: "
                                       f"{', '.join(f'{t} ({kinds.get(t)})' for t in images) or 'none'}")
                chosen[kind] = found[0]
            elif chosen[kind] not in images:
                raise DatasetError(f"{file}: no image topic {chosen[kind]}; image topics: {', '.join(images) or 'none'}")
        infos = sorted(by_type.get("sensor_msgs/msg/CameraInfo", []))
        if not chosen.get("info"):
            ns = chosen["color"].rsplit("/", 1)[0]
            near = [t for t in infos if t.startswith(ns + "/")]
            if not (near or infos):
                raise DatasetError(f"{file}: no sensor_msgs/msg/CameraInfo topic: the camera's K is needed")
            chosen["info"] = (near or infos)[0]
        if "pose" not in chosen:
            chosen["pose"] = POSE_TOPIC if POSE_TOPIC in by_type.get("geometry_msgs/msg/PoseStamped", []) else None
        times: dict[str, list[int]] = {chosen["color"]: [], chosen["depth"]: []}
        camera, pose_times, poses = None, [], []
        wanted = [t for t in (chosen["color"], chosen["depth"], chosen["info"], chosen["pose"]) if t]
        for _, channel, message in reader.iter_messages(topics=wanted, log_time_order=True):
            if channel.topic in times:
                times[channel.topic].append(message.log_time)
        for _, channel, message, msg in reader.iter_decoded_messages(topics=[t for t in (chosen["info"], chosen["pose"])
                                                                             if t], log_time_order=True):
            if channel.topic == chosen["info"] and camera is None:
                k = [float(v) for v in msg.k]
                camera = CameraIntrinsics(int(msg.width), int(msg.height), k[0], k[4], k[2], k[5])
            elif channel.topic == chosen["pose"]:
                p, q = msg.pose.position, msg.pose.orientation
                pose_times.append(message.log_time)
                poses.append(se3.make_T(se3.quat_wxyz_to_matrix(np.array([q.w, q.x, q.y, q.z])), np.array([p.x, p.y, p.z])))
    if camera is None or not all(np.isfinite([camera.fx, camera.fy, camera.cx, camera.cy])) or camera.fx <= 0 \
            or camera.fy <= 0 or not (0 < camera.width <= MAX_SIDE and 0 < camera.height <= MAX_SIDE):
        raise DatasetError(f"{file}: {chosen['info']} holds no usable camera (K = "
                           f"{[camera.fx, camera.fy, camera.cx, camera.cy] if camera else 'none'}, size "
                           f"{f'{camera.width}x{camera.height}' if camera else 'none'}); record the colour camera_info")
    colour, depth = times[chosen["color"]], sorted(times[chosen["depth"]])
    if not colour or not depth:
        raise DatasetError(f"{file}: {chosen['color'] if not colour else chosen['depth']} has no messages")
    gap = int(max_gap_s * 1e9)
    pairs = []
    for t in colour:
        k = bisect.bisect_left(depth, t)
        near = min((depth[j] for j in (k - 1, k) if 0 <= j < len(depth)), key=lambda d: abs(d - t))
        if abs(near - t) <= gap:
            pairs.append((t, near))
    if not pairs:
        raise DatasetError(f"{file}: no colour image has a depth image within {max_gap_s * 1000:.0f} ms")
    return Recording(file, chosen, camera, [a for a, _ in pairs], [b for _, b in pairs], len(colour) - len(pairs),
                     (pose_times, poses))


def write_recording(path: str | Path, frames: Iterable[Frame], rate_hz: float = 30.0, start_ns: int = 10 ** 18,
                    topics: dict[str, str] | None = None) -> Path:
    """Frames as a ROS 2 recording in MCAP (what a RealSense node publishes: colour rgb8, depth aligned to it in
    16UC1 millimetres, the colour CameraInfo; and each frame's T_world_camera as a PoseStamped), `rate_hz`
    apart from `start_ns`; streamed into a file beside `path` (a minute at 30 Hz is ~3 GB: never held in memory),
    then renamed onto it, so `path` is whole or as it was."""
    from mcap_ros2.writer import Writer  # loaded where it is used

    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            _write_frames(Writer(f), frames, rate_hz, start_ns, {**TOPICS, **(topics or {})})
            f.flush()
            os.fchmod(f.fileno(), 0o666 & ~current_umask())
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def _write_frames(w, frames: Iterable[Frame], rate_hz: float, start_ns: int, t: dict[str, str]) -> None:
    image, info, pose = (w.register_msgdef(n, d) for n, d in (("sensor_msgs/msg/Image", IMAGE),
                                                              ("sensor_msgs/msg/CameraInfo", CAMERA_INFO),
                                                              ("geometry_msgs/msg/PoseStamped", POSE_STAMPED)))
    for k, fr in enumerate(frames):
        stamp = start_ns + int(round(k * 1e9 / rate_hz))
        head = {"stamp": {"sec": stamp // 10 ** 9, "nanosec": stamp % 10 ** 9}, "frame_id": "camera_color_optical_frame"}
        h, wd = fr.depth.shape
        mm = np.clip(np.round(np.nan_to_num(fr.depth) * 1000.0), 0, 65535).astype("<u2")
        cam = fr.camera
        w.write_message(t["color"], image, {"header": head, "height": h, "width": wd, "encoding": "rgb8", "is_bigendian": 0,
                                            "step": wd * 3, "data": np.ascontiguousarray(fr.rgb, np.uint8).tobytes()},
                        log_time=stamp, publish_time=stamp)
        w.write_message(t["depth"], image, {"header": head, "height": h, "width": wd, "encoding": "16UC1",
                                            "is_bigendian": 0, "step": wd * 2, "data": mm.tobytes()},
                        log_time=stamp, publish_time=stamp)
        w.write_message(t["info"], info, {"header": head, "height": h, "width": wd, "distortion_model": "plumb_bob",
                                          "d": [0.0] * 5, "k": [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0],
                                          "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                                          "p": [cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
                                          "binning_x": 0, "binning_y": 0,
                                          "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}},
                        log_time=stamp, publish_time=stamp)
        T = np.asarray(fr.T_world_camera, float)
        wq = se3.matrix_to_quat_wxyz(T[:3, :3])
        w.write_message(t["pose"], pose, {"header": {**head, "frame_id": "world"}, "pose": {
            "position": dict(zip("xyz", (float(v) for v in T[:3, 3]))),
            "orientation": {"x": float(wq[1]), "y": float(wq[2]), "z": float(wq[3]), "w": float(wq[0])}}},
            log_time=stamp, publish_time=stamp)
    w.finish()
