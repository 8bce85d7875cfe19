"""`apose track`: a step's pose through a sequence of frames (a dataset from `apose render --trajectory`, or a
ROS 2 recording in MCAP), each frame tracked from the one before (estimation.Tracker), detected anew where
tracking loses the base; a line per frame and a summary (with the truth's errors where the dataset has
them). `apose export-mcap`: a rendered step as such a recording."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from apose_studio.assembly.model import load_assembly
from apose_studio.cli.common import check_output_file, params_of, parse_prompt
from apose_studio.data.dataset import Dataset, Frame, write_capture, write_json
from apose_studio.data.realsense import live_serial
from apose_studio.data.recording import MAX_SIDE, is_recording, open_recording, write_recording
from apose_studio.data.sources import open_frames
from apose_studio.errors import AposeError
from apose_studio.estimation import (
    TRACK_MODES,
    MaskRequest,
    Tracker,
    array_mask,
    estimate_view,
    find_mask,
    region_truth_prompt,
    step_context,
)
from apose_studio.evaluate import score_frame
from apose_studio.registration.types import View


def open_sequence(args):
    """(the assembly, the frames to track in order (an iterator: --first/--count), how many (None: a live camera
    until --count or Ctrl-C)) of a rendered dataset, a recording or a live RealSense (`realsense[:SERIAL]`)."""
    live, serial = live_serial(args.input)
    if live or is_recording(args.input):
        if not args.assembly:
            raise AposeError(f"{args.input}: a {'camera' if live else 'recording'} has no assembly of its own; give "
                             "--assembly A.yaml (and --step)")
        asm = load_assembly(args.assembly)
    if live:
        from apose_studio.data.realsense import open_realsense

        cam = open_realsense(serial)

        def stream():
            try:
                k = 0
                while not args.count or k < args.count:
                    yield cam.next_frame()
                    k += 1
            finally:
                cam.close()
        return asm, stream(), args.count or None
    if is_recording(args.input):
        rec = open_recording(args.input)
        if rec.unpaired:
            print(f"note: {rec.unpaired} colour images without a depth image within 20 ms are left out")
        ids = list(range(args.first, len(rec)))
        player = rec.player()  # one pass over the file

        def get(im_id):
            return player.frame(im_id)
    else:
        src = open_frames(args.input)
        if not isinstance(src, Dataset):
            raise AposeError(f"{args.input}: `apose track` follows a sequence of frames: give a dataset folder from "
                             "`apose render --trajectory`, a ROS 2 recording (.mcap) or `realsense`; a capture folder "
                             "holds one frame: use `apose estimate`")
        if args.step not in src.steps:
            raise AposeError(f"{src.root}: step {args.step} was not rendered; rendered steps: "
                             f"{', '.join(map(str, src.steps))}")
        ids = [i for i in src.image_ids(args.step) if i >= args.first]
        asm = load_assembly(args.assembly) if args.assembly else src.assembly

        def get(im_id):
            return src.frame(args.step, im_id)
    if not ids:
        raise AposeError(f"{args.input}: no frames from --first {args.first}")
    ids = ids[:args.count] if args.count else ids
    return asm, (get(i) for i in ids), len(ids)


def cmd_track(args) -> int:
    asm, frames, count = open_sequence(args)
    if args.json:
        check_output_file(Path(args.json), "--json", [args.input])
    asm, ctx = step_context(asm, args.step)
    params = params_of(args, asm.registration)
    ctx.base.warm_up(params)
    request = MaskRequest(args.mask, *(parse_prompt(args, flag) for flag in ("box", "point")))

    first: list[int] = []  # the first frame's im_id, once it is read

    def detect(frame: Frame, box):
        """The first frame's mask as asked; after a loss, a box prompt where the base was last seen. A region on a
        rendered frame with no prompt of the user's: the box round it from the truth (as `apose estimate`; the
        truth masks its whole part, and every frame had been 'not found: give a box')."""
        if box is None and not (frame.im_id == first[0] and (request.box or request.point)):
            truth = region_truth_prompt(frame, ctx, request.source or "gt")
            if truth is not None:
                return estimate_view(replace(View.of(frame, truth[0]), box=truth[1]), ctx, params, args.orientation_prior)
        if box is not None:
            mask, _ = array_mask(frame.rgb, frame.depth, frame.camera, box=box, region=ctx.base.region is not None)
        elif frame.im_id == first[0]:
            mask, _ = find_mask(frame, request, asm, args.input, region=ctx.base.region is not None)
        else:  # a prompt is drawn on the first frame; a later one with nothing to start from uses the data's masks
            mask, _ = find_mask(frame, replace(request, box=None, point=None), asm, args.input)
        prompt = box if box is not None else request.box if frame.im_id == first[0] else None
        return estimate_view(replace(View.of(frame, mask), box=prompt), ctx, params, args.orientation_prior)

    tracker = Tracker(ctx, params, detect)
    rows: list = []
    print(f"tracking step {args.step} ({ctx.part.id} on {'+'.join(ctx.view.base)}) through "
          f"{f'{count} frames' if count else 'the frames (Ctrl-C stops)'} of {args.input}")
    print(f"{'frame':>5}  {'how':<11} {'ms':>7}  {'confident':<9}  {'error mm':>8}  note")
    try:
        for frame in frames:
            first[:] = first or [frame.im_id]
            rows.append(_track_one(args, tracker, ctx, frame))
    except KeyboardInterrupt:  # a live camera: the summary of what was tracked
        print("stopped")
    summary = summarise(rows, ctx.part.diameter)
    print(summary_text(summary))
    if args.json:
        write_json(Path(args.json), {"step": args.step, "part": ctx.part.id, "base": list(ctx.view.base),
                                     "summary": summary, "frames": [frame_json(s, e) for s, e in rows]})
        print(f"per-frame results: {args.json}")
    return 0 if summary["confident"] else 1


def _track_one(args, tracker: Tracker, ctx, frame: Frame) -> tuple:
    """One frame tracked and its line printed: (TrackStep, MSSD against the truth or None)."""
    if frame.part is None:  # a recorded or live frame: the step's parts, no truth
        frame = replace(frame, base=tuple(ctx.view.base), part=ctx.view.part, step=args.step)
    s = tracker.step(frame)
    r = s.result
    err = None
    if frame.T_world_part is not None and r.ok:
        err = score_frame(frame, r, ctx.part, None, ctx.base.symmetries).mssd_mod_base_sym
    note = s.lost_because if s.mode in ("re-detected", "lost") else ("" if r.ok else r.reason)
    if s.advice is not None:  # ambiguous, nothing tracked: where to look from (fused when a frame comes from there)
        t = s.advice.T_world_camera[:3, 3] * 1000
        note = f"ambiguous: look from ({t[0]:.0f}, {t[1]:.0f}, {t[2]:.0f}) mm (world); {note}"
    if not args.quiet:
        print(f"{frame.im_id:>5}  {s.mode:<11} {s.seconds * 1000:7.1f}  {'yes' if r.confident else 'no':<9}  "
              f"{'' if err is None else f'{err * 1000:8.2f}':>8}  {note[:100]}")
    return s, err


def summarise(rows: list, part_diameter: float) -> dict:
    """Counts by mode, times of tracked and detected frames (ms), and against the truth (where known): right
    (MSSD within 10 % of the part's diameter, exact twins of the base forgiven) and confident-and-wrong."""
    modes = [s.mode for s, _ in rows]
    tracked = np.array([s.seconds for s, _ in rows if s.mode == "tracked"]) * 1000
    detected = np.array([s.seconds for s, _ in rows if s.mode != "tracked"]) * 1000
    known = [(s, e) for s, e in rows if e is not None]
    out = {"frames": len(rows), **{m.replace(" ", "_").replace("-", "_"): modes.count(m) for m in TRACK_MODES},
           "confident": sum(s.result.confident for s, _ in rows),
           "tracked_ms": _pct(tracked), "detected_ms": _pct(detected)}
    if known:
        right = [e < 0.1 * part_diameter for _, e in known]
        out["right"] = int(sum(right))
        out["confident_and_wrong"] = int(sum(s.result.confident and not ok for (s, _), ok in zip(known, right)))
        tracked_err = [e for s, e in known if s.mode == "tracked"]
        out["tracked_error_mm"] = _pct(np.array(tracked_err) * 1000)
    return out


def _pct(v: np.ndarray) -> dict:
    return {"n": int(len(v)), "median": float(np.median(v)) if len(v) else None,
            "p95": float(np.percentile(v, 95)) if len(v) else None}


def summary_text(s: dict) -> str:
    def ms(d):
        return "-" if not d["n"] else f"median {d['median']:.1f}, p95 {d['p95']:.1f}"

    lines = [f"{s['frames']} frames: {s['detected']} detected, {s['tracked']} tracked, {s['re_detected']} lost and "
             f"re-detected, {s['fused']} fused from an advised view, {s['lost']} lost, {s['not_found']} not found; "
             f"{s['confident']} confident",
             f"ms per tracked frame: {ms(s['tracked_ms'])}; per detected frame: {ms(s['detected_ms'])}"]
    if "right" in s:
        lines.append(f"against the truth: {s['right']} right, {s['confident_and_wrong']} confident and wrong; "
                     f"tracked frames' error (MSSD, mm): {ms(s['tracked_error_mm'])}")
    return "\n".join(lines)


def frame_json(s, err) -> dict:
    r = s.result
    return {"im_id": s.im_id, "mode": s.mode, "seconds": s.seconds, "ok": r.ok, "confident": bool(r.confident),
            "reason": r.reason, "lost_because": s.lost_because,
            "T_world_base": None if r.T_world_base is None else np.asarray(r.T_world_base).tolist(),
            "T_world_part": None if r.T_world_part is None else np.asarray(r.T_world_part).tolist(),
            "mssd_mod_base_sym": err, "advice": None if s.advice is None else s.advice.to_json()}



def cmd_export_mcap(args) -> int:
    src = open_frames(args.dataset)
    if not isinstance(src, Dataset):
        raise AposeError(f"{args.dataset}: expected a dataset folder from `apose render` (a --trajectory one plays best)")
    if args.step not in src.steps:
        raise AposeError(f"{src.root}: step {args.step} was not rendered; rendered steps: {', '.join(map(str, src.steps))}")
    if args.rate <= 0 or args.rate > 1000:
        raise AposeError(f"--rate {args.rate:g}: expected frames per second above 0 and up to 1000")
    out = Path(args.out)
    check_output_file(out, "--out", [args.dataset])
    ids = src.image_ids(args.step)
    write_recording(out, (src.frame(args.step, i) for i in ids), args.rate)
    print(f"wrote {len(ids)} frames of step {args.step} ({len(ids) / args.rate:.1f} s at {args.rate:g} frames/s) to {out}: "
          "colour, depth aligned to it (16UC1, mm), camera_info and the camera's pose (/apose/camera_pose)")
    return 0


def cmd_capture(args) -> int:
    """Frames from a RealSense written as capture folders that `apose estimate` reads."""
    from apose_studio.data import realsense

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        w = h = 0
    if not (16 <= w <= MAX_SIDE and 16 <= h <= MAX_SIDE):
        raise AposeError(f"--size {args.size}: expected WIDTHxHEIGHT of 16 to {MAX_SIDE} pixels each, e.g. 640x480")
    if args.serial is not None:
        live_serial(f"realsense:{args.serial}")  # a serial's characters checked before the SDK sees it
    out = Path(args.out)
    names = [out] if args.count == 1 else [out / f"{k:06d}" for k in range(args.count)]
    for n in names:
        if n.exists():
            raise AposeError(f"{n}: already exists; captures are never overwritten: choose another --out")
    if args.count == 1 and not out.parent.is_dir():
        raise AposeError(f"--out {out}: the folder {out.parent} does not exist")
    cam = realsense.open_realsense(args.serial, (w, h), args.fps)
    if args.count > 1:
        out.mkdir(parents=True, exist_ok=True)  # only once a camera streams: nothing left behind otherwise
    try:
        for note in cam.notes:
            print(f"note: {note}", file=sys.stderr)
        for _ in range(args.settle):  # auto-exposure settles over the first frames
            cam.next_frame()
        for n in names:
            fr = cam.next_frame()
            write_capture(fr, n, cam.depth_unit_m * 1000.0, {"device": cam.name})
            print(f"{n}: frame {fr.im_id} of {cam.name} ({w}x{h}, depth in {cam.depth_unit_m * 1000:g} mm steps)")
    finally:
        cam.close()
    return 0
