"""The camera's pose in the robot's base frame, from a hand-eye calibration file.

Two set-ups:
- **eye-to-hand** (the camera fixed in the cell): `T_robot_camera`.
- **eye-in-hand** (the camera on the arm): `T_flange_camera`, and the arm's `T_robot_flange` at the moment
  of the capture; then T_robot_camera = T_robot_flange · T_flange_camera.

Files read (JSON or YAML; metres; the camera frame is the OpenCV optical frame: x right, y down, z
forward, as ROS's `*_optical_frame`):
- ours: `{T_robot_camera: 4x4}` or `{T_flange_camera: 4x4, T_robot_flange: 4x4 (optional)}`, each with
  optional `robot_frame`, `camera_frame`, `flange_frame` names;
- a bare 4x4 matrix (JSON/YAML list of rows, or a text file of 4 rows of 4 numbers): T_robot_camera;
- easy_handeye2's calibration (`parameters: {calibration_type: eye_on_base | eye_in_hand,
  robot_base_frame, robot_effector_frame, tracking_base_frame}`, `transform: {translation: {x, y, z},
  rotation: {x, y, z, w}}`), and easy_handeye's older form (`eye_on_hand`, `transformation: {x, y, z, qx,
  qy, qz, qw}`). Their quaternions are x, y, z, w (ROS's order); apose's own are w, x, y, z.

Every problem is one AposeError naming the file, the key and the fix: a missing key, a matrix that is not
a rotation (orthonormal, determinant +1), a quaternion that is not of unit length, a translation of
kilometres (millimetres written as metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apose_studio import safeio
from apose_studio.assembly.fileio import parse_yaml
from apose_studio.errors import AposeError, AssemblyError
from apose_studio.geometry import se3

MAX_REACH_M = 20.0  # no robot cell is larger: a translation beyond this was written in millimetres
ROTATION_TOLERANCE = 1e-4  # |R R^T - I| above this is not a rotation (calibrations write 6+ digits)
QUATERNION_TOLERANCE = 1e-3  # |q| - 1 beyond this is not a unit quaternion
DEFAULT_ROBOT_FRAME = "base_link"
DEFAULT_CAMERA_FRAME = "camera_color_optical_frame"
DEFAULT_FLANGE_FRAME = "tool0"


@dataclass(frozen=True, eq=False)
class HandEye:
    """A calibration: `T` is T_robot_camera (eye_to_hand) or T_flange_camera (eye_in_hand)."""

    kind: str  # "eye_to_hand" | "eye_in_hand"
    T: np.ndarray
    robot_frame: str = DEFAULT_ROBOT_FRAME
    camera_frame: str = DEFAULT_CAMERA_FRAME
    flange_frame: str = DEFAULT_FLANGE_FRAME
    T_robot_flange: np.ndarray | None = None  # eye_in_hand: the arm at the capture, when the file gives it
    source: str = ""
    notes: tuple[str, ...] = ()  # what a user should check (a camera frame that is not an optical frame)

    def T_robot_camera(self, T_robot_flange: np.ndarray | None = None) -> np.ndarray:
        """The camera in the robot's base frame; eye-in-hand needs the flange's pose at the capture
        (`T_robot_flange`, else the file's own)."""
        if self.kind == "eye_to_hand":
            return self.T.copy()
        flange = T_robot_flange if T_robot_flange is not None else self.T_robot_flange
        if flange is None:
            raise AposeError(f"{self.source}: an eye-in-hand calibration (T_flange_camera) needs the arm's pose at the "
                             "capture: add T_robot_flange (4x4, metres) to the capture's camera.json, or to this file")
        return flange @ self.T


def read_hand_eye(path: str | Path) -> HandEye:
    """A hand-eye calibration file (see the module docstring); AposeError naming the file and key otherwise."""
    path = Path(path)
    text = safeio.read_text(path, "a hand-eye calibration file")
    where = str(path)
    data = _parse(text, where, path.suffix.lower())
    return hand_eye_from_data(data, where)


def hand_eye_from_data(data, where: str) -> HandEye:
    """A parsed calibration (a mapping, or a 4x4 list of rows) as HandEye; `where` names it in errors."""
    if isinstance(data, list):
        return HandEye("eye_to_hand", matrix(data, where, "the matrix"), source=where)
    if not isinstance(data, dict):
        raise AposeError(f"{where}: expected a mapping with T_robot_camera or T_flange_camera (4x4, metres), an "
                         "easy_handeye2 calibration, or a 4x4 matrix")
    if "transform" in data and isinstance(data.get("parameters"), dict):
        return _easy_handeye2(data, where)
    if "transformation" in data and "eye_on_hand" in data:
        return _easy_handeye1(data, where)
    names = {k: _frame_name(data, k, where) for k in ("robot_frame", "camera_frame", "flange_frame")}
    names = {k: v for k, v in names.items() if v is not None}
    if "T_robot_camera" in data and "T_flange_camera" in data:
        raise AposeError(f"{where}: gives both T_robot_camera (eye-to-hand) and T_flange_camera (eye-in-hand); keep the "
                         "one that matches the cell")
    if "T_robot_camera" in data:
        return HandEye("eye_to_hand", matrix(data["T_robot_camera"], where, "T_robot_camera"), source=where,
                       notes=_frame_notes(names.get("camera_frame")), **names)
    if "T_flange_camera" in data:
        flange = matrix(data["T_robot_flange"], where, "T_robot_flange") if data.get("T_robot_flange") is not None else None
        return HandEye("eye_in_hand", matrix(data["T_flange_camera"], where, "T_flange_camera"), T_robot_flange=flange,
                       source=where, notes=_frame_notes(names.get("camera_frame")), **names)
    keys = ", ".join(map(str, list(data)[:6])) or "none"
    raise AposeError(f"{where}: missing T_robot_camera (eye-to-hand) or T_flange_camera (eye-in-hand), 4x4 in metres "
                     f"(keys found: {keys}); or give an easy_handeye2 calibration file")


def capture_flange(folder: Path) -> np.ndarray | None:
    """The arm's T_robot_flange at a capture (eye-in-hand), from the capture's camera.json key `T_robot_flange`
    (4x4, metres); None when the capture does not give it."""
    where = str(Path(folder) / "camera.json")
    data = safeio.read_json(Path(folder) / "camera.json", "a capture's camera.json", safeio.LIMITS.text_bytes)
    if not isinstance(data, dict) or data.get("T_robot_flange") is None:
        return None
    return matrix(data["T_robot_flange"], where, "T_robot_flange")


def matrix(value, where: str, key: str) -> np.ndarray:
    """A 4x4 rigid transform in metres, checked: 16 finite numbers, last row 0 0 0 1, a rotation (orthonormal,
    determinant +1), a translation within MAX_REACH_M."""
    try:
        kind = np.asarray(value).dtype.kind  # true/false or text are not numbers, whatever float() makes of them
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        kind = "?"
    if kind not in "iuf":
        raise AposeError(f"{where}: {key} must be a 4x4 matrix of numbers (4 rows of 4)") from None
    if T.shape == (16,):
        T = T.reshape(4, 4)
    if T.shape != (4, 4):
        raise AposeError(f"{where}: {key} must be a 4x4 matrix (4 rows of 4 numbers), got shape {T.shape}")
    if not np.isfinite(T).all():
        raise AposeError(f"{where}: {key} holds NaN or infinite numbers")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise AposeError(f"{where}: {key}'s last row is {T[3].tolist()}, not [0, 0, 0, 1]; is the matrix transposed "
                         "(the translation in the last column)?")
    return se3.make_T(_rotation(T[:3, :3], where, key), _translation(T[:3, 3], where, key))


def _rotation(R: np.ndarray, where: str, key: str) -> np.ndarray:
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ROTATION_TOLERANCE:
        raise AposeError(f"{where}: {key}'s rotation is not orthonormal (R R^T differs from I by {err:.3g}); a "
                         "calibration's rotation has orthonormal rows: is it scaled, or a projection matrix?")
    if np.linalg.det(R) < 0:
        raise AposeError(f"{where}: {key}'s rotation is a reflection (determinant -1); was one axis flipped "
                         "(a left-handed frame)?")
    return R


def _translation(t, where: str, key: str) -> np.ndarray:
    t = np.asarray(t, float)
    if np.linalg.norm(t) > MAX_REACH_M:
        raise AposeError(f"{where}: {key}'s translation is {np.linalg.norm(t):g} m from the robot; calibrations are in "
                         f"metres (is it in millimetres? divide by 1000)")
    return t


def _quaternion_xyzw(q: dict, where: str, key: str, names=("x", "y", "z", "w")) -> np.ndarray:
    values = [_number(q, n, where, key) for n in names]
    x, y, z, w = values
    norm = float(np.linalg.norm(values))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise AposeError(f"{where}: {key} ({', '.join(names)}) has length {norm:.4g}, not 1: not a rotation "
                         "quaternion (ROS's order is x, y, z, w)")
    return se3.quat_wxyz_to_matrix([w, x, y, z])


def _number(d, name: str, where: str, key: str) -> float:
    if not isinstance(d, dict) or name not in d:
        raise AposeError(f"{where}: missing {key}.{name}")
    v = d[name]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise AposeError(f"{where}: {key}.{name} must be a finite number, got {v!r}"[:200])
    return float(v)


def _easy_handeye2(data: dict, where: str) -> HandEye:
    p = data["parameters"]
    kind = p.get("calibration_type")
    if kind not in ("eye_on_base", "eye_in_hand"):
        raise AposeError(f"{where}: parameters.calibration_type must be eye_on_base or eye_in_hand, got {kind!r}"[:200])
    tr = data["transform"]
    if not isinstance(tr, dict):
        raise AposeError(f"{where}: transform must be a mapping with translation {{x, y, z}} and rotation {{x, y, z, w}}")
    t = [_number(tr.get("translation"), n, where, "transform.translation") for n in ("x", "y", "z")]
    R = _quaternion_xyzw(tr.get("rotation"), where, "transform.rotation")
    T = se3.make_T(R, _translation(t, where, "transform.translation"))
    names = _names(p, where, "parameters.")
    return HandEye("eye_to_hand" if kind == "eye_on_base" else "eye_in_hand", T, source=where,
                   notes=_frame_notes(names.get("camera_frame")), **names)


def _easy_handeye1(data: dict, where: str) -> HandEye:
    tr = data["transformation"]
    if not isinstance(tr, dict):
        raise AposeError(f"{where}: transformation must be a mapping {{x, y, z, qx, qy, qz, qw}}")
    t = [_number(tr, n, where, "transformation") for n in ("x", "y", "z")]
    R = _quaternion_xyzw(tr, where, "transformation", names=("qx", "qy", "qz", "qw"))
    T = se3.make_T(R, _translation(t, where, "transformation"))
    if not isinstance(data["eye_on_hand"], bool):
        raise AposeError(f"{where}: eye_on_hand must be true or false, got {data['eye_on_hand']!r}"[:200])
    names = _names(data, where, "")
    return HandEye("eye_in_hand" if data["eye_on_hand"] else "eye_to_hand", T, source=where,
                   notes=_frame_notes(names.get("camera_frame")), **names)


def _names(d: dict, where: str, prefix: str) -> dict:
    """easy_handeye's frame names as ours (robot_base_frame, robot_effector_frame, tracking_base_frame)."""
    out = {}
    for theirs, ours in (("robot_base_frame", "robot_frame"), ("robot_effector_frame", "flange_frame"),
                         ("tracking_base_frame", "camera_frame")):
        v = d.get(theirs)
        if v is not None:
            out[ours] = _frame_text(v, where, prefix + theirs)
    return out


def _frame_name(d: dict, key: str, where: str) -> str | None:
    return None if d.get(key) is None else _frame_text(d[key], where, key)


def _frame_text(v, where: str, key: str) -> str:
    if not (isinstance(v, str) and 0 < len(v) <= 128 and v.isascii() and v.replace("_", "").replace("/", "").isalnum()):
        raise AposeError(f"{where}: {key} must be a ROS frame id (letters, digits, '_', '/'), got {v!r}"[:200])
    return v.lstrip("/")


def _frame_notes(camera_frame: str | None) -> tuple[str, ...]:
    if camera_frame is None or camera_frame.endswith("optical_frame"):
        return ()
    return (f"the calibration's camera frame {camera_frame!r} is not an optical frame (x right, y down, z forward): "
            "apose's camera frame is the optical one; calibrate to the *_optical_frame, or the poses turn by the "
            "fixed rotation between the two",)


def _parse(text: str, where: str, suffix: str):
    if suffix in (".txt", ".csv"):
        try:
            rows = [[float(v) for v in line.replace(",", " ").split()] for line in text.splitlines() if line.strip()
                    and not line.lstrip().startswith("#")]
        except ValueError:
            raise AposeError(f"{where}: expected 4 rows of 4 numbers (a 4x4 matrix, metres)") from None
        return rows
    if suffix == ".json":
        return safeio.parse_json(text, where)
    try:  # the assembly files' strict YAML: no aliases, no key twice, bounded nesting
        return parse_yaml(text, where)
    except AssemblyError as e:
        raise AposeError("; ".join(str(p) for p in e.problems)) from None
