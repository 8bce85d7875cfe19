#!/usr/bin/env python3
"""Live and recorded cameras (issue #30, item 4): a RealSense stream tracked as it comes, and a recording
played in the studio at its recorded rate.

    .venv/bin/python benchmarks/live.py [--seconds 20] [--fps 30] [--record-seconds 20] [--data artifacts/live]

Renders (once, kept in --data) a camera closing in on the helical gearbox's step 2 base over a cluttered
bench in 60 frames (RealSense-like depth), played forth and back (0..59, 58..1, ...) so that any length of
stream moves smoothly; the renderer's truth of each frame is known to this script only.

1. **Stream**: the frames injected at --fps through Intel's SDK `software_device` (the SDK's syncer and
   rs.align, as a device's), read as they come for --seconds, each tracked (estimation.Tracker; the first
   frame and a lost one estimated with a box prompt: the first frame's from the truth, then where the base
   was last seen). Twice: without camera poses (a hand-held camera: every frame's world is the camera's)
   and with the robot's poses (the truth's T_world_camera given with each frame, as kinematics would).
2. **Recording in the studio**: the same frames as an MCAP of --record-seconds at --fps (written once),
   opened in a studio server (no browser: the server's side of the work) and played with tracking at its
   recorded rate: wall time against the recording's length, frames shown and skipped.

Prints per run: frames sent, read (the rest skipped: not read in time), modes, milliseconds per tracked frame
(median, p95), right (MSSD below 10 % of the part's diameter) and confident-and-wrong against the truth.
"""

from __future__ import annotations

import apose_studio  # noqa: F401  (first: its thread settings apply only before numpy loads)

# isort: split

import argparse
import socket
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from apose_studio.assembly.model import load_assembly  # noqa: E402
from apose_studio.data.dataset import Dataset  # noqa: E402
from apose_studio.errors import AposeError  # noqa: E402
from apose_studio.estimation import Tracker, array_mask, estimate_frame, step_context, truth_box  # noqa: E402
from apose_studio.evaluate import score_frame  # noqa: E402
from apose_studio.geometry import se3  # noqa: E402
from apose_studio.registration import resolve_params  # noqa: E402
from apose_studio.synth.frame import RenderSettings  # noqa: E402
from apose_studio.synth.render import render_dataset  # noqa: E402

GEARBOX = REPO / "sample_assemblies" / "helical_gearbox" / "assembly.yaml"
STEP = 2


def rendered(args) -> list:
    out = Path(args.data) / "approach_60"
    if not (out / "dataset_info.json").is_file():
        print(f"rendering 60 frames into {out} (once)", flush=True)
        render_dataset(load_assembly(GEARBOX), out, RenderSettings(frames=60, trajectory="approach", noise="realsense",
                                                                   clutter=("bench",), seed=2),
                       steps=[STEP], overwrite=True, progress=False)
    ds = Dataset(out)
    return [ds.frame(STEP, i) for i in ds.image_ids(STEP)]


def forth_and_back(k: int, n: int) -> int:
    """The rendered frame shown as the stream's k-th: 0..n-1, n-2..1, 0.. (smooth at both ends)."""
    k %= 2 * n - 2
    return k if k < n else 2 * n - 2 - k


def error(result, frame, truth, ctx) -> float:
    """MSSD (metres) of the result's part pose against the truth, in the frame's camera (its world may differ)."""
    T_camera_part = se3.inv(frame.T_world_camera) @ result.T_world_part
    gt = replace(truth, T_world_camera=np.eye(4), T_world_part=se3.inv(truth.T_world_camera) @ truth.T_world_part)
    est = replace(result, T_world_part=T_camera_part)
    return score_frame(gt, est, ctx.part, None, ctx.base.symmetries).mssd


def summary(name, sent, read, tracker, errs, confident, diameter, seconds) -> str:
    modes = [s.mode for s in tracker.steps]
    ms = np.array([s.seconds * 1000 for s in tracker.steps if s.mode == "tracked" and s.seconds > 0])
    right = sum(e < 0.1 * diameter for e in errs)
    cw = sum(c and e >= 0.1 * diameter for c, e in zip(confident, errs))
    timing = f"{np.median(ms):6.1f} {np.percentile(ms, 95):6.1f}" if len(ms) else "     -      -"
    return (f"{name:28s} {seconds:5.1f} {sent:5d} {read:5d} {sent - read:5d} | {modes.count('tracked'):5d} "
            f"{modes.count('re-detected'):5d} {modes.count('lost') + modes.count('not found'):5d} | {timing} | "
            f"{right:5d} {cw:4d} | {np.median(errs) * 1000 if errs else float('nan'):6.2f}")


