"""The ways real desk captures defeated the estimate, each reproduced in a render (benchmarks/captures.py's
`stacked` and `hidden` rows) and checked against the renderer's own truth: a box prompt drawn around what
is seen of the base (its visible mask, 10 px wider), the prompted mask, the estimate. Each of these frames
gave a wrong pose, or none, before the mask's readings were checked by the model (hypotheses.py) and
near-ties were compared polished."""

import numpy as np
import pytest

from apose_studio.assembly.mesh import load_parts
from apose_studio.assembly.model import load_assembly
from apose_studio.estimation import StepContext, estimate_frame
from apose_studio.geometry import se3
from apose_studio.geometry.metrics import mssd
from apose_studio.masks.prompt import prompted_mask
from apose_studio.masks.segment import iou
from apose_studio.registration import resolve_params
from apose_studio.registration.types import doubts

from ..conftest import SAMPLES, rendered_frame, true_shift

GEARBOX = SAMPLES / "helical_gearbox" / "assembly.yaml"
DESK = SAMPLES / "desk_objects" / "assembly.yaml"
KINECT = dict(seed=5, noise="kinect")


def prompt_box(mask: np.ndarray, margin: int = 10) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    return (max(int(xs.min()) - margin, 0), max(int(ys.min()) - margin, 0), min(int(xs.max()) + 1 + margin, w),
            min(int(ys.max()) + 1 + margin, h))


_CONTEXTS: dict = {}


def estimate_prompted(assembly, step: int, im_id: int, params=None, **settings):
    """(frame, result, prompted mask, error of the part's pose / its diameter) for one rendered frame
    (`params`: the estimator's, default the default preset's)."""
    if (assembly, step) not in _CONTEXTS:
        asm = load_assembly(assembly)
        _CONTEXTS[(assembly, step)] = StepContext(asm, load_parts(asm), step)
    ctx = _CONTEXTS[(assembly, step)]
    frame = rendered_frame(assembly, step, im_id, **settings)
    box = prompt_box(frame.base_mask())
    mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box).mask
    r = estimate_frame(frame, ctx, params or resolve_params("default"), mask=mask, box=box)
    err = mssd(r.T_world_part, frame.T_world_part, ctx.part.samples, ctx.part.symmetries) / ctx.part.diameter \
        if r.ok else float("inf")
    return frame, r, mask, err


def test_a_flat_object_lying_on_the_base_stays_out_of_its_mask():
    """A flat box lying on the gearbox casing's rim, its sides continuing the casing's depth: the prompt takes
    it in (before: "the depth contradicts 50 % of what the model shows", no pose). Without what stands higher
    than the casing can reach, or without its colour, the pose is right and confident, and the result's mask
    leaves the box out. (Both readings leave it out; which explains the frame best has changed with the
    search: the colour one since the readings are judged over the box's own depth too.)"""
    frame, r, mask, err = estimate_prompted(GEARBOX, 1, 3, clutter="bench,stacked", **KINECT)
    truth = frame.base_mask()
    assert iou(mask, truth) < 0.7  # the prompted mask holds the flat box
    assert r.ok and r.confident and err < 0.1, (r.reason, r.reading, err)
    assert r.reading == "below the base's height" or r.reading.startswith("without colour"), r.reading
    assert iou(r.model_mask, truth) > iou(mask, truth) + 0.15


def test_two_things_in_one_mask_a_flat_object_on_the_base_and_a_box_in_front():
    """A flat object lies on the casing and a box stands in front of it: the prompt takes in both (before
    the readings: wrong, unconfident). Without what lies higher than the casing can reach, the pose is right
    and confident, and the result's mask, the casing's silhouette at that pose, leaves out both. (Until the
    upright search also started the casing standing on the table, leaving out the flat object alone left
    the box to pull the pose 7 mm off, and the best reading was read again: without what stands in front.)"""
    frame, r, mask, err = estimate_prompted(GEARBOX, 2, 2, clutter="bench,stacked", **KINECT)
    truth = frame.base_mask()
    assert iou(mask, truth) < 0.65  # the prompted mask holds both
    assert r.ok and r.confident and err < 0.1, (r.reason, r.reading, err)
    assert "below the base's height" in r.reading
    assert iou(r.model_mask, truth) > iou(mask, truth) + 0.3


def test_a_flat_object_of_another_colour_is_told_apart_by_its_colour():
    """A flat disc too thin to stand out in depth, lying across the casing: its colour sets it apart."""
    frame, r, mask, err = estimate_prompted(GEARBOX, 1, 0, clutter="bench,stacked", **KINECT)
    assert r.ok and err < 0.1, (r.reason, r.reading, err)
    assert r.reading.startswith("without colour")


