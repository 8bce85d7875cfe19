"""SE(3) helpers over numpy. A 4x4 matrix is named T_<to>_<from>; quaternions are wxyz (as viser)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (exact, no general matrix inverse)."""
    R, t = T[:3, :3], T[:3, 3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ t
    return Ti


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply T (4x4) to points (N, 3); returns (N, 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def quat_wxyz_to_matrix(q) -> np.ndarray:
    """3x3 rotation from a quaternion [w, x, y, z] (normalised here)."""
    w, x, y, z = np.asarray(q, dtype=float)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternion [w, x, y, z] with w >= 0 from a 3x3 rotation."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def euler_deg_to_matrix(angles, order: str) -> np.ndarray:
    """3x3 rotation from Euler angles in degrees; scipy's order string (lower = extrinsic)."""
    return Rotation.from_euler(order, angles, degrees=True).as_matrix()


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees, in [0, 180]."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def axis_angle_matrix(axis, angle_rad) -> np.ndarray:
    """3x3 rotation about a (not necessarily unit) axis; (n, 3, 3) for an array of n angles (Rodrigues)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    th = np.asarray(angle_rad, dtype=float)[..., None, None]
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.cos(th) * np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * np.outer(a, a)


def turn_about(axis, angle_rad, point) -> np.ndarray:
    """T turning by `angle_rad` about the line along `axis` through `point` (a base turned about its own
    centre, a part about its symmetry axis): 4x4, or (n, 4, 4) for an array of n angles."""
    R = axis_angle_matrix(axis, angle_rad)
    p = np.asarray(point, dtype=float)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, p - R @ p, 1.0
    return T


def scale_motion(T: np.ndarray, s: float) -> np.ndarray:
    """A rigid motion `s` times as large: the rotation's angle about its axis and the translation scaled by `s`
    (T^s for small motions; s = 2: the same motion twice, near enough for a frame-to-frame motion)."""
    q = matrix_to_quat_wxyz(T[:3, :3])
    q = q if q[0] >= 0 else -q
    half = float(np.arctan2(np.linalg.norm(q[1:]), q[0]))
    R = np.eye(3) if half < 1e-12 else axis_angle_matrix(q[1:] / np.linalg.norm(q[1:]), 2.0 * half * s)
    return make_T(R, T[:3, 3] * s)


def perpendicular(v) -> np.ndarray:
    """A unit vector perpendicular to v (any one; stable for every direction)."""
    v = np.asarray(v, dtype=float)
    p = np.cross(v, [1.0, 0.0, 0.0] if abs(v[0]) < 0.9 * np.linalg.norm(v) else [0.0, 1.0, 0.0])
    return p / np.linalg.norm(p)


def fit_rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The T (4x4) minimising sum ||T src_i - dst_i||^2 over matched point pairs (Kabsch)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, cd - R @ cs)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_camera for an OpenCV camera (x right, y down, z forward) at `eye` looking at `target`."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=float)
    if abs(np.dot(z, up / np.linalg.norm(up))) > 0.999:  # looking straight along `up`: pick another
        up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), eye)
