"""The depth image's registration to the colour image, found from the frame itself (geometry.sensor), on
Kinect-like desk renders whose depth the renderer shifted against the colour image: the true shift is found
here by comparing the render with the same render unshifted (numpy alone, not the code under test)."""

import cv2
import numpy as np
import pytest

from apose_studio.geometry import sensor
from apose_studio.geometry.sensor import depth_colour_shift, shift_image

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


@pytest.mark.parametrize("du,dv", [(3, 0), (-2, 3)])
def test_a_shift_is_found_on_an_object_at_the_image_border(du, dv):
    """A block touching the image's left border, its depth moved (du, dv) against the colour image (numpy
    slicing alone): the shift is found with a box that reaches the border (where shifted edges leave the
    image and only those inside count), to within a pixel each way (the depth's edge is its near side's pixel,
    Canny's the one of steepest colour)."""
    h, w = 240, 320
    rgb = np.full((h, w, 3), 60, np.uint8)
    rgb[100:200, 0:120] = (220, 200, 40)
    depth = np.full((h, w), 1.0, np.float32)
    depth[100:200, 0:120] = 0.9
    shifted = shift_image(depth, du, dv)
    shifted[shifted == 0] = 1.0  # what came in at the border: the table
    found = depth_colour_shift(rgb, shifted, (0, 90, 130, 210))
    assert abs(found[0] - du) <= 1 and abs(found[1] - dv) <= 1 and found != (0, 0), found
    assert depth_colour_shift(rgb, depth, (0, 90, 130, 210)) == (0, 0)


def test_colour_edges_the_object_makes_itself_are_left_out_of_the_comparison():
    """A casing seen from above and in front, its rim as grey as the table: the depth jumps only along its far
    outline (its near side face runs down to the table), where the colour shows no edge; 4 px inside it the
    colour shows the far inner wall. Compared with that, the depth's outline finds a clear shift of (0, -3)
    that is not there (the gearbox casing's renders, benchmarks/captures.py). Told which colour edges are the
    casing's own (its creases at its pose: raycast.own_edges), no clear shift. Painted to stand out, its depth
    moved by (-2, 3), the shift is found with its own edges left out; unmoved, none."""
    from apose_studio.geometry.sensor import shift_evidence

    h, w = 240, 320
    depth = np.full((h, w), 1.0, np.float32)
    depth[100:130, 40:280] = 0.9  # the top face: a jump onto the table behind it
    depth[130:160, 40:280] = np.linspace(0.9, 1.0, 30, dtype=np.float32)[:, None]  # the near side face, to the table
    rgb = np.full((h, w, 3), 128, np.uint8)  # the rim as grey as the table
    rgb[104:109, 43:277] = 40  # the far inner wall, seen over the rim
    rgb[130:160, 40:280] = 60  # the near side face, in shadow
    own = np.zeros((h, w), bool)
    own[[104, 109, 130], 40:280] = True  # the rim's inner edge, the wall's foot, the crease above the side face
    box = (35, 95, 285, 165)
    (du, dv), ratio = shift_evidence(rgb, depth, box)
    # fooled (a bleed of the outline upward explains a part of the 4 px too, so the shift gains less than it did)
    assert (du, dv) == (0, -3) and ratio < 0.75, ((du, dv), ratio)
    (du, dv), ratio = shift_evidence(rgb, depth, box, own)
    assert ratio > 0.9, ((du, dv), ratio)
    painted = rgb.copy()
    painted[100:130, 40:280][rgb[100:130, 40:280, 0] == 128] = (200, 60, 60)
    moved = shift_image(depth, -2, 3)
    moved[moved == 0] = 1.0
    (du, dv), ratio = shift_evidence(painted, moved, box, own)
    assert (du, dv) == (-2, 3) and ratio < 0.5, ((du, dv), ratio)
    assert shift_evidence(painted, depth, box, own)[0] == (0, 0)


def test_nearest_within_sees_nothing_beyond_the_image():
    """The least depth within px of each pixel, inf beyond the image's edge (OpenCV's own border for a float
    erosion is FLT_MAX: the edge's pixels read 3e38 m, finite), and the same in a window as in the whole image."""
    from apose_studio.geometry.sensor import nearest_within

    z = np.full((40, 60), np.inf, np.float32)
    z[10:14, 20:25] = 1.0
    z[12, 22] = 0.5
    out = nearest_within(z, 2)
    want = np.full_like(z, np.inf)
    for v in range(40):  # the definition, pixel by pixel
        for u in range(60):
            want[v, u] = z[max(v - 2, 0):v + 3, max(u - 2, 0):u + 3].min()
    np.testing.assert_array_equal(out, want)
    assert np.isfinite(out).sum() == 8 * 9  # the 4 x 5 patch, 2 px wider each way; nothing at the image's edge
    window = nearest_within(z[7:17, 17:28], 2)  # a window 3 px round the patch
    np.testing.assert_array_equal(window, out[7:17, 17:28])