def test_a_dark_object_in_front_without_depth_stays_out_of_the_result_mask():
    """A dark object stands in front of the duck; a Kinect reads depth off few of its pixels, and the prompted mask
    takes in the rest, pixels without depth that nothing in the depth tells from the duck's own holes. Their colour
    does: that of what stands in front, not of the duck's surface. Before, the result's mask kept them (431 false
    pixels of a mask of 2,709, IoU 0.85); the pose and its confidence are as before."""
    frame, r, mask, err = estimate_prompted(DESK, 4, 0, clutter="bench,stacked", **KINECT)
    truth = frame.base_mask()
    assert r.ok and r.confident and err < 0.1, (r.reason, err)
    no_depth = ~(frame.depth > 0)
    assert (mask & ~truth & no_depth).sum() > 300  # the prompted mask holds the dark object's holes
    assert (r.model_mask & ~truth & no_depth).sum() < 30
    assert iou(r.model_mask, truth) > 0.93


def test_a_base_mostly_hidden_behind_an_object_in_front():
    """A box stands in front of the casing and leaves a quarter of it visible; the prompt around that quarter
    takes in the box (the mask holds something else). It was right and confident without that depth patch;
    since the upright search also starts the casing standing on the table (searches.resting_starts) the
    estimate on the mask as given finds a pose, its depth noise widens the tolerance the mask's readings are
    cut with, and the reading that wins ends 26 mm off (0.21 of the part's diameter): a regression taken
    for the 8 mostly hidden frames the resting starts make right and confident (docs/BENCHMARKS.md). It
    must not be confident: the depth contradicts 38 % of the model's view and three placements fit."""
    frame, r, mask, err = estimate_prompted(GEARBOX, 3, 0, clutter="hidden", pitch_range_deg=(20.0, 50.0), **KINECT)
    assert iou(mask, frame.base_mask()) < 0.6  # the prompted mask holds much of the box in front
    assert r.ok and (not r.confident or err < 0.1), (r.reason, r.reading, err)


def test_a_base_whose_prompt_took_the_object_in_front_is_read_off_what_lies_wholly_in_the_box():
    """Only a strip of a gearbox casing's top shows above a box standing in front of it; the box drawn round
    the strip is mostly filled by the box in front, and the prompt takes that in and hardly any of the
    casing. The box in front runs far out of the prompt's box, the strip does not: what lies wholly in the
    box (hypotheses.in_box) is the casing. On it, the resting starts are screened less what the camera sees
    past them (a hundred starts explain the strip as well) and refined on what nothing stands in front of
    (scoring.unhidden: the box in front hides most of the casing's face towards the camera, and ICP pulled
    the start the wrong way to match it). Before: no pose, "the depth contradicts 74 %"."""
    frame, r, mask, err = estimate_prompted(GEARBOX, 2, 0, clutter="hidden", pitch_range_deg=(20.0, 50.0), **KINECT)
    truth = frame.base_mask()
    assert iou(mask, truth) < 0.4  # the prompted mask is mostly the box in front
    assert r.ok and r.confident and err < 0.1, (r.reason, r.reading, err)
    assert r.reading == "what lies wholly in the box"
    assert iou(r.model_mask, truth) > 0.6


def test_a_round_base_found_only_by_sliding_it_is_not_confident_when_turned():
    """A watering can 30 % hidden at the bench's edge: no start centred on what is seen fits, the upright search
    slides the can over the table, and the pose it ends with is turned 22 degrees about the round body (the
    label 36 mm off) while the right turn, scored from the truth, comes within 0.012 of it. Screening the slid
    starts less what the camera sees past them found that turn and called it confident; a pose found only by
    sliding now has its neighbours tried as a mostly hidden one's are (refine.neighbour_rivals), and the
    result is not confident."""
    frame, r, mask, err = estimate_prompted(DESK, 2, 5, seed=5, noise="gaussian", clutter="bench")
    assert r.ok
    assert not r.confident or err < 0.1, (r.reading, err, doubts(r))


def test_a_twin_turned_half_round_is_not_chosen_over_the_right_pose():
    """A casing behind a box, seen from its open side: the right pose and its half-turned twin (its pins 4 mm
    apart) both fit. Before, the right candidate was compared unpolished (1 mm, 1 degree off) with a polished
    twin, and the twin was reported confident, 72 mm off; compared at their best, the right pose wins."""
    frame, r, mask, err = estimate_prompted(GEARBOX, 1, 1, clutter="hidden", pitch_range_deg=(20.0, 50.0), **KINECT)
    assert r.ok and err < 0.1, (r.reason, err)


@pytest.mark.parametrize("step,im_id", [(3, 2), (3, 5)])
def test_a_nearly_symmetric_hole_punch_is_never_confident_and_wrong(step, im_id):
    """A hole punch (a half turn maps it onto itself but for its grip) with a flat object on it: confident
    only when right."""
    frame, r, mask, err = estimate_prompted(DESK, step, im_id, clutter="bench,stacked", **KINECT)
    assert not (r.ok and r.confident) or err < 0.1, (r.reading, err)


def test_what_lies_on_the_base_does_not_outweigh_the_sides_a_lifted_pose_contradicts():
    """A flat object lying on the casing: the mask as given holds it, and a pose raised onto it explains
    its pixels too, while the camera sees past that pose's sides. A pixel seen past the model weighs more
    than one more pixel explained (hypotheses.CONTRADICTION_WEIGHT), so a reading without the flat object
    (by its colour, or by its height above what the casing can reach) wins, right and confident (before: the
    raised pose, wrong and unconfident)."""
    frame, r, mask, err = estimate_prompted(GEARBOX, 2, 1, clutter="bench,stacked", **KINECT)
    assert iou(mask, frame.base_mask()) < 0.5  # the prompted mask holds much of the flat object
    assert r.ok and r.confident and err < 0.1, (r.reason, r.reading, err)
    assert r.reading.startswith(("without colour", "below the base's height"))  # a reading without the flat object
    assert iou(r.model_mask, frame.base_mask()) > iou(mask, frame.base_mask()) + 0.3


