"""A parallel-jaw grasp from one picked face of a part, and the gripper's shape for drawing.

`grasp_at_face`: the jaws close across the part where the user clicked:
- a flat face: along its normal: one jaw on the face, the other on the first surface a ray from the face
  meets going into the part (the opposite face); the TCP midway, the opening their distance;
- a round face (cylinder, cone): across its axis: the TCP on the axis at the picked point, the opening
  the diameter there.
The gripper comes in along `approach` (a direction in the part's frame: the TCP's z), made square to
the closing direction (y); x = y × z. The TCP frame is the format's: z out of the gripper towards the
part, y the jaws' closing direction, the origin between the finger tips.
"""

from __future__ import annotations

import numpy as np
import trimesh

from apose_studio.assembly.grasps import Grasp, Gripper
from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.geometry.raycast import body

APPROACHES = {"from +z": (0.0, 0.0, -1.0), "from -z": (0.0, 0.0, 1.0), "from +x": (-1.0, 0.0, 0.0),
              "from -x": (1.0, 0.0, 0.0), "from +y": (0.0, -1.0, 0.0), "from -y": (0.0, 1.0, 0.0)}  # the TCP's z
DEFAULT_GRIPPER = Gripper("parallel", max_width=0.085, finger_length=0.045)  # a common 85 mm parallel gripper


def grasp_at_face(mesh: trimesh.Trimesh, kind: str, point, direction, radius: float, approach, name: str) -> Grasp:
    """The grasp across the part at a picked face (see the module docstring); AposeError when the face
    gives no grasp (not flat or round, no opposite face, an approach along the closing direction)."""
    point, direction = np.asarray(point, float), np.asarray(direction, float) / np.linalg.norm(direction)
    if kind == "plane":
        far = _opposite(mesh, point, direction)
        if far is None:
            raise AposeError("no face opposite the picked one (the ray into the part leaves it nowhere); pick a face "
                             "with a parallel face across the part, or a round face")
        y, tcp, width = direction, 0.5 * (point + far), float(np.linalg.norm(point - far))
    elif kind in ("cylinder", "cone"):
        axis = direction
        z0 = np.asarray(approach, float)
        y = np.cross(axis, z0)
        if np.linalg.norm(y) < 1e-6:  # coming in along the axis: the jaws close across it, either way
            y = se3.perpendicular(axis)
        y /= np.linalg.norm(y)
        tcp, width = point, 2.0 * float(radius)
    else:
        raise AposeError("pick a flat face (the jaws close on it and the face opposite) or a round one (they close "
                         "across it)")
    z = np.asarray(approach, float)
    z = z - (z @ y) * y
    if np.linalg.norm(z) < 1e-6:
        raise AposeError("the approach runs along the jaws' closing direction; choose another approach")
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    return Grasp(name, se3.make_T(np.column_stack([x, y, z]), tcp), width)


def _opposite(mesh: trimesh.Trimesh, point: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
    """The first surface point a ray from just inside `point` meets going along -normal (the face across)."""
    import open3d as o3d  # heavy: loaded where it is used

    scale = float(np.linalg.norm(mesh.extents)) or 1.0
    start = point - 1e-4 * scale * normal
    ray = np.concatenate([start, -normal]).astype(np.float32)[None]
    hit = body(mesh).scene.cast_rays(o3d.core.Tensor(ray))
    t = float(hit["t_hit"].numpy()[0])
    return None if not np.isfinite(t) else start - t * normal


def gripper_mesh(width: float | None, gripper: Gripper | None = None) -> trimesh.Trimesh:
    """A parallel-jaw gripper in its TCP frame, open at `width` (m): two fingers ending at z = 0 on either
    side of the origin along y, a palm behind them (-z). For drawing, not for collision checks."""
    g = gripper if gripper is not None and gripper.type == "parallel" else DEFAULT_GRIPPER
    length = g.finger_length or DEFAULT_GRIPPER.finger_length
    opening = width if width is not None else (g.max_width or DEFAULT_GRIPPER.max_width) / 2
    t = max(0.12 * length, 0.004)  # finger thickness
    fingers = [trimesh.creation.box((0.6 * t * 3, t, length), se3.make_T(None, (0.0, s * (opening / 2 + t / 2), -length / 2)))
               for s in (-1.0, 1.0)]
    palm = trimesh.creation.box((1.8 * t * 3, opening + 2 * t + 0.4 * length, 0.5 * length),
                                se3.make_T(None, (0.0, 0.0, -length - 0.25 * length)))
    return trimesh.util.concatenate(fingers + [palm])
