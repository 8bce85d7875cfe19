"""Symmetries found from a surface (the geometry side of the estimator)."""

"""The estimator's stages on small data, and degenerate inputs that must fail cleanly."""

import numpy as np
import pytest
import trimesh

from apose_studio import se3
from apose_studio.assembly import load_assembly
from apose_studio.mesh import base_mesh, load_parts
from apose_studio.registration import (
    detect_symmetries,
    prepare_base,
)


def test_symmetry_detection():
    box = trimesh.creation.box((0.04, 0.02, 0.01))
    syms, res = detect_symmetries(trimesh.sample.sample_surface_even(box, 6000, seed=1)[0], 0.046)
    assert len(syms) == 4  # identity and the three half turns
    assert np.all(res < 0.0005)
    l_shape = trimesh.util.concatenate([box, trimesh.creation.box((0.01, 0.03, 0.01)).apply_translation([0.015, 0.02, 0])])
    syms, _ = detect_symmetries(trimesh.sample.sample_surface_even(l_shape, 6000, seed=1)[0], 0.06)
    assert len(syms) == 1


def test_fidget_casing_is_two_fold(fidget_yaml):
    asm = load_assembly(fidget_yaml)
    models = load_parts(asm)
    base = prepare_base(base_mesh(models, asm.step_view(1)))
    assert len(base.symmetries) == 2
    axis = base.symmetries[1][:3, :3]
    assert se3.rotation_angle_deg(axis) == pytest.approx(180, abs=1)
    assert abs(axis[2, 2] - 1) < 1e-3  # about z
    assert base.symmetry_residuals[1] < 0.0005


def test_a_symmetry_turns_about_the_true_axis_despite_an_off_centre_feature():
    """A 2-fold symmetric block with a small knob off to one side: the knob pulls the samples'
    centroid off the block's axis, so a half turn about the centroid would put the twin pose ~0.3 mm
    off; the detected symmetry is refined onto the block and turns about the block's own axis."""
    block = trimesh.creation.box((0.1, 0.06, 0.04))
    knob = trimesh.creation.box((0.004, 0.004, 0.005)).apply_translation([0.045, 0.025, 0.0225])
    mesh = trimesh.util.concatenate([block, knob])
    pts = trimesh.sample.sample_surface_even(mesh, 20000, seed=2)[0]
    assert np.linalg.norm(pts.mean(axis=0)[:2]) > 1e-4  # the centroid is off the axis
    syms, res = detect_symmetries(pts, 0.125)
    half = [S for S in syms[1:] if abs(S[2, 2] - 1) < 1e-3]  # the half turn about z
    assert len(half) == 1 and se3.rotation_angle_deg(half[0][:3, :3]) == pytest.approx(180, abs=0.5)
    assert np.linalg.norm(half[0][:3, 3]) < 1.5e-4  # maps the block's centre (the origin) onto itself (0.36 mm unrefined)