def test_a_plate_as_wide_as_the_base_does_not_win_over_the_reading_without_it(fidget_yaml):
    """An orange plate lying on a fidget and covering most of it: the pose raised onto the plate explains more
    pixels (the plate's) than the right pose explains, even with what the camera sees past it weighed five times;
    but the depth contradicts 15 % of what it shows. A reading the depth does not contradict is kept before one it
    does (pipeline.uncontradicted): without what stands in front, right and confident (before: the raised pose,
    3 mm off the casing and 3 % of the part's diameter off, and not confident)."""
    frame, r, mask, err = estimate_prompted(fidget_yaml, 2, 4, clutter="bench,stacked", **KINECT)
    assert iou(mask, frame.base_mask()) < 0.5  # the prompted mask holds the plate
    assert r.ok and r.confident and err < 0.01, (r.reason, r.reading, err)
    assert r.reading and r.contradiction <= 0.05
    assert iou(r.model_mask, frame.base_mask()) > 0.7


def test_a_plate_lying_tilted_on_the_base_is_left_out_of_the_fit_by_the_settle():
    """A grey plate, the casing's own colour, lies tilted across the gearbox casing, its low end on the casing's top:
    one depth patch with it, so no reading of the mask leaves it out (below the base's height cuts only its high end).
    Fitted with the rest, it tilted the pose 7 degrees: 5.5 mm off against the part's line of 4.9 mm, the camera seeing
    past 13 % of the model. Settled (refine.settle: the depth in front of the model's surface left out, round by
    round), the pose is right; not confident (much of the mask is the plate's), and the depth no longer contradicts
    it. The same frame without the settle is wrong, as before."""
    from dataclasses import replace

    from apose_studio.registration.types import CONFIDENT_CONTRADICTION

    frame, r, mask, err = estimate_prompted(GEARBOX, 2, 3, clutter="bench,stacked", **KINECT)
    assert iou(mask, frame.base_mask()) < 0.4  # the prompted mask holds the plate, a cube and a cylinder
    assert r.ok and err < 0.1, (r.reason, r.reading, err)
    assert [s.name for s in r.stages][-1] == "settled" and r.timings["settle"] > 0
    assert r.contradiction <= CONFIDENT_CONTRADICTION
    _, unsettled, _, err_before = estimate_prompted(GEARBOX, 2, 3, replace(resolve_params("default"), settle=False),
                                                    clutter="bench,stacked", **KINECT)
    assert err_before > 0.1 and unsettled.contradiction > CONFIDENT_CONTRADICTION, err_before


def test_two_readings_that_each_leave_out_one_thing_leave_out_both_together():
    """A desk object under a pink disc with another object standing against it: no single reading of the
    prompted mask leaves both out, and each one's pose explains the frame worse than the mask as given. What two
    readings both keep (hypotheses.both_out: here without what stands in front, and without the second depth
    patch) is estimated too: right and confident (before: 82 mm off, not confident)."""
    frame, r, mask, err = estimate_prompted(DESK, 3, 3, clutter="bench,stacked", **KINECT)
    assert iou(mask, frame.base_mask()) < 0.3
    assert r.ok and r.confident and err < 0.1, (r.reason, r.reading, err)
    assert r.reading.count(", ") == 1  # two readings' names: both left out
    assert iou(r.model_mask, frame.base_mask()) > 0.7


def test_the_readings_side_by_side_give_the_answer_of_one_after_the_other(monkeypatch):
    """The frame above goes through both rounds of readings (four, then what two of them both keep): estimated
    with them side by side on two threads and one after the other, the pose is the same to the last bit, from
    the same reading, judged alike."""
    from apose_studio.registration import side_by_side

    monkeypatch.setattr(side_by_side, "usable_cpus", lambda: 2)
    results = [estimate_prompted(DESK, 3, 3, resolve_params("default", threads=n), clutter="bench,stacked", **KINECT)[1]
               for n in (1, 2)]
    one, two = results
    assert one.reading.count(", ") == 1  # the second round ran
    assert np.array_equal(one.T_world_part, two.T_world_part)
    assert (one.reading, one.confident, one.coverage, one.contradiction, one.spread) == \
        (two.reading, two.confident, two.coverage, two.contradiction, two.spread)


