"""A base that is a region of a large part (`roi`): a rocker-arm seat of the engine-head sample, prompted by a box
around it on a cluttered bench, through the CLI as a user runs it. The truth is the renderer's (its pose and its
visible mask of the head); the box comes from ray casts of the region and of the whole head at the true pose."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from apose_studio.assembly.mesh import load_parts
from apose_studio.data.dataset import Dataset
from apose_studio.geometry import metrics

from ..conftest import SAMPLES, region_box

APOSE = [sys.executable, "-m", "apose_studio.cli.commands"]
ENGINE = SAMPLES / "engine_head" / "assembly.yaml"


def run(*args):
    return subprocess.run([*APOSE, *map(str, args)], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def engine(tmp_path_factory):
    """Seats 1 (a corner of the head) and 6 (the other row) seen 0.45-0.8 m away on a cluttered bench, RealSense-like."""
    out = tmp_path_factory.mktemp("engine") / "ds"
    r = run("render", ENGINE, "--out", out, "--frames", "2", "--steps", "1,6", "--clutter", "bench", "--noise",
            "realsense", "--distance-range", "0.45,0.8", "--seed", "5", "-q")
    assert r.returncode == 0, r.stderr
    return Dataset(out)


def seat_box(ds: Dataset, step: int, im_id: int):
    frame = ds.frame(step, im_id)
    return frame, region_box(frame, ds.assembly)


@pytest.mark.parametrize("step", [1, 6])
def test_a_seat_of_an_engine_head_is_placed_right_and_confident_from_a_box(engine, step):
    models = load_parts(engine.assembly)
    arm = models[engine.assembly.steps[step - 1].part]
    for im_id in engine.image_ids(step):
        frame, box = seat_box(engine, step, im_id)
        r = run("estimate", engine.root, "--step", step, "--frame", im_id, "--box", ",".join(map(str, box)), "--json")
        assert r.returncode == 0, r.stderr
        doc = json.loads(r.stdout)
        assert doc["ok"] and doc["confident"], (im_id, doc.get("doubts"), doc.get("reason"))
        T = np.asarray(doc["T_world_part"])
        err = metrics.mssd(T, frame.T_world_part, arm.samples, arm.symmetries)
        assert err < 0.1 * arm.diameter, (im_id, err)


def test_a_seat_is_registered_as_its_region_not_as_the_head(engine):
    """With the roi taken off (the whole head as the base), the same box gives no confident pose: the seat's box
    holds a small piece of a 360 mm head. The region is what makes the seat work."""
    from apose_studio.estimation import StepContext, estimate_frame
    from apose_studio.masks.prompt import prompted_mask
    from apose_studio.registration import resolve_params

    asm = engine.assembly
    whole = replace(asm, parts={k: replace(p, roi=None) for k, p in asm.parts.items()})
    params = resolve_params("default")
    frame, box = seat_box(engine, 1, 0)
    for a, region in ((asm, True), (whole, False)):
        ctx = StepContext(a, load_parts(a), 1)
        mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box, region=region).mask if region else \
            prompted_mask(frame.rgb, frame.depth, frame.camera, box=box).mask
        r = estimate_frame(frame, ctx, params, mask=mask, box=box)
        err = metrics.mssd(r.T_world_part, frame.T_world_part, ctx.part.samples, ctx.part.symmetries) if r.ok else np.inf
        if region:
            assert r.ok and r.confident and err < 0.1 * ctx.part.diameter
        else:
            assert not (r.ok and r.confident and err < 0.1 * ctx.part.diameter)


def test_a_click_on_a_region_is_refused_with_the_fix(engine):
    frame, box = seat_box(engine, 1, 0)
    r = run("estimate", engine.root, "--step", 1, "--frame", 0, "--point", f"{(box[0] + box[2]) // 2},{(box[1] + box[3]) // 2}")
    assert r.returncode == 2 and "region of a larger part" in r.stderr and "draw a box around the region" in r.stderr, \
        r.stderr


def test_rendered_scenes_hold_the_head_once(engine):
    """The eight seats are regions of one head: a step's scene draws the head once (its seat's obj id), not a head
    per seat standing about the bench as the instances of a whole part do."""
    gt = json.loads((engine.root / "test" / "000001" / "scene_gt.json").read_text())["0"]
    ids = [o["obj_id"] for o in gt]
    info = json.loads((engine.root / "test" / "000001" / "scene_assembly.json").read_text())
    assert ids.count(info["base_obj_ids"][0]) == 1 and info["instance_obj_ids"] == [info["base_obj_ids"][0]]
    assert sorted(ids) == sorted([*info["base_obj_ids"], info["part_obj_id"]])


def test_a_seat_is_tracked_as_the_camera_closes_in(tmp_path):
    """An eye-in-hand camera approaching seat 1 (Kinect-like, cluttered): from a confident estimate on the box round
    the seat, the frames are followed (tracked, or estimated anew from the box where the tracker lets go), most of
    them tracked right and confident, and none confident and wrong (where the seat is small and far, the first
    estimate is 72 mm off and said not confident: the rest of the head stands where the camera sees the bench)."""
    from apose_studio.assembly.model import load_assembly
    from apose_studio.estimation import Tracker, estimate_frame, step_context
    from apose_studio.masks.prompt import prompted_mask
    from apose_studio.params import resolve_params
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    from ..conftest import mssd_to_truth

    out = tmp_path / "approach"
    render_dataset(load_assembly(ENGINE), out, RenderSettings(frames=8, trajectory="approach", noise="kinect",
                                                              clutter=("bench",), seed=4, distance_range_m=(0.45, 0.8)),
                   steps=[1], progress=False)
    ds = Dataset(out)
    asm, ctx = step_context(ds.assembly, 1)
    params = resolve_params("default", asm.registration)

    def detect(frame, box):
        box = region_box(frame, ds.assembly)
        mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box, region=True).mask
        return estimate_frame(frame, ctx, params, mask=mask, box=box)

    tracker = Tracker(ctx, params, detect)
    tracked_right = 0
    for im_id in ds.image_ids(1):
        frame = ds.frame(1, im_id)
        s = tracker.step(frame)
        r = s.result
        right = r.ok and mssd_to_truth(r.T_world_part, frame.T_world_part, ENGINE, ctx.view.part) < 0.1 * ctx.part.diameter
        assert right or not (r.ok and r.confident), (im_id, s.mode)
        tracked_right += s.mode == "tracked" and right and r.confident
    assert tracked_right >= 5, tracked_right
    # `apose track` as the issue spells it, no prompt: the box round the seat from the truth (every frame had been
    # 'not found: give a box')
    r = run("track", out, "--step", 1, "--json", tmp_path / "track.json")
    assert r.returncode == 0 and "0 confident and wrong" in r.stdout, r.stdout + r.stderr
    doc = json.loads((tmp_path / "track.json").read_text())
    assert sum(f["mode"] == "tracked" for f in doc["frames"]) >= 5, [f["mode"] for f in doc["frames"]]


def test_a_box_beside_the_head_gives_no_confident_seat(engine):
    """A seat's box drawn on the bench beside the head (table, perhaps clutter): the region laid on the table fits the
    table's points (its pad's top is flat), but its deck and sides lie below the table top, which hides them; the
    pose is not called confident (`sunk`). Before the check, such a pose was confident 411 mm off."""
    from apose_studio.estimation import StepContext, estimate_frame
    from apose_studio.masks.prompt import prompted_mask
    from apose_studio.registration import resolve_params

    asm = engine.assembly
    ctx = StepContext(asm, load_parts(asm), 1)
    params = resolve_params("default")
    tried = 0
    for im_id in engine.image_ids(1):
        frame, (x0, y0, x1, y1) = seat_box(engine, 1, im_id)
        w, h = x1 - x0, y1 - y0
        head = frame.base_mask()
        H, W = head.shape
        for top, left in [(t, x) for t in range(0, H - h, h // 2) for x in range(0, W - w, w // 2)]:
            box = (left, top, left + w, top + h)
            if head[max(top - 20, 0):top + h + 20, max(left - 20, 0):left + w + 20].any():
                continue  # the head (or near it): not beside it
            mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box, region=True).mask
            r = estimate_frame(frame, ctx, params, mask=mask, box=box)
            tried += 1
            assert not (r.ok and r.confident), (im_id, box)
            if tried >= 3:
                return
    assert tried, "no box beside the head in these renders"


def test_every_seat_of_the_head_is_found_without_a_prompt(engine):
    """`--instances all` on step 1 (seat 1): every seat of the head the camera sees well is an instance, its arm placed
    as step 1 places it on seat 1, and no confident instance is anywhere else. The truth: the head's true pose
    moved by the shift between the seats' roi centres (the file's, not the estimator's look-alike search)."""
    from apose_studio.assembly.mesh import load_parts as parts_of

    asm = engine.assembly
    models = parts_of(asm)
    arm = models["arm_1"]
    own = np.asarray(asm.parts["seat_1"].roi.center)
    for im_id in engine.image_ids(1):
        frame = engine.frame(1, im_id)
        r = run("estimate", engine.root, "--step", 1, "--frame", im_id, "--instances", "all", "--json")
        assert r.returncode in (0, 1), r.stderr
        found = json.loads(r.stdout)["instances"]
        truths = []
        for k in range(1, 9):
            S = np.eye(4)
            S[:3, 3] = np.asarray(asm.parts[f"seat_{k}"].roi.center) - own
            truths.append(frame.T_world_base @ S @ asm.steps[0].T_base_part)
        near = [[metrics.mssd(np.asarray(f["T_world_part"]), T, arm.samples, arm.symmetries) < 0.1 * arm.diameter
                 for T in truths] for f in found]
        assert not [f for f, n in zip(found, near) if f["confident"] and not any(n)]  # none confident elsewhere
        assert sum(any(n) and f["confident"] for f, n in zip(found, near)) >= 6, (im_id, len(found))


