"""Shared by the registration tests: a pinhole camera, prepared base objects, synthetic views, yaw renders."""

import numpy as np
import pytest

from apose_studio.assembly.mesh import base_mesh, load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.registration import prepare_base

from ..conftest import SAMPLES

CAM = CameraIntrinsics(640, 480, 615.0, 615.0, 320.0, 240.0)


@pytest.fixture(scope="module")
def gearbox_step2():
    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    models = load_parts(asm)
    view = asm.step_view(2)
    return view, prepare_base(base_mesh(models, view)), models


def synthetic_view(base, T_world_base, T_world_camera):
    """Depth and mask of the base alone, ray-cast exactly (no table, no noise)."""
    from apose_studio.geometry.raycast import raycast_points

    pts, _ = raycast_points(base.mesh, T_world_base, T_world_camera, CAM)
    pc = se3.transform_points(se3.inv(T_world_camera), pts)
    u = np.round(CAM.fx * pc[:, 0] / pc[:, 2] + CAM.cx).astype(int)
    v = np.round(CAM.fy * pc[:, 1] / pc[:, 2] + CAM.cy).astype(int)
    depth = np.zeros((CAM.height, CAM.width), np.float32)
    depth[v, u] = pc[:, 2]
    return depth, depth > 0


@pytest.fixture(scope="module")
def gearbox_yaw(tmp_path_factory):
    from apose_studio.data.dataset import Dataset
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    out = tmp_path_factory.mktemp("yaw") / "ds"
    asm = load_assembly(SAMPLES / "helical_gearbox" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=2, seed=4), steps=[2], progress=False)
    return Dataset(out)


@pytest.fixture(scope="module")
def planetary_yaw(tmp_path_factory):
    from apose_studio.data.dataset import Dataset
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    out = tmp_path_factory.mktemp("planetary") / "ds"
    asm = load_assembly(SAMPLES / "planetary_reducer" / "assembly.yaml")
    render_dataset(asm, out, RenderSettings(frames=6, seed=11, base_pose="yaw"), steps=[3], progress=False)
    return Dataset(out)