def test_the_mask_as_given_is_searched_freely_only_when_no_reading_of_it_settles_the_frame(monkeypatch):
    """A gearbox under a flat object, prompted by a box: on the mask as given the upright pose does not fit, so the
    free search is due there (it runs when the readings are off). With the readings on, the reading below the base's
    height settles the frame (right and confident) and the free search of the mask as given never runs (before: it
    ran first and lost). On a frame that no reading settles it still runs, once."""
    from apose_studio.registration import pipeline

    runs = []
    free_search = pipeline.better_of_free_search
    monkeypatch.setattr(pipeline, "better_of_free_search", lambda *a, **k: runs.append(1) or free_search(*a, **k))
    stacked = dict(clutter="bench,stacked", **KINECT)
    estimate_prompted(GEARBOX, 3, 3, resolve_params("default", mask_hypotheses=False), **stacked)
    assert runs  # due on the mask as given
    runs.clear()
    _, r, _, err = estimate_prompted(GEARBOX, 3, 3, **stacked)
    assert r.confident and err < 0.1 and r.reading == "below the base's height", (r.reading, err)
    assert not runs
    _, r, _, _ = estimate_prompted(GEARBOX, 3, 1, **stacked)
    assert not r.confident and runs == [1]


def test_the_object_in_front_is_left_out_of_a_mostly_hidden_base():
    """A watering can three quarters hidden behind a box; the box drawn around what is seen of the can takes
    in the box's corner, which stands in front of the can where the two meet. Without the front-most patch
    the pose lies on the can, its mask the can's (before: 211 mm off, fitted to the box). It is not confident:
    the quarter in view leaves the can free to move by more than the 70 mm label on it allows
    (estimation.held_to_part), and indeed the label is 14 mm off (0.19 of its diameter). (Opened in the
    renderer's world frame it was 3.8 mm off, in a capture folder's 26 mm, until the estimate stopped
    depending on the world frame: tests/registration/test_world_frame.py.)"""
    frame, r, mask, err = estimate_prompted(DESK, 2, 0, clutter="hidden", pitch_range_deg=(20.0, 50.0), **KINECT)
    assert iou(mask, frame.base_mask()) < 0.3  # the prompted mask is mostly the box in front
    assert r.ok and err < 0.3, (r.reason, r.reading, err)  # on the can, not the box
    assert not r.confident and "the placement allows" in doubts(r)
    assert r.reading.startswith("without what stands in front"), r.reading  # (since the search for mostly
    # hidden bases, read once more: one depth patch more left out)
    assert iou(r.model_mask, frame.base_mask()) > 0.5


def test_a_duck_label_the_view_pins_down_too_loosely_is_not_confident():
    """A toy duck three quarters hidden: its pose is right by the duck's own measure (3.7 mm ADD against 11 mm)
    but the label on its back lands 8.5 mm off against the label's 7 mm, and the view leaves 4.6 mm of
    freedom. Before, the duck's own allowance (6.7 mm) called it confident; held to the label (3.5 mm) it is
    not."""
    frame, r, mask, err = estimate_prompted(DESK, 4, 2, clutter="hidden", pitch_range_deg=(20.0, 50.0), **KINECT)
    assert r.ok and not r.confident, (r.reading, err, r.spread)
    assert "the placement allows" in doubts(r)


CHECKED = resolve_params("default", colour_check=True, move_depth_to_colour=False)  # the depth's edges compared with
# the colour's after the estimate, the depth left as it is
REAL_DESK = dict(KINECT, noise_sigma_at_05m=0.0005, clutter="bench,stacked,textured", depth_bias_m=0.003,
                 misregistration_px=3.0, distance_range_m=(0.65, 1.2))  # benchmarks/captures.py's `real` row


@pytest.mark.parametrize("im_id", [3, 5])
def test_a_clasp_a_few_millimetres_proud_tells_the_tin_box_from_its_half_turn(im_id):
    """A tin box on a Kinect desk (a 3 mm depth bias, depth 3 px off the colour, noise growing with distance):
    a half turn maps it onto itself but for its clasp and hinge, a few millimetres proud of its sides, less
    than the three sigmas of depth noise within which a pixel counts as confirmed. Before, its right pose
    tied with the half-turned twin (the label 93-133 mm off) and the result was `ambiguous`; compared pixel
    by pixel (which surface the depth lies nearer to), the right pose wins and is confident."""
    frame, r, mask, err = estimate_prompted(DESK, 1, im_id, **REAL_DESK)
    assert r.ok and err < 0.1 and not r.ambiguous and r.confident, (r.reading, err, doubts(r))


def test_a_casing_mostly_hidden_is_found_standing_on_the_table():
    """A gearbox casing behind a box, only its far corner in view, with the renderer's own visible mask (no
    reading of the mask can help): centring the model on that corner left every upright start a third of
    the casing off, and the estimate was 33 mm and 176 degrees off ("the depth contradicts 72 %"). Started
    standing on the table and slid over it (searches.resting_starts), the casing is found: the right
    placement of the part is the result's or, the casing's half turn hiding what tells the two apart, one
    of its alternatives (the result is then ambiguous)."""
    asm = load_assembly(GEARBOX)
    ctx = StepContext(asm, load_parts(asm), 1)
    frame = rendered_frame(GEARBOX, 1, 0, clutter="hidden", pitch_range_deg=(20.0, 50.0), **KINECT)
    truth = frame.base_mask()
    r = estimate_frame(frame, ctx, resolve_params("default"), mask=truth, box=prompt_box(truth))
    assert r.ok, r.reason
    placements = [r.T_world_part] + [c.T_world_part for c in r.alternatives]
    errs = [mssd(T, frame.T_world_part, ctx.part.samples, ctx.part.symmetries) / ctx.part.diameter for T in placements]
    assert min(errs) < 0.1, (errs, doubts(r))
    assert errs[0] < 0.1 or r.ambiguous