def test_a_box_round_the_neighbouring_seat_gives_no_confident_pose(engine):
    """The seats look alike: a box drawn round seat 2 while step 1 (seat 1) is estimated fits seat 1's region there,
    80 mm off. The rest of the head at that pose overhangs the real head's end, where the camera sees the bench:
    not confident (`body_past`). Before the check, such a pose was confident 79 mm off."""
    from apose_studio.estimation import StepContext, estimate_frame
    from apose_studio.masks.prompt import prompted_mask
    from apose_studio.registration import resolve_params

    asm = engine.assembly
    ctx = StepContext(asm, load_parts(asm), 1)
    params = resolve_params("default")
    for im_id in engine.image_ids(1):
        frame = engine.frame(1, im_id)
        box = region_box(replace(frame, step=2), asm)  # seat 2: a region of the same head, at the head's pose
        mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box, region=True).mask
        r = estimate_frame(frame, ctx, params, mask=mask, box=box)
        err = metrics.mssd(r.T_world_part, frame.T_world_part, ctx.part.samples, ctx.part.symmetries) if r.ok else np.inf
        assert not (r.ok and r.confident and err > 0.1 * ctx.part.diameter), (im_id, err, r.body_past)


def test_a_plain_region_is_never_confident(engine):
    """Seat 1's roi moved to a flat patch of the deck between the rows: the patch slides along itself, so no box round
    it gives a confident pose, and the doubt says why (a plain region)."""
    from apose_studio.assembly.roi import Roi
    from apose_studio.estimation import StepContext, estimate_frame
    from apose_studio.masks.prompt import prompted_mask
    from apose_studio.registration import resolve_params
    from apose_studio.registration.types import doubts

    asm = engine.assembly
    parts = dict(asm.parts)
    parts["seat_1"] = replace(parts["seat_1"], roi=Roi("box", (0.0, 0.0, 0.084), size=(0.07, 0.03, 0.016)))
    flat = replace(asm, parts=parts)
    ctx = StepContext(flat, load_parts(flat), 1)
    assert ctx.base.region.plain
    params = resolve_params("default")
    for im_id in engine.image_ids(1):
        frame = engine.frame(1, im_id)
        box = region_box(frame, flat, margin=10)
        mask = prompted_mask(frame.rgb, frame.depth, frame.camera, box=box, region=True).mask
        r = estimate_frame(frame, ctx, params, mask=mask, box=box)
        assert not (r.ok and r.confident)
        assert not r.ok or "plain region" in doubts(r)


