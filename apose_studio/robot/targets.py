"""Pick-and-place targets for a robot: from an estimated assembly pose, a grasp and the camera's pose in
the robot's base frame, the gripper's poses at place, pre-place, pick and lift.

Pure functions over 4x4 matrices (metres, `T_<to>_<from>`):
- place: T_robot_part = T_robot_camera · T_camera_part (the assembly pose), the gripper there
  T_robot_gripper_place = T_robot_part · T_part_gripper, and the pre-place pose: the part backed off along
  the step's `approach` (its direction in base[0]'s frame), the gripper holding it as at the place;
- pick: the part's own pose where it lies (T_robot_part_pick), the gripper there, and the lift: the gripper
  moved back along its own z (the way the fingers came in) by the lift distance;
- alternatives: a symmetric part is the same placement turned by any of its symmetries, so each turn gives
  another gripper target at the place (n-fold: all n; continuous: `CONTINUOUS_SAMPLES` turns and the axis);
  a symmetric base makes other placements the same assembly (the estimate's `equivalent`): their gripper
  targets are listed too, so a planner can choose one the arm reaches.

Quaternions: w, x, y, z in apose (`quat_wxyz`, as viser); x, y, z, w where ROS wants it (`quat_xyzw`, and
the MCAP messages).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from apose_studio.assembly.grasps import Grasp
from apose_studio.assembly.mates import Approach
from apose_studio.assembly.model import Symmetry
from apose_studio.geometry import se3

CONTINUOUS_SAMPLES = 8  # gripper targets listed for a part with a continuous symmetry (and its axis)
MAX_DISCRETE = 36  # at most this many turns of an n-fold symmetric part are listed (every k-th beyond)
DEFAULT_BACKOFF_M = 0.05  # pre-place without a step approach, and lift after the pick: along the gripper's -z


@dataclass
class Targets:
    """What a robot program needs for one step; every pose in the robot's base frame, metres."""

    robot_frame: str
    camera_frame: str
    T_robot_camera: np.ndarray
    T_robot_base: np.ndarray | None = None  # the base object (base[0]) where it was seen
    T_robot_part: np.ndarray | None = None  # the assembly pose
    T_robot_part_preplace: np.ndarray | None = None  # the part where the approach starts
    grasp: str | None = None
    width: float | None = None
    T_robot_gripper_place: np.ndarray | None = None
    T_robot_gripper_preplace: np.ndarray | None = None
    gripper_alternatives: list[np.ndarray] = field(default_factory=list)  # other T_robot_gripper_place
    alternatives_why: list[str] = field(default_factory=list)  # one phrase per alternative
    symmetry_axis: dict | None = None  # a continuous symmetry: {point, direction} in the robot frame
    T_robot_part_pick: np.ndarray | None = None
    T_robot_gripper_pick: np.ndarray | None = None
    T_robot_gripper_lift: np.ndarray | None = None
    pick: dict | None = None  # the pick estimate's own verdict: ok, confident, reason, doubts
    notes: list[str] = field(default_factory=list)

    POSES = ("T_robot_camera", "T_robot_base", "T_robot_part", "T_robot_part_preplace", "T_robot_gripper_place",
             "T_robot_gripper_preplace", "T_robot_part_pick", "T_robot_gripper_pick", "T_robot_gripper_lift")

    def poses(self) -> dict[str, np.ndarray]:
        """Every pose that was computed, by name."""
        return {k: getattr(self, k) for k in self.POSES if getattr(self, k) is not None}

    def to_json(self) -> dict:
        """The fields `apose estimate --json` adds (4x4 row-major lists), and `poses`: each as position and
        both quaternion orders, for code that wants those."""
        out: dict = {k: v.tolist() for k, v in self.poses().items()}
        out.update(grasp=self.grasp, grasp_width_m=self.width,
                   gripper_alternatives=[T.tolist() for T in self.gripper_alternatives],
                   gripper_alternatives_why=list(self.alternatives_why), symmetry_axis=self.symmetry_axis,
                   pick=self.pick, robot_notes=list(self.notes))
        out["robot_poses"] = {k: pose_record(v) for k, v in self.poses().items()}
        out["conventions"] = conventions(self.robot_frame, self.camera_frame)
        return out


def conventions(robot_frame: str, camera_frame: str) -> dict:
    return {"units": "metres", "matrices": "4x4 row-major; T_a_b maps points in frame b into frame a",
            "quaternions": "quat_wxyz is w, x, y, z (apose, viser); quat_xyzw is x, y, z, w (ROS, MCAP)",
            "robot_frame": robot_frame, "camera_frame": camera_frame + " (optical: x right, y down, z forward)",
            "gripper_frame": "TCP: z out of the gripper towards the part, y the jaws' closing direction, origin "
                             "between the finger tips"}