@pytest.mark.parametrize("assembly,step,im_id", [("fidget", 2, 3), (DESK, 1, 0)])
def test_a_mostly_hidden_base_that_could_stand_elsewhere_is_not_confident(assembly, step, im_id, request):
    """A fidget casing 4 % visible behind a box (only its gear seen) and a tin three quarters hidden: a pose
    turned 18 degrees, and one 56 mm along the table and half turned, each explains what is seen and the
    depth contradicts nothing of either (it lies behind the box). Both were judged confident and wrong
    (the part 11 and 130 mm off); the pose's neighbours on the table (refine.neighbour_rivals) and the
    chosen candidate's own twins (refine.add_chosen_twins) keep them from it."""
    assembly = request.getfixturevalue("fidget_yaml") if assembly == "fidget" else assembly  # skips without ../shared
    frame, r, mask, err = estimate_prompted(assembly, step, im_id,
                                            clutter="hidden", pitch_range_deg=(20.0, 50.0), **KINECT)
    assert r.ok
    assert not r.confident or err < 0.1, (r.reading, err, doubts(r))


@pytest.mark.parametrize("step,im_id,settings", [
    (2, 5, dict(seed=5, noise="gaussian", clutter="bench")),
    (2, 5, dict(seed=5, noise="realsense", clutter="bench")),
    (3, 5, dict(KINECT, clutter="hidden", pitch_range_deg=(20.0, 50.0))),
])
def test_a_near_round_base_turned_is_not_confident(step, im_id, settings):
    """A watering can on a bench (its body round, its spout and handle a small share of what is seen) and a
    hole punch mostly hidden: a pose turned 47 degrees about the can's axis explains the data as well as the
    right one (score 0.543 against 0.540), the punch turned half round better. The refined upright yaws were
    the four best screened, all neighbours in one basin, so the turn that fits as well was never a candidate
    and the wrong pose was called confident (the labels 45 and 73 mm off). Refined yaws spread round the
    circle (searches.spread_yaws) put the rival in, and the result is not confident."""
    frame, r, mask, err = estimate_prompted(DESK, step, im_id, **settings)
    assert r.ok
    assert not r.confident or err < 0.1, (r.reading, err, doubts(r))


def test_depth_registered_off_the_colour_image_is_moved_back_onto_it():
    """The hole punch on a Kinect desk whose depth lies 3 px off the colour image the box is drawn on: the
    cloud under the mask lies that far sideways, and the label's pose fitted to it 6.0 mm off (against the
    label's 7 mm line), confident without the colour check. The check (estimation.colour_checked) finds the
    depth's edges off the colour's by the renderer's shift, to within a pixel, and holds what that would put
    the pose off against the confidence: with the depth left as it is, not confident, the doubt names the
    remedy. Asked to (`align_depth`), the depth is moved back before the mask and the registration; by
    default (`move_depth_to_colour`) after the first estimate, by the shift the check found, and the pose made
    again: either way the label within 5 mm, and by default confident. Through the API, as a robot cell
    calls it. (Frame 0: on frame 1, moved back by the exact shift since the edges tell the depth's bleed from it,
    the estimate took the mask's readings and ended right but not confident; docs/BENCHMARKS.md.)"""
    from apose_studio import api

    frame = rendered_frame(DESK, 3, 0, **REAL_DESK)
    du, dv = true_shift(frame.depth, rendered_frame(DESK, 3, 0, **{**REAL_DESK, "misregistration_px": 0.0}).depth)
    asm = load_assembly(DESK)
    ctx = StepContext(asm, load_parts(asm), 3)
    box = prompt_box(frame.base_mask())

    def error(est):
        return mssd(est.T_world_part, frame.T_world_part, ctx.part.samples, ctx.part.symmetries) if est.ok else np.inf

    def estimate(**kw):
        return api.estimate_pose(frame.rgb, frame.depth, frame.camera.K, DESK, 3, T_world_camera=frame.T_world_camera,
                                 box=box, **kw)

    checked, unchecked = estimate(move_depth_to_colour=False), estimate(colour_check=False)
    asked, moved = estimate(align_depth=True), estimate()
    found = checked.result.colour_offset_px
    assert abs(found[0] - du) <= 1 and abs(found[1] - dv) <= 1, (found, du, dv)
    assert checked.ok and not checked.confident and "--align-depth" in checked.doubts, checked.doubts
    assert unchecked.result.colour_offset == 0 and np.allclose(unchecked.T_world_part, checked.T_world_part)
    assert max(abs(v) for v in asked.depth_shift_px) >= 2 and asked.result.colour_offset == 0
    assert error(asked) < 0.005 and error(asked) < error(checked) - 0.0015, (error(asked), error(checked))
    # by default the check's own shift moves the depth back after the first estimate, and the pose is made again
    # (its own first estimate's check: within a pixel of the renderer's shift, as the check above)
    assert moved.depth_shift_px == moved.result.depth_moved_px and moved.result.colour_offset == 0
    assert abs(moved.depth_shift_px[0] - du) <= 1 and abs(moved.depth_shift_px[1] - dv) <= 1, (moved.depth_shift_px, du, dv)
    assert error(moved) < 0.005 and error(moved) < error(checked) - 0.0015, (error(moved), error(checked))
    assert moved.confident, moved.doubts


