"""Pick-and-place targets as ROS 2 messages in an MCAP file, without a ROS install (the `mcap` and
`mcap-ros2-support` libraries: the MCAP project's own, which `ros2 bag` and Foxglove read).

What the file holds (REP-103: metres, right-handed; the camera frame is an `*_optical_frame`):
- `/tf_static` (tf2_msgs/TFMessage): robot base -> camera, -> the base object (`apose_base`), -> each target
  (`apose_part_place`, `apose_gripper_place`, `apose_gripper_preplace`, `apose_part_pick`, `apose_gripper_pick`,
  `apose_gripper_lift`; the frame names take `--tf-prefix`);
- `/apose/place/gripper`, `/apose/place/preplace`, `/apose/place/part`, `/apose/pick/gripper`,
  `/apose/pick/lift`, `/apose/pick/part` (geometry_msgs/PoseStamped, in the robot frame);
- `/apose/place/approach` (geometry_msgs/PoseArray): the gripper's waypoints pre-place -> place; `/apose/pick/
  approach`: pre-pick (the lift pose) -> pick -> lift; `/apose/place/alternatives`: every other gripper target
  at the place (symmetries).
Quaternions in the messages are x, y, z, w (ROS's order).

Play it: `ros2 bag play targets.mcap` (ROS 2 Iron or newer reads MCAP; Humble with
`ros-humble-rosbag2-storage-mcap`, `-s mcap`), then `ros2 topic echo /apose/place/gripper`; or open it
in Foxglove (Open local file) and add a 3D panel.
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np

from apose_studio.assembly.fileio import atomic_write_bytes
from apose_studio.geometry import se3
from apose_studio.robot.targets import Targets

_SEP = "=" * 80
_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id"
_POINT = "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z"
_QUAT = "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w"
_VEC = "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z"
_POSE = "MSG: geometry_msgs/Pose\ngeometry_msgs/Point position\ngeometry_msgs/Quaternion orientation"


def msgdef(main: str, *deps: str) -> str:
    """A ROS 2 message definition as MCAP's ros2msg schema: the message's fields, then each type it uses."""
    return "\n".join([main] + [f"{_SEP}\n{d}" for d in deps])


HEADER_DEF, TIME_DEF = _HEADER, _TIME  # std_msgs/Header and builtin_interfaces/Time, for other messages' schemas


POSE_STAMPED = msgdef("std_msgs/Header header\ngeometry_msgs/Pose pose", _HEADER, _TIME, _POSE, _POINT, _QUAT)
POSE_ARRAY = msgdef("std_msgs/Header header\ngeometry_msgs/Pose[] poses", _HEADER, _TIME, _POSE, _POINT, _QUAT)
TF_MESSAGE = msgdef("geometry_msgs/TransformStamped[] transforms",
                     "MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\n"
                     "geometry_msgs/Transform transform", _HEADER, _TIME,
                     "MSG: geometry_msgs/Transform\ngeometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation",
                     _VEC, _QUAT)

TF_CHILDREN = {"T_robot_base": "apose_base", "T_robot_part": "apose_part_place",
               "T_robot_gripper_place": "apose_gripper_place", "T_robot_gripper_preplace": "apose_gripper_preplace",
               "T_robot_part_pick": "apose_part_pick", "T_robot_gripper_pick": "apose_gripper_pick",
               "T_robot_gripper_lift": "apose_gripper_lift"}
POSE_TOPICS = {"T_robot_gripper_place": "/apose/place/gripper", "T_robot_gripper_preplace": "/apose/place/preplace",
               "T_robot_part": "/apose/place/part", "T_robot_gripper_pick": "/apose/pick/gripper",
               "T_robot_gripper_lift": "/apose/pick/lift", "T_robot_part_pick": "/apose/pick/part"}


def _quat_xyzw(T: np.ndarray) -> dict:
    w, x, y, z = (float(v) for v in se3.matrix_to_quat_wxyz(np.asarray(T)[:3, :3]))
    return {"x": x, "y": y, "z": z, "w": w}


def _pose(T: np.ndarray) -> dict:
    p = np.asarray(T)[:3, 3]
    return {"position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}, "orientation": _quat_xyzw(T)}


def _header(frame: str, stamp_ns: int) -> dict:
    return {"stamp": {"sec": stamp_ns // 10 ** 9, "nanosec": stamp_ns % 10 ** 9}, "frame_id": frame}


def write_mcap(path: str | Path, targets: Targets, tf_prefix: str = "", stamp_ns: int | None = None) -> Path:
    """Write `targets` as ROS 2 messages to an MCAP file (atomically, through a temporary file of its own:
    fileio.atomic_write_bytes, so that two processes writing the same path never share one)."""
    from mcap_ros2.writer import Writer  # loaded where it is used

    path = Path(path)
    stamp = time.time_ns() if stamp_ns is None else int(stamp_ns)
    buf = io.BytesIO()  # a few kB: written whole, then placed
    _write(buf, targets, tf_prefix, stamp, Writer)
    atomic_write_bytes(path, buf.getvalue())
    return path


def _write(f, targets: Targets, tf_prefix: str, stamp: int, Writer) -> None:
    poses = targets.poses()
    robot = targets.robot_frame
    w = Writer(f)
    tf_schema = w.register_msgdef("tf2_msgs/msg/TFMessage", TF_MESSAGE)
    pose_schema = w.register_msgdef("geometry_msgs/msg/PoseStamped", POSE_STAMPED)
    array_schema = w.register_msgdef("geometry_msgs/msg/PoseArray", POSE_ARRAY)
    transforms = []
    children = {"T_robot_camera": targets.camera_frame, **{k: tf_prefix + v for k, v in TF_CHILDREN.items()}}
    for key, child in children.items():
        if key in poses:
            T = poses[key]
            transforms.append({"header": _header(robot, stamp), "child_frame_id": child,
                               "transform": {"translation": dict(zip("xyz", (float(v) for v in T[:3, 3]))),
                                             "rotation": _quat_xyzw(T)}})
    w.write_message("/tf_static", tf_schema, {"transforms": transforms}, log_time=stamp, publish_time=stamp)
    for key, topic in POSE_TOPICS.items():
        if key in poses:
            w.write_message(topic, pose_schema, {"header": _header(robot, stamp), "pose": _pose(poses[key])},
                            log_time=stamp, publish_time=stamp)
    arrays = {"/apose/place/approach": ["T_robot_gripper_preplace", "T_robot_gripper_place"],
              "/apose/pick/approach": ["T_robot_gripper_lift", "T_robot_gripper_pick", "T_robot_gripper_lift"]}
    for topic, keys in arrays.items():
        if all(k in poses for k in keys):
            w.write_message(topic, array_schema, {"header": _header(robot, stamp),
                                                  "poses": [_pose(poses[k]) for k in keys]},
                            log_time=stamp, publish_time=stamp)
    if targets.gripper_alternatives:
        w.write_message("/apose/place/alternatives", array_schema,
                        {"header": _header(robot, stamp), "poses": [_pose(T) for T in targets.gripper_alternatives]},
                        log_time=stamp, publish_time=stamp)
    w.finish()


def read_mcap(path: str | Path) -> list[tuple[str, object]]:
    """(topic, decoded ROS 2 message) of every message in an MCAP file, in order (the standard reader)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        return [(channel.topic, msg) for _, channel, _, msg in
                make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
