"""The principal point's word on the intrinsics: a point outside the image, or the centre of an image twice or
half as large on both axes (intrinsics for another resolution), is refused with the fix; real cameras' are not."""

import numpy as np
import pytest

from apose_studio.api import camera_from_K
from apose_studio.errors import AposeError
from apose_studio.geometry.camera import principal_point_problem


@pytest.mark.parametrize("size,cxcy", [
    ((640, 480), (320.0, 240.0)),  # centred
    ((640, 480), (325.26, 242.04)),  # BOP's LM (Kinect)
    ((1280, 720), (651.3, 362.1)),  # a RealSense D435 at 1280 x 720
    ((640, 480), (600.0, 240.0)),  # a crop off centre on one axis only: not another resolution
    ((640, 480), (420.0, 130.0)),  # off centre both ways, unlike each other
])
def test_real_cameras_pass(size, cxcy):
    assert principal_point_problem(*size, *cxcy) is None


@pytest.mark.parametrize("factor,native", [(2.0, "1280x960"), (0.5, "320x240"), (1.6, "1024x768"), (1.4, "896x672"),
                                           (3.0, "1920x1440"), (0.6, "384x288")])
def test_intrinsics_for_another_resolution_are_named_with_the_scale(factor, native):
    said = principal_point_problem(640, 480, 320.0 * factor, 240.0 * factor)
    assert said is not None and f"centre of a {native} image, not of this 640x480 one" in said
    assert f"by about {1 / factor:.3g}" in said


def test_a_calibration_for_another_aspect_is_named_without_one_factor():
    """A 1280 x 720 calibration on 640 x 480 frames (a RealSense's other mode): no one factor mends it."""
    said = principal_point_problem(640, 480, 640.0, 360.0)
    assert "centre of a 1280x720 image, not of this 640x480 one" in said and "scale fx" not in said


def test_a_portrait_frame_with_the_landscape_calibration_is_named():
    said = principal_point_problem(480, 640, 320.0, 240.0)
    assert "centre of a 640x480 image, this 480x640 one turned a quarter" in said
    assert principal_point_problem(480, 640, 240.0, 320.0) is None  # the turned image's own intrinsics


def test_a_point_outside_the_image_or_at_its_corner_is_refused():
    assert "lies outside the 640x480 image" in principal_point_problem(640, 480, 700.0, 240.0)
    assert "lies outside the 640x480 image" in principal_point_problem(640, 480, -1.0, 240.0)
    assert "or cx and cy missing" in principal_point_problem(640, 480, 0.0, 0.0)


def test_the_api_refuses_K_for_another_resolution():
    K = np.array([[1230.0, 0, 640.0], [0, 1230.0, 480.0], [0, 0, 1]])
    with pytest.raises(AposeError, match="K: the principal point .* centre of a 1280x960 image"):
        camera_from_K(K, 640, 480)
    cam = camera_from_K(K / np.array([[2], [2], [1]]), 640, 480)  # the same camera at 640 x 480
    assert (cam.fx, cam.cx, cam.cy) == (615.0, 320.0, 240.0)


@pytest.mark.parametrize("K,said", [
    ([[615.0, 0, 0], [0, 615.0, 0], [320.0, 240.0, 1]], "last row must be 0 0 1 .* is it transposed"),
    ([[615.0, 2.0, 320.0], [0, 615.0, 240.0], [0, 0, 1]], "skew"),
    ({"fx": 615.0}, "K must be a 3x3 intrinsic matrix of numbers"),
])
def test_the_api_refuses_a_K_that_is_no_pinhole_matrix(K, said):
    """camera.json and `apose serve` refused these; the API took a transposed K and returned a pose."""
    with pytest.raises(AposeError, match=said):
        camera_from_K(K, 640, 480)