def test_a_shift_the_edges_suggest_before_any_pose_is_estimated_once_and_checked_on_the_depth_as_it_lay(monkeypatch):
    """The hole punch on the Kinect desk of the test above, its depth 3 px off the colour image. The edges suggest the
    shift before any pose, so the depth is moved back by it and estimated, and the check at that pose on the depth as
    it lay confirms the shift (to within a pixel): one
    registration, not two (the estimate on the depth as it lay is not made), and the pose right and confident as
    before. Told a wrong shift instead (the other way, 6 px off in all, beyond what the check calls clear), the
    estimate on that depth finds no shift left, but the check at its pose on the depth as it lay does not find that
    shift: it is not taken, and the depth is moved by the shift the check finds."""
    import apose_studio.estimation as estimation

    frame = rendered_frame(DESK, 3, 4, **REAL_DESK)
    du, dv = true_shift(frame.depth, rendered_frame(DESK, 3, 4, **{**REAL_DESK, "misregistration_px": 0.0}).depth)
    asm = load_assembly(DESK)
    ctx = StepContext(asm, load_parts(asm), 3)
    box = prompt_box(frame.base_mask())
    mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box).mask
    depths = []  # the depth each registration ran on, as its shift from the depth as it lay (None: another)
    registration = estimation.estimate

    def counted(view, *args, **kw):
        moved = [s for s in [(a, b) for a in range(-6, 7) for b in range(-6, 7)]
                 if np.array_equal(view.depth, estimation.shift_image(frame.depth, -s[0], -s[1]))]
        depths.append(moved[0] if moved else None)
        return registration(view, *args, **kw)

    monkeypatch.setattr(estimation, "estimate", counted)
    r = estimate_frame(frame, ctx, resolve_params("default"), mask=mask, box=box)
    err = mssd(r.T_world_part, frame.T_world_part, ctx.part.samples, ctx.part.symmetries)
    assert abs(r.depth_moved_px[0] - du) <= 1 and abs(r.depth_moved_px[1] - dv) <= 1, (r.depth_moved_px, du, dv)
    assert depths == [r.depth_moved_px], depths  # one registration, on the depth moved back
    assert r.confident and err < 0.005 and r.colour_offset == 0, (err, doubts(r))

    wrong = (-r.depth_moved_px[0], -r.depth_moved_px[1])
    suggest = estimation.edges_suggest_shift

    def wrongly(view):  # on the depth as it lay: the wrong shift, alone and confirmed
        look = suggest(view)
        return estimation.EdgeLook((wrong, look.confirmed[1]), (wrong, look.confirmed[1])) \
            if view.depth is frame.depth else look

    monkeypatch.setattr(estimation, "edges_suggest_shift", wrongly)
    depths.clear()
    told_wrong = estimate_frame(frame, ctx, resolve_params("default"), mask=mask, box=box)
    assert depths[0] == wrong and (0, 0) in depths, depths  # tried first, then the depth as it lay
    assert told_wrong.depth_moved_px == r.depth_moved_px, told_wrong.depth_moved_px
    assert np.array_equal(told_wrong.T_world_part, r.T_world_part) and told_wrong.confident
    # the estimate wasted on the wrong shift is counted once, apart; the kept one's own time is in its stages
    assert told_wrong.timings["estimate on the depth moved back"] > 0 and "estimate on the depth moved back" not in r.timings


def test_a_pose_the_depth_may_have_put_off_the_colour_image_is_not_confident():
    """A toy duck on a Kinect desk whose depth lies 3 px off the colour image: its label about 7 mm off, at the
    label's 7 mm line (7.4 mm when the polish ran to its last step, 6.98 mm when it stops at steps under a tenth of a
    voxel), confident without the colour check. With it, the depth's edges lie a few px off the colour's (3.5-5.3 mm
    at its distance), which with the spread is more than the label's allowance: not confident, the doubt says why."""
    frame, r, mask, err = estimate_prompted(DESK, 4, 0, CHECKED, **REAL_DESK)
    assert err > 0.09  # the pose the depth gives lies at the label's line (0.1 of its diameter) or past it
    assert r.ok and r.colour_offset > 0, r.colour_offset
    assert not r.confident and "off the colour image's here" in doubts(r), doubts(r)


