"""The depth image's registration to the colour image, found from the frame itself (geometry.sensor), on
Kinect-like desk renders whose depth the renderer shifted against the colour image: the true shift is found
here by comparing the render with the same render unshifted (numpy alone, not the code under test)."""

import numpy as np
import pytest

from apose_studio.geometry.sensor import depth_colour_shift, outline_shift, shift_image

from ..conftest import SAMPLES, rendered_frame, true_shift

DESK = SAMPLES / "desk_objects" / "assembly.yaml"
REAL_DESK = dict(seed=5, noise="kinect", noise_sigma_at_05m=0.0005, clutter="bench,stacked,textured",
                 depth_bias_m=0.003, distance_range_m=(0.65, 1.2))  # benchmarks/captures.py's `real` row, less its shift


def prompt_box(mask: np.ndarray, margin: int = 10) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    return int(xs.min()) - margin, int(ys.min()) - margin, int(xs.max()) + 1 + margin, int(ys.max()) + 1 + margin


def test_shift_image_moves_right_and_down():
    img = np.arange(20, dtype=np.float32).reshape(4, 5)
    out = shift_image(img, 2, 1)
    assert out[1, 2] == img[0, 0] and out[3, 4] == img[2, 2]
    assert not out[0].any() and not out[:, :2].any()  # what came in at the border is 0


@pytest.mark.parametrize("step,im_id", [(1, 1), (3, 1), (4, 5)])
def test_the_depth_found_shifted_against_the_colour_image(step, im_id):
    """A desk frame whose depth lies 3 px off the colour image: the shift is found, around the prompt's box,
    to within a pixel each way (a Kinect's near surfaces bleed a pixel into far ones); the same frame
    registered exactly gives none."""
    off = rendered_frame(DESK, step, im_id, misregistration_px=3.0, **REAL_DESK)
    exact = rendered_frame(DESK, step, im_id, **REAL_DESK)
    du, dv = true_shift(off.depth, exact.depth)
    assert max(abs(du), abs(dv)) >= 2
    box = prompt_box(exact.base_mask())
    found = depth_colour_shift(off.rgb, off.depth, box)
    assert abs(found[0] - du) <= 1 and abs(found[1] - dv) <= 1, (found, (du, dv))
    assert depth_colour_shift(exact.rgb, exact.depth, box) == (0, 0)


def test_no_shift_without_edges_to_compare():
    """A flat table (no object, so no depth edge) and a colour image of noise: nothing to align, no shift."""
    rng = np.random.default_rng(0)
    depth = np.full((120, 160), 0.8, np.float32)
    rgb = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    assert depth_colour_shift(rgb, depth) == (0, 0)
    assert depth_colour_shift(rgb, np.zeros_like(depth), (10, 10, 100, 100)) == (0, 0)


def _card(shape=(200, 240), rect=(60, 140, 70, 150)) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, silhouette): a red card on a grey bench, and where it lies (numpy slicing alone)."""
    rgb = np.full((*shape, 3), 40, np.uint8)
    rgb[rect[0]:rect[1], rect[2]:rect[3]] = (200, 50, 50)
    sil = np.zeros(shape, bool)
    sil[rect[0]:rect[1], rect[2]:rect[3]] = True
    return rgb, sil


@pytest.mark.parametrize("shift", [(3, -2), (-2, 0), (0, 4), (0, 0)])
def test_a_model_outline_fitted_to_shifted_depth_is_moved_onto_the_colour_edges(shift):
    """A pose fitted to depth that lies (du, dv) off the colour image puts the model's outline (du, dv) off the
    colour's edges: the outline's shift is (-du, -dv); an outline on the colour's edges needs none."""
    rgb, sil = _card()
    du, dv = shift
    fitted_to_depth = np.roll(sil, (dv, du), axis=(0, 1))
    assert outline_shift(rgb, fitted_to_depth) == (-du, -dv)


def test_no_outline_to_compare_gives_no_shift():
    """A silhouette of a few pixels, or no colour image, tells nothing."""
    rgb, sil = _card(rect=(60, 63, 70, 72))
    assert outline_shift(np.roll(rgb, 3, axis=1), sil) == (0, 0)
    assert outline_shift(rgb[..., 0], np.roll(_card()[1], 3, axis=1)) == (0, 0)