def test_estimate_and_eval_on_a_rendered_region_take_the_box_round_it_from_the_truth(engine, tmp_path):
    """On a rendered frame the truth masks the whole head: for a seat, `apose estimate` without a prompt and `apose
    eval --mask box|gt` take the box round what is seen of the seat (the region ray-cast at the true pose) as a user's
    box, and find the seat (before, every frame was refused: 'give a box')."""
    r = run("estimate", engine.root, "--step", 1, "--frame", 0, "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["ok"] and doc["confident"] and doc["mask"]["source"].startswith("box"), doc.get("reason")
    assert doc["mask"]["prompt_source"] == "box round the region from the ground truth"
    for mask in ("gt", "box"):  # asked for by name (a newcomer's --mask gt had been refused: 'and --box/--point')
        r = run("estimate", engine.root, "--step", 1, "--frame", 0, "--mask", mask)
        assert r.returncode == 0 and "mask: box round the region from the ground truth" in r.stdout, r.stdout + r.stderr
    r = run("eval", engine.root, "--mask", "box", "--steps", "1", "--json", tmp_path / "eval.json")
    assert r.returncode == 0, r.stderr
    step = json.loads((tmp_path / "eval.json").read_text())["steps"][0]
    assert step["recall_mssd"] == 1.0 and step.get("mask_iou") is None


def test_a_place_too_small_to_prompt_at_the_image_border_is_left_out(engine, monkeypatch):
    """`--instances all` draws a box round each place of the region that the camera sees; a place at the image's corner
    showing 2 x 2 pixels made a box the prompt refuses, and the whole call stopped with a traceback
    (benchmarks/seats.py --instances). Such a place is left out; the others are still found."""
    from apose_studio import estimation
    from apose_studio.estimation import StepContext
    from apose_studio.registration import resolve_params

    frame = engine.frame(1, 0)
    ctx = StepContext(engine.assembly, load_parts(engine.assembly), 1)
    real = estimation.region_in_front
    places = []

    def corner_after_the_first(region, T, z_body, fr):  # every place after the first shows its corner pixels only
        places.append(1)
        seen = real(region, T, z_body, fr)
        if len(places) == 1:
            return seen
        corner = np.zeros_like(seen)
        corner[-2:, -2:] = True
        return corner

    monkeypatch.setattr(estimation, "region_in_front", corner_after_the_first)
    found = estimation.estimate_instances(frame, ctx, resolve_params("default"))
    assert len(places) == 8 and len(found) == 1 and found[0].result.ok, (len(places), len(found))



def test_a_head_turned_half_round_is_not_confirmed_by_its_own_cut(tmp_path):
    """Step 8, frame 4 of benchmarks/seats.py's renders: the head, cut by the image's right and bottom borders, came out
    of its second look turned half round onto its near-symmetric twin, confident, when that look refitted the pose
    alone on the cut; its seat_8 place lay 102 mm from every seat and was confident. The full second look compares the
    twins on the cut: every confident instance places the arm at one of the seats."""
    from apose_studio.estimation import StepContext, estimate_instances
    from apose_studio.registration import resolve_params

    out = tmp_path / "ds"
    r = run("render", ENGINE, "--out", out, "--frames", "6", "--steps", "8", "--clutter", "bench", "--noise",
            "realsense", "--distance-range", "0.45,0.8", "--seed", "5", "-q")
    assert r.returncode == 0, r.stderr
    ds = Dataset(out)
    asm = ds.assembly
    ctx = StepContext(asm, load_parts(asm), 8)
    frame = ds.frame(8, 4)
    own = np.asarray(asm.parts["seat_8"].roi.center)
    truths = []
    for k in range(1, 9):
        S = np.eye(4)
        S[:3, 3] = np.asarray(asm.parts[f"seat_{k}"].roi.center) - own
        truths.append(frame.T_world_base @ S @ ctx.view.T_base_part)
    d = ctx.part.diameter
    found = estimate_instances(frame, ctx, resolve_params("default", asm.registration))
    near = [[metrics.mssd(i.result.T_world_part, T, ctx.part.samples, ctx.part.symmetries) < 0.1 * d for T in truths]
            for i in found if i.result.ok]
    confident = [i.result.confident for i in found if i.result.ok]
    assert not [n for n, c in zip(near, confident) if c and not any(n)]  # none confident at no seat
    assert sum(c and any(n) for n, c in zip(near, confident)) >= 4, (len(found), confident)


def test_an_ambiguous_seat_keeps_its_second_look(engine, monkeypatch):
    """An ambiguous result that fits gets no second look (pipeline.estimate_mask), but a region's does: its mask is the
    box's depth, much of it the rest of the head, which the cut takes out (on the seats under Kinect-like noise that
    look made right, ambiguous views confident: benchmarks/seats.py)."""
    from apose_studio.estimation import StepContext, estimate_view
    from apose_studio.masks.prompt import box_depth
    from apose_studio.registration import pipeline, resolve_params
    from apose_studio.registration.types import View

    frame, box = seat_box(engine, 1, 0)
    ctx = StepContext(engine.assembly, load_parts(engine.assembly), 1)
    looks = []
    second_look, judged = pipeline.second_look, pipeline.judged
    monkeypatch.setattr(pipeline, "second_look", lambda r, *a, **k: looks.append(r) or second_look(r, *a, **k))
    monkeypatch.setattr(pipeline, "judged", lambda r, *a, **k: replace(judged(r, *a, **k), ambiguous=True))
    params = resolve_params("default", engine.assembly.registration, mask_hypotheses=False)
    estimate_view(replace(View.of(frame, box_depth(frame.depth, box)), box=box), ctx, params)
    assert looks and all(r.ambiguous for r in looks) and any(r.fits for r in looks), [(r.fits, r.ok) for r in looks]