def test_a_casing_whose_rim_fools_the_edges_keeps_its_confidence(monkeypatch):
    """A gearbox casing on a plain table seen from above, its depth registered exactly (benchmarks/tune.py's
    fixed protocol, noise-free): its rim is as grey as the table, so along its far outline the colour shows
    no edge but the inner wall's, a wall's thickness inside, and the depth's outline laid onto that finds,
    compared as a shift alone, a clear shift (a few px, several times nearer). With the casing's own creases and inner outlines at its
    pose left out of the comparison (estimation.colour_checked, raycast.own_edges), none: the right pose stays
    confident and the depth is not moved."""
    from apose_studio.estimation import CLEAR_SHIFT_GAIN, CLEAR_SHIFT_MAX_PX
    from apose_studio.geometry import sensor
    from apose_studio.geometry.sensor import SHIFT_MIN_PX, shift_evidence

    frame = rendered_frame(GEARBOX, 2, 6, seed=11, noise="none", base_pose="fixed")
    truth = frame.base_mask()
    box = prompt_box(truth)
    with monkeypatch.context() as m:  # compared as a shift alone (a bleed of the outline explains a part of it too)
        m.setattr(sensor, "BLEED_MAX_PX", 0)
        (du, dv), ratio = shift_evidence(frame.rgb, frame.depth, box)
    assert SHIFT_MIN_PX <= max(abs(du), abs(dv)) <= CLEAR_SHIFT_MAX_PX and ratio < CLEAR_SHIFT_GAIN, ((du, dv), ratio)
    asm = load_assembly(GEARBOX)
    ctx = StepContext(asm, load_parts(asm), 2)
    r = estimate_frame(frame, ctx, resolve_params("default"), mask=truth, box=box)
    err = mssd(r.T_world_part, frame.T_world_part, ctx.part.samples, ctx.part.symmetries) / ctx.part.diameter
    assert r.ok and err < 0.02 and r.confident, (err, doubts(r))
    assert r.colour_offset == 0 and r.depth_moved_px == (0, 0), r.colour_offset_px


def test_a_shift_the_edges_half_suggest_on_depth_registered_exactly_costs_nothing(monkeypatch):
    """A gearbox frame registered exactly, under Kinect-like noise: near surfaces bleed into far ones and
    projector shadows hide one side, and the depth's edges lie nearest the colour's 4 px off (27 % nearer:
    enough for --align-depth's gate) when compared as a shift alone. With the bleed in the comparison
    (geometry.sensor.shift_and_bleed) no shift at all; and it was never a clear one (at most 4 px along each axis
    and 35 % nearer), so with the colour check on the confident, right pose stays confident."""
    from apose_studio.geometry import sensor
    from apose_studio.geometry.sensor import depth_colour_shift

    frame, r, mask, err = estimate_prompted(GEARBOX, 1, 5, CHECKED, clutter="bench", **KINECT)
    with monkeypatch.context() as m:  # compared as a shift alone: the loose gate's; with the bleed, none
        m.setattr(sensor, "BLEED_MAX_PX", 0)
        assert depth_colour_shift(frame.rgb, frame.depth, prompt_box(frame.base_mask())) != (0, 0)
    assert depth_colour_shift(frame.rgb, frame.depth, prompt_box(frame.base_mask())) == (0, 0)
    assert r.ok and err < 0.02 and r.colour_offset == 0 and r.confident, (err, r.colour_offset_px, doubts(r))


@pytest.mark.parametrize("step,im_id", [(1, 4), (2, 2)])
def test_depth_bled_round_its_outlines_is_not_moved_as_if_registered_off(step, im_id):
    """A gearbox casing on a Kinect bench, its depth registered exactly but every near surface 2 px wider in depth
    than in colour (`--bleed 2`, benchmarks/captures.py's `bleed` row): the outlines the depth shows lie above and
    right of the colour's (the projector's shadow leaves none on the left, the table none at the foot), as a shift
    up and right would put them. Taken for a shift, the depth was moved back by (2, -3) and (3, -4) px before the
    estimate and the casing came out confident, 10.4 and 10.0 % of its part's diameter off (checked with the
    bleed left out of the search). The edges are now read as a bleed and a shift together
    (geometry.sensor.shift_and_bleed): the depth is left where it is and the pose is right."""
    frame, r, mask, err = estimate_prompted(GEARBOX, step, im_id, clutter="bench", bleed_px=2, **KINECT)
    assert r.depth_moved_px == (0, 0) and r.ok and err < 0.1, (r.depth_moved_px, err, doubts(r))


def test_a_base_turned_the_view_cannot_tell_is_reported_when_the_part_goes_alike():
    """A planetary motor with its sun gear on a bench, its connector hidden: the gear goes to the same place
    whichever way the motor is turned (the gear is symmetric), and the estimate chose the motor half turned
    (38 mm off by its own ADD), confident about the gear. The motor's other turns that place the gear alike and
    fit as well are now reported (`base_alternatives`; the truth's turn among them) and `base_confident` is
    false, as a check scoring the motor's own pose needs; `confident` (the gear's placement) is unchanged."""
    planetary = SAMPLES / "planetary_reducer" / "assembly.yaml"
    frame, r, mask, err = estimate_prompted(planetary, 2, 5, seed=5, noise="none", clutter="bench")
    assert r.ok and r.confident and err < 0.1, (err, doubts(r))
    turned = se3.rotation_angle_deg(r.T_world_base[:3, :3].T @ frame.T_world_base[:3, :3])
    assert turned > 90  # the motor as the estimate has it
    assert not r.base_confident and r.base_alternatives
    assert min(se3.rotation_angle_deg(A[:3, :3].T @ frame.T_world_base[:3, :3]) for A in r.base_alternatives) < 3