def block_scene(h: int = 240, w: int = 320) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, depth): a yellow block 0.9 m away on a grey table 1.0 m away, its outline in colour and depth alike."""
    rgb = np.full((h, w, 3), 60, np.uint8)
    rgb[80:160, 100:220] = (220, 200, 40)
    depth = np.full((h, w), 1.0, np.float32)
    depth[80:160, 100:220] = 0.9
    return rgb, depth


@pytest.mark.parametrize("px", [1, 2, 3])
def test_depth_bled_round_an_outline_is_a_bleed_not_a_shift(px):
    """A block whose depth is registered exactly but bleeds `px` pixels into the table all round (noise.bleed, a
    correlation window's fattening): every outline lies px farther out in depth than in colour, each away from the
    block, which no shift explains. The bleed is found and no shift; the same depth moved (2, -1) as well: that
    shift, and the bleed."""
    from apose_studio.geometry.noise import bleed
    from apose_studio.geometry.sensor import shift_and_bleed

    rgb, depth = block_scene()
    bled = bleed(depth, px)
    assert (bled != depth).sum() > 300
    box = (90, 70, 230, 170)
    # to within a pixel (the depth's edge is its near side's pixel, Canny's the one of steepest colour)
    (du, dv), found, _ = shift_and_bleed(rgb, bled, box)
    assert max(abs(du), abs(dv)) <= 1 and abs(found - px) <= 1, ((du, dv), found)
    assert depth_colour_shift(rgb, bled, box) == (0, 0)
    moved = shift_image(bled, 2, -1)
    moved[moved == 0] = 1.0
    (du, dv), found, ratio = shift_and_bleed(rgb, moved, box)
    assert abs(du - 2) <= 1 and abs(dv + 1) <= 1 and abs(found - px) <= 1 and ratio < 0.75, ((du, dv), found, ratio)


def test_an_outline_seen_only_on_two_sides_bled_is_not_taken_for_a_shift(monkeypatch):
    """A Kinect's view of a block on a table: the projector's shadow leaves no depth left of it and its foot meets
    the table, so its depth shows only its top and right outlines, and a 2 px bleed moves both up and right, as a
    shift of (2, -2) would. Bleed and shift explain the edges alike, and the shorter shift wins: none (a depth moved
    on that evidence put four confident gearbox poses 2-5 mm off, benchmarks/captures.py's `bleed` row)."""
    from apose_studio.geometry.noise import bleed
    from apose_studio.geometry.sensor import shift_and_bleed

    rgb, depth = block_scene()
    v = np.arange(depth.shape[0], dtype=np.float32)[:, None]
    depth[:] = 0.9 + 0.002 * (160 - v)  # the table seen aslant: farther up the image, at the block's depth at its foot
    depth[80:160, 100:220] = 0.9
    bled = bleed(depth, 2)
    bled[70:160, 90:100] = 0  # the projector's shadow: no depth beside the block's left outline
    box = (90, 70, 230, 170)
    (du, dv), found, _ = shift_and_bleed(rgb, bled, box)
    assert max(abs(du), abs(dv)) <= 1 and found >= 1, ((du, dv), found)
    assert depth_colour_shift(rgb, bled, box) == (0, 0)
    monkeypatch.setattr(sensor, "BLEED_MAX_PX", 0)  # a search that knows no bleed takes it for a shift
    (du, dv), found, ratio = shift_and_bleed(rgb, bled, box)
    assert du >= 1 and dv <= -1 and max(du, -dv) >= 2 and ratio < 0.75, ((du, dv), ratio)  # up and right
    assert depth_colour_shift(rgb, bled, box) != (0, 0)


def test_a_pose_outline_off_the_colour_outline_tells_a_shift_from_a_bleed():
    """The model's outline at a pose fitted to depth lying (2, -1) px off the colour image lies as far off the
    colour's edges: moved back by that shift it lies on them (a ratio well under 1). At a pose fitted to depth that
    only bleeds past its outlines the model's outline lies on the colour's already, and any move takes it off."""
    from apose_studio.geometry.sensor import outline_shift_ratio

    rgb, _ = block_scene()
    block = np.zeros(rgb.shape[:2], bool)
    block[80:160, 100:220] = True
    outline = block & ~(cv2.erode(block.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    off = np.roll(outline, (-1, 2), axis=(0, 1))  # the pose's outline 2 px right and 1 px up
    assert outline_shift_ratio(rgb, off, 2, -1) < 0.5
    assert all(outline_shift_ratio(rgb, outline, du, dv) > 1.0 for du, dv in [(2, -1), (2, -2), (1, -3), (-2, 0)])
    assert outline_shift_ratio(rgb, np.zeros_like(outline), 2, -1) == 1.0  # nothing to compare