def pose_record(T: np.ndarray) -> dict:
    """A pose as position (m) and quaternions in both orders."""
    w, x, y, z = (float(v) for v in se3.matrix_to_quat_wxyz(T[:3, :3]))
    return {"xyz": [float(v) for v in T[:3, 3]], "quat_wxyz": [w, x, y, z], "quat_xyzw": [x, y, z, w]}


def backed_off(T_robot_gripper: np.ndarray, distance: float) -> np.ndarray:
    """The gripper moved back along its own -z (the way its fingers came in) by `distance`."""
    T = np.array(T_robot_gripper, dtype=float)
    T[:3, 3] -= distance * T[:3, 2]
    return T


def symmetry_turns(symmetry: Symmetry | None) -> tuple[list[np.ndarray], list[str]]:
    """The part's symmetries other than identity as T_part_part, and a phrase each."""
    if symmetry is None:
        return [], []
    n = symmetry.order if symmetry.order >= 2 else CONTINUOUS_SAMPLES
    ks = range(1, n) if n - 1 <= MAX_DISCRETE else np.unique(np.linspace(1, n - 1, MAX_DISCRETE).round().astype(int))
    origin = np.asarray(symmetry.origin)
    turns, why = [], []
    for k in ks:
        turns.append(se3.turn_about(symmetry.axis, 2.0 * np.pi * k / n, origin))
        why.append(f"the part turned {360.0 * k / n:.4g} deg about its symmetry axis"
                   + (" (continuous symmetry: a sample)" if symmetry.order == 0 else ""))
    return turns, why


def place_targets(T_robot_camera: np.ndarray, T_camera_base: np.ndarray, T_camera_part: np.ndarray,
                  grasp: Grasp | None, approach: Approach | None, symmetry: Symmetry | None,
                  equivalent_T_camera_part: list[np.ndarray] = (), robot_frame: str = "base_link",
                  camera_frame: str = "camera_color_optical_frame") -> Targets:
    """The place targets of one step (see the module docstring)."""
    T_robot_base = T_robot_camera @ T_camera_base
    T_robot_part = T_robot_camera @ T_camera_part
    t = Targets(robot_frame, camera_frame, np.array(T_robot_camera, float), T_robot_base, T_robot_part)
    if approach is not None:
        t.T_robot_part_preplace = approach.start(T_robot_part, T_robot_base)
    if grasp is None:
        t.notes.append("the part has no grasps in the assembly file: only the part's poses are given (add "
                       "parts.<id>.grasps to get the gripper's)")
        return t
    G = grasp.T_part_gripper
    t.grasp, t.width = grasp.name, grasp.width
    t.T_robot_gripper_place = T_robot_part @ G
    if t.T_robot_part_preplace is not None:
        t.T_robot_gripper_preplace = t.T_robot_part_preplace @ G
    else:
        t.T_robot_gripper_preplace = backed_off(t.T_robot_gripper_place, DEFAULT_BACKOFF_M)
        t.notes.append(f"the step has no approach: pre-place is the place backed off {DEFAULT_BACKOFF_M * 1000:.0f} mm "
                       "along the gripper's z (add steps[i].approach for the real direction)")
    turns, why = symmetry_turns(symmetry)
    for S, w in zip(turns, why):
        t.gripper_alternatives.append(T_robot_part @ S @ G)
        t.alternatives_why.append(w)
    for i, E in enumerate(equivalent_T_camera_part):
        t.gripper_alternatives.append(T_robot_camera @ E @ G)
        t.alternatives_why.append(f"another placement the base's symmetry makes the same assembly (equivalent[{i}])")
    if symmetry is not None and symmetry.order == 0:
        p = se3.transform_points(T_robot_part, np.asarray(symmetry.origin)[None])[0]
        t.symmetry_axis = {"point": p.tolist(), "direction": (T_robot_part[:3, :3] @ np.asarray(symmetry.axis)).tolist(),
                           "note": "the part may be held turned by any angle about this axis (robot frame)"}
    return t


def add_pick(t: Targets, T_robot_part_pick: np.ndarray, grasp: Grasp | None, lift: float = DEFAULT_BACKOFF_M) -> None:
    """Add the pick targets: the part where it lies, the gripper there, and the lift (backed off `lift`)."""
    t.T_robot_part_pick = np.array(T_robot_part_pick, float)
    if grasp is not None:
        t.T_robot_gripper_pick = t.T_robot_part_pick @ grasp.T_part_gripper
        t.T_robot_gripper_lift = backed_off(t.T_robot_gripper_pick, lift)