def test_a_base_whose_view_tells_its_turn_stays_base_confident():
    """The gearbox casing (its input-shaft boss breaks its symmetry): confident and base_confident alike."""
    frame, r, mask, err = estimate_prompted(GEARBOX, 1, 1, seed=5, noise="none", clutter="bench")
    assert r.ok and r.confident and err < 0.1
    assert r.base_confident and not r.base_alternatives


def test_a_tracked_frame_keeps_the_depth_shift_its_detection_found():
    """A camera's depth lies 3 px off its colour image on every frame (a sensor's registration does not change):
    the detection finds the shift by the colour's edges and estimates on the depth moved back; the frames
    tracked after it are moved back by as much, so the tracked pose stays where the detection put it (on the
    depth as given it would slide the 4-5 mm the shift puts the cloud sideways)."""
    from apose_studio.estimation import Tracker

    frame = rendered_frame(DESK, 4, 1, **REAL_DESK)
    asm = load_assembly(DESK)
    ctx = StepContext(asm, load_parts(asm), 4)
    params = resolve_params("default")
    box = prompt_box(frame.base_mask())
    mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box).mask
    tracker = Tracker(ctx, params, lambda f, b: estimate_frame(f, ctx, params, mask=mask, box=box))
    first = tracker.step(frame)
    assert first.mode == "detected" and first.result.confident and first.result.depth_moved_px != (0, 0), doubts(first.result)
    again = tracker.step(frame)  # the same view again: nothing moved
    assert again.mode == "tracked" and again.result.depth_moved_px == first.result.depth_moved_px
    moved = np.linalg.norm(again.result.T_world_part[:3, 3] - first.result.T_world_part[:3, 3])
    assert moved < 0.001, moved


@pytest.mark.parametrize("step, im_id", [(1, 3), (3, 4)])
def test_a_camera_holding_still_over_a_base_with_a_flat_object_on_it_keeps_tracking(step, im_id):
    """A desk object with a flat one lying on it, the camera still: tracked from the detection's pose, the flat
    object's depth lay within the tracker's reach of the base's predicted top and was registered as the base's.
    Before, frame 1/3's pose was pulled 22 mm up ("the base moved 22 mm since the last frame") and 3/4's judged
    "only 80 % of the target lies near the model": re-detected on every frame, 0.5-1.5 s each instead of ~15 ms. Now
    the depth where something stood over the base in the frame before is left out (registration.track.hidden_points):
    tracked, the pose where the detection put it."""
    from apose_studio.estimation import Tracker

    frame = rendered_frame(DESK, step, im_id, **REAL_DESK)
    asm = load_assembly(DESK)
    ctx = StepContext(asm, load_parts(asm), step)
    params = resolve_params("default")
    box = prompt_box(frame.base_mask())
    tracker = Tracker(ctx, params, lambda f, b: estimate_frame(
        f, ctx, params, mask=prompted_mask(f.rgb, f.depth, f.camera, box=box).mask, box=box))
    first = tracker.step(frame)
    assert first.mode == "detected" and first.result.confident, doubts(first.result)
    for _ in range(2):  # the same view again: nothing moved
        again = tracker.step(frame)
        assert again.mode == "tracked", again.lost_because
        moved = np.linalg.norm(again.result.T_world_part[:3, 3] - first.result.T_world_part[:3, 3])
        assert moved < 0.001 and again.result.confident, (moved, doubts(again.result))


def test_a_true_shift_that_a_bleed_would_explain_is_held_against_the_confidence_not_taken_for_a_bleed():
    """The path an outside tester's capture took (its depth truly some (-2, -3) px off, the way its outlines bled),
    in a render: a desk frame whose depth lies 3 px right of the colour image. The edges compared as a shift alone
    read (4, -2); beside a bleed they need no shift; the model's outline at the pose, moved back by the shift, lies
    neither clearly nearer the colour's edges nor as near as it is (estimation.colour_checked, OUTLINE_BLEED,
    CLEAR_SHIFT_GAIN). The shift is then held against the confidence and the doubt says the edges cannot tell a
    shift from a bleed; the depth is not moved (a shift a pixel or two off the truth would move the pose as far).
    Taken for a bleed, nothing would have been held against the pose: the capture's label came out confident,
    7.6 mm off against its 7.2 mm line."""
    frame, r, mask, err = estimate_prompted(DESK, 2, 3, **REAL_DESK)
    du, dv = true_shift(frame.depth, rendered_frame(DESK, 2, 3, **{**REAL_DESK, "misregistration_px": 0.0}).depth)
    assert (du, dv) == (3, 0)  # the premise: registered off, along the way a Kinect's outlines bleed (right)
    assert r.ok and r.colour_offset_bleed and r.colour_offset > 0 and r.depth_moved_px == (0, 0)
    assert abs(r.colour_offset_px[0] - du) <= 1, (r.colour_offset_px, du, dv)
    assert not r.confident and "the edges cannot tell which" in doubts(r), doubts(r)
    assert err < 0.1  # right: the doubt is honest, not a wrong pose's
