"""The answer depends on the frame, not on where the caller's world frame is.

A capture folder gets its world from the table it sees (plane.table_frame); a rendered dataset from the
renderer; a robot cell from the robot's base, a metre or two from the camera. The same depth, mask and
intrinsics must give the same pose in the camera's frame in all of them: before, a world moved 0.9 m
left every coarse pose of a fidget casing off the target (the ICP turned about the world's origin), and
the same render opened as a dataset and as a capture folder gave a 19.5 mm ambiguous pose in one and a
0.6 mm pose in the other (the upright search's yaws, its slides and Open3D's voxel grid were laid along
the world's axes)."""

from dataclasses import replace

import numpy as np
import pytest

from apose_studio.assembly.mesh import load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.estimation import StepContext, estimate_frame
from apose_studio.geometry import se3
from apose_studio.geometry.plane import table_frame
from apose_studio.masks.prompt import prompted_mask
from apose_studio.registration import icp, raycast_source, resolve_params
from apose_studio.registration.stages import cloud

from ..conftest import SAMPLES, rendered_frame
from .conftest import CAM

GEARBOX = SAMPLES / "helical_gearbox" / "assembly.yaml"
KINECT = dict(seed=5, noise="kinect")
# a world turned 2 rad about a tilted axis, its origin 1.5 m from the camera's: a robot's base frame, say
T_FAR = se3.make_T(se3.axis_angle_matrix([1.0, 2.0, 3.0], 2.0), [0.9, -1.1, 0.5])


def _box(mask: np.ndarray, margin: int = 10) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    return (max(int(xs.min()) - margin, 0), max(int(ys.min()) - margin, 0), min(int(xs.max()) + 1 + margin, 640),
            min(int(ys.max()) + 1 + margin, 480))


@pytest.mark.parametrize("step,im_id,clutter", [(1, 0, "hidden"), (2, 2, "bench,stacked")])
def test_the_same_frame_in_three_world_frames_gives_one_answer(step, im_id, clutter):
    """A casing mostly hidden behind a box (the upright search slides it over the table) and one with a flat
    object lying on it and a box in front (the mask's readings): as rendered, in the world a capture folder
    would give it, and in a far, turned world, the pose in the camera's frame and every flag are the same
    (to rounding: the world's transform is the only arithmetic that differs)."""
    asm = load_assembly(GEARBOX)
    ctx = StepContext(asm, load_parts(asm), step)
    frame = rendered_frame(GEARBOX, step, im_id, clutter=clutter, **KINECT)
    box = _box(frame.base_mask())
    mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box).mask
    worlds = {"rendered": frame.T_world_camera, "capture": table_frame(frame.depth, frame.camera),
              "far": T_FAR @ frame.T_world_camera}
    assert worlds["capture"] is not None
    answers = {}
    for name, T_world_camera in worlds.items():
        r = estimate_frame(replace(frame, T_world_camera=T_world_camera), ctx, resolve_params("default"), mask=mask, box=box)
        answers[name] = (r, se3.inv(T_world_camera) @ r.T_world_part if r.ok else None)
    r0, T0 = answers["rendered"]
    assert r0.ok, r0.reason
    for name in ("capture", "far"):
        r, T = answers[name]
        assert (r.ok, r.confident, r.ambiguous, r.reading) == (r0.ok, r0.confident, r0.ambiguous, r0.reading), name
        assert np.abs(T[:3, 3] - T0[:3, 3]).max() < 1e-9 and np.abs(T[:3, :3] - T0[:3, :3]).max() < 1e-9, name
        assert abs(r.coverage - r0.coverage) < 1e-9 and abs(r.contradiction - r0.contradiction) < 1e-9, name


def test_icp_far_from_the_origin_converges_as_at_it(gearbox_step2):
    """The same registration problem with the world's origin at the part and 1.5 m away, turned: the same pose
    (the step turns about the matched points' centre, as a rotation vector). Linearised about the origin,
    the far copy's turn and shift traded off against each other and the pose ended elsewhere."""
    _, base, _ = gearbox_step2
    T_world_camera = se3.look_at([0.25, -0.2, 0.3], [0, 0, 0.01])
    T_true = se3.make_T(se3.axis_angle_matrix([0.3, 0.2, 1.0], np.radians(40)), [0.01, -0.02, 0.0])
    target_w, target_n = raycast_source(base, T_true, T_world_camera, CAM)
    source_b = cloud(se3.transform_points(se3.inv(T_true), target_w)).voxel_down_sample(0.002)
    T0 = T_true @ se3.make_T(se3.axis_angle_matrix([1, 0, 0], np.radians(8)), [0.006, -0.004, 0.005])
    near = icp(source_b, cloud(target_w, target_n), T0, 0.01, 30)
    far = icp(source_b, cloud(se3.transform_points(T_FAR, target_w), target_n @ T_FAR[:3, :3].T), T_FAR @ T0, 0.01, 30)
    assert np.linalg.norm(near[:3, 3] - T_true[:3, 3]) < 5e-4  # the problem is solvable
    back = se3.inv(T_FAR) @ far
    assert np.abs(back - near).max() < 1e-9