def stream(frames, args, posed: bool) -> str:
    from apose_studio.data.realsense import software_camera

    n = len(frames)
    order = [frames[forth_and_back(k, n)] for k in range(int(args.seconds * args.fps))]
    asm, ctx = step_context(load_assembly(GEARBOX), STEP)
    params = resolve_params("default", asm.registration)
    ctx.base.warm_up(params)

    def detect(frame, box):
        box = box or truth_box(order[frame.im_id].base_mask())
        return estimate_frame(frame, ctx, params, mask=array_mask(frame.rgb, frame.depth, frame.camera, box=box)[0],
                              box=box)

    tracker, errs, confident = Tracker(ctx, params, detect), [], []
    cam = software_camera(order, fps=args.fps)
    t0 = time.monotonic()
    try:
        while True:
            try:
                fr = cam.next_frame(timeout_s=2.0)
            except AposeError:
                break
            truth = order[fr.im_id]
            if posed:  # the robot's kinematics give the camera's pose with the frame
                fr = replace(fr, T_world_camera=truth.T_world_camera)
            s = tracker.step(fr)
            if s.result.ok:
                errs.append(error(s.result, fr, truth, ctx))
                confident.append(bool(s.result.confident))
    finally:
        cam.close()
    name = f"stream {args.fps:g} Hz, {'robot poses' if posed else 'no poses'}"
    return summary(name, len(order), len(tracker.steps), tracker, errs, confident, ctx.part.diameter,
                   time.monotonic() - t0 - 2.0)


def studio_play(frames, args) -> str:
    from apose_studio.data.recording import write_recording
    from apose_studio.studio import serve
    from apose_studio.studio.state import Event

    n = len(frames)
    count = int(args.record_seconds * args.fps)
    rec = Path(args.data) / f"approach_{args.record_seconds:g}s_{args.fps:g}hz.mcap"
    if not rec.is_file():
        print(f"writing {rec} ({count} frames, once)", flush=True)
        write_recording(rec, (frames[forth_and_back(k, n)] for k in range(count)), args.fps)
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server, st = serve(GEARBOX, None, host="127.0.0.1", port=port, root=Path(args.data), tabs=False)
    click = type("Click", (), {"client": None})()  # as the page's button would call (no page here)
    try:
        st.notify = lambda *a, **k: None
        st.inspect.i_path.value = str(rec)
        st.guarded("open")(lambda c: st.inspect.on_open_data(c))(click)
        st.inspect.i_step.value = st.inspect.i_step.options[STEP - 1]
        st.inspect.i_mask.value = "prompt"
        st.prompt.i_prompt.value = ",".join(map(str, truth_box(frames[0].base_mask())))
        shown, done = [], threading.Event()
        st.events.on(Event.FRAME_PLAYED, lambda im_id: shown.append((im_id, st.inspect.result, st.inspect.frame)))
        t0 = time.monotonic()
        st.guarded("play")(lambda c: st.sequence.on_play(c))(click)
        while st.sequence.playing:
            done.wait(0.1)
        wall = time.monotonic() - t0
    finally:
        server.stop()
    asm, ctx = step_context(load_assembly(GEARBOX), STEP)
    errs, confident = [], []
    for im_id, result, fr in shown:
        if result is not None and result.ok:
            errs.append(error(result, fr, frames[forth_and_back(im_id, n)], ctx))
            confident.append(bool(result.confident))

    class Steps:  # the player's own tracker is inside the studio: its modes are in the results shown
        steps = [type("S", (), {"mode": "tracked" if r.tracked else "re-detected", "seconds": 0.0})()
                 for _, r, _ in shown if r is not None]
    line = summary(f"studio plays {args.record_seconds:g} s MCAP", count, len(shown), Steps, errs, confident,
                   ctx.part.diameter, wall)
    return line + f"\n    (recorded {count / args.fps:.1f} s, played in {wall:.1f} s wall; the player's summary: " \
                  f"{st.sequence.last_summary})"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each live stream (default 20)")
    ap.add_argument("--fps", type=float, default=30.0, help="the camera's frames per second (default 30)")
    ap.add_argument("--record-seconds", type=float, default=20.0, help="length of the recording (default 20)")
    ap.add_argument("--data", default=str(REPO / "artifacts" / "live"), help="where the renders and recording are kept")
    args = ap.parse_args()
    Path(args.data).mkdir(parents=True, exist_ok=True)
    frames = rendered(args)
    print(f"{'run':28s} {'s':>5s} {'sent':>5s} {'read':>5s} {'skip':>5s} | {'trk':>5s} {'redet':>5s} {'lost':>5s} | "
          f"{'ms med':>6s} {'p95':>6s} | {'right':>5s} {'c&w':>4s} | {'mm med':>6s}", flush=True)
    for posed in (False, True):
        print(stream(frames, args, posed), flush=True)
    print(studio_play(frames, args), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
