"""The Inspect tab's Sequence folder: the opened frames played in time (a ROS 2 recording at its recorded rate,
a dataset's step or a BOP scene at the rate typed), with the base tracked from frame to frame
(estimation.Tracker): the first frame estimated with the Estimate folder's settings (its Mask, prompt,
preset), each next one tracked from the last confident pose, a frame where tracking loses the base
estimated anew around where it was last seen. Each frame played is put on show with its result (the
3D view, the Result folder) and the Frame slider follows it.

Playing keeps time: a frame that is not ready when the next is due is skipped (counted), so a recording
plays at its own pace whatever the machine; the status line says how many frames were shown, tracked, lost
and skipped, and the milliseconds per tracked frame. The player runs in its own thread, holds the
estimator while it plays (Estimate says so), and takes the studio's lock only to show a frame; Pause, new
data or another step stops it."""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import replace

import numpy as np

from apose_studio.data.bop import BopScene
from apose_studio.data.dataset import Dataset, write_capture
from apose_studio.data.realsense import LiveCamera
from apose_studio.data.recording import Recording
from apose_studio.errors import AposeError
from apose_studio.estimation import Tracker, array_mask, estimate_view, last_seen_box
from apose_studio.evaluate import score_frame
from apose_studio.registration.types import View, doubts
from apose_studio.studio.state import Event

log = logging.getLogger(__name__)
DEFAULT_RATE = 10.0  # frames per second of a dataset or BOP scene (a recording plays at its own)


class SequencePanel:
    def __init__(self, app):
        self.app = app
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.last_summary = ""  # the status line of the last play (tests read it)

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Sequence"):
            self.s_play = gui.add_button("Play", hint="play the opened frames in time from the frame on show, the base "
                                         "tracked from frame to frame; press again to pause")
            self.s_play.on_click(self.app.guarded("Play")(self.on_play))
            self.s_track = gui.add_checkbox("Track", True, hint="follow the base from the last confident pose (off: "
                                            "estimate every frame played with the Estimate folder's settings)")
            self.s_rate = gui.add_number("Rate (frames/s)", 0.0, min=0.0, max=120.0, step=1.0,
                                         hint=f"0: a recording's own rate ({DEFAULT_RATE:g} for a dataset)")
            self.s_status = gui.add_markdown("")
            self.s_capture_to = gui.add_text("Capture folder", "", hint="the new folder Capture writes the frame on show "
                                             "into (in the workspace; it must not exist yet); empty: captures/<date-time>-"
                                             "<frame> under the workspace")
            b = gui.add_button("Capture", hint="save the frame on show as a capture folder (rgb.png, depth.png, "
                               "camera.json with the camera's cam_K and depth scale) that `apose estimate` reads")
            b.on_click(self.app.guarded("Capture")(self.on_capture))

    @property
    def playing(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def on_play(self, client) -> None:
        if self.playing:
            self._stop.set()  # the player ends its frame, then says where it stopped
            return
        ins = self.app.state.inspect
        frames = ins.frames
        if frames is None or ins.frame is None:
            raise AposeError("open a recording, a dataset or a live camera first (Data folder)")
        if not isinstance(frames, (Recording, Dataset, BopScene, LiveCamera)):
            raise AposeError("a capture is one frame: there is nothing to play (Estimate frame estimates it)")
        step = ins.step
        if isinstance(frames, LiveCamera):
            ids, k0, rate = [ins.frame.im_id], 0, 0.0
        else:
            ids = (list(range(len(frames))) if isinstance(frames, Recording) else
                   frames.image_ids(step) if isinstance(frames, Dataset) else frames.image_ids())
            k0 = ids.index(ins.frame.im_id) if ins.frame.im_id in ids else 0
            if k0 >= len(ids) - 1:
                k0 = 0  # at the end: play from the start
            rate = float(self.s_rate.value) or (len(frames) / frames.seconds if isinstance(frames, Recording) and
                                                frames.seconds > 0 else DEFAULT_RATE)
            if not np.isfinite(rate) or rate <= 0:
                raise AposeError("Rate (frames/s): type a positive number (0: the recording's own)")
        job = self.app.estimate_job(step, [ids[k0]])  # the Estimate folder's settings of this moment
        on_show = ins.result if ins.result is not None and ins.result.confident and ins.frame.im_id == ids[k0] else None
        if not self.app.busy.acquire(blocking=False):
            raise AposeError("an estimation is running; play when it has finished")
        self._stop.clear()
        self.s_play.label = "Pause"
        self._thread = self.app.start_thread(self._play, job, ids, k0, rate, bool(self.s_track.value), client, on_show,
                                             ins.frame, name="sequence player")

    def _frames(self, job, ids: list[int], k0: int, rate: float, counts: dict):
        """The frames to show, in time: a live camera's as they come (a gap in its frame numbers: frames that
        were not read in time), else ids[k0:] at `rate`, a frame already due when the last is shown skipped."""
        if isinstance(job.frames, LiveCamera):
            last = None
            while not self._stop.is_set():
                frame = self.app.state.load_frame(job.step, job.frames.next_frame().im_id, job.frames, job.assembly)
                if last is not None and frame.im_id > last + 1:
                    counts["skipped"] += frame.im_id - last - 1
                last = frame.im_id
                yield frame
            return
        source = job.frames.player() if isinstance(job.frames, Recording) else job.frames  # read in one pass
        t0, k = time.monotonic(), k0
        try:
            while k < len(ids) and not self._stop.is_set():
                yield self.app.state.load_frame(job.step, ids[k], source, job.assembly)
                late = time.monotonic() - (t0 + (k + 1 - k0) / rate)
                if late < 0:
                    self._stop.wait(-late)
                    k += 1
                else:  # behind: the frames already due are skipped, as a live camera's would be (the last is shown)
                    skip = min(int(late * rate), max(len(ids) - k - 2, 0))
                    counts["skipped"] += skip
                    k += 1 + skip
        finally:
            if source is not job.frames:
                source.close()

    def _play(self, job, ids: list[int], k0: int, rate: float, tracking: bool, client, on_show=None,
              shown_frame=None) -> None:
        """The frames shown in time (runs in the player's thread; the studio's lock only to show one). `on_show`: a
        confident result of the frame on show when Play was pressed (`shown_frame`): tracking goes on from it (a
        paused player resumes where it was, not from the prompt drawn on the first frame)."""
        ctx = self.app.step_context(job.step)
        params = job.params()
        first = ids[k0]

        def detect(frame, box):
            if box is None and frame.im_id == first:  # the user's settings, for the frame they were made on
                return self.app.estimate_frame(job, frame.im_id)[0]
            if box is not None:  # where the base was last seen: a box prompt there
                mask, _ = array_mask(frame.rgb, frame.depth, frame.camera, box=box, region=ctx.base.region is not None)
                return estimate_view(replace(View.of(frame, mask), box=box), ctx, params, job.prior)
            return self.app.estimate_frame(replace(job, ids=(frame.im_id,)), frame.im_id)[0]

        tracker = Tracker(ctx, params, detect)
        if on_show is not None and tracking:
            tracker.resume(on_show, shown_frame)
        counts = {"shown": 0, "skipped": 0, "n": None if isinstance(job.frames, LiveCamera) else len(ids)}
        why, im_id = "the end", first
        try:
            for frame in self._frames(job, ids, k0, rate, counts):
                im_id = frame.im_id
                s = tracker.step(frame) if tracking else None
                result = s.result if s is not None else detect(frame, None)
                score = score_frame(frame, result, ctx.part, None, ctx.base.symmetries) \
                    if frame.T_world_part is not None else None
                with self.app.lock:
                    ins = self.app.state.inspect
                    if ins.frames is not job.frames or ins.step != job.step:
                        why = "other data or another step opened"
                        break
                    ins.frame, ins.result, ins.score = frame, result, score
                    self.app.events.emit(Event.FRAME_CHANGED)
                    ins.advice = s.advice if s is not None else None  # drawn as "look from here" (Views panel)
                    self.app.events.emit(Event.FRAME_PLAYED, im_id=frame.im_id)
                    counts["shown"] += 1
                    self.s_status.content = self.status(tracker, counts, frame.im_id, s, result)
            else:
                why = "paused" if self._stop.is_set() else why
        except Exception as e:  # a bad frame, a camera unplugged: said, the player stops, the studio goes on
            if self.app.state.inspect.frames is not job.frames:  # the camera was closed for other data
                why = "other data opened"
            else:
                log.exception("playing stopped")
                why = f"an error: {e}"
                self.app.notify(client, "Play", f"stopped at frame {im_id}: {e}", error=True)
        finally:
            self.app.busy.release()
            with self.app.lock:
                self.s_play.label = "Play"
                self.last_summary = f"stopped ({why}). " + self.status(tracker, counts, None, None, None)
                self.s_status.content = self.last_summary

    @staticmethod
    def status(tracker: Tracker, counts: dict, im_id, step, result) -> str:
        """The player's line: where it is, how the frame was found, and the counts so far."""
        modes = [s.mode for s in tracker.steps]
        ms = [s.seconds * 1000 for s in tracker.steps if s.mode == "tracked"]
        now = ""
        if im_id is not None:
            how = step.mode if step is not None else "estimated"
            conf = "confident" if result.confident else ("not confident: " + doubts(result) if result.ok else
                                                         "no pose: " + result.reason)
            of = f"of {counts['n']}" if counts["n"] else "(live)"
            now = f"**frame {im_id}** {of}: {how}, {conf[:160]}  \n"
        timing = f"; {np.median(ms):.0f} ms per tracked frame (median)" if ms else ""
        fused = f"{modes.count('fused')} fused from the advised view, " if "fused" in modes else ""
        failed = modes.count("not found") + modes.count("lost")
        if failed:
            fused += f"{failed} without a confident pose, "
        if step is not None and step.advice is not None and im_id is not None:
            now += "ambiguous: the orange camera shows where to look from (a frame from there is fused)  \n"
        return (f"{now}{counts['shown']} shown, {counts['skipped']} skipped (not ready in time); {modes.count('tracked')} tracked, {fused}"
                f"{modes.count('re-detected')} lost and found again{timing}")

    def on_capture(self, client) -> None:
        """The frame on show written as a capture folder (data.dataset.write_capture): a live camera's in its
        device's depth unit, others in 0.1 mm steps (1 mm past 6.5 m)."""
        ins = self.app.state.inspect
        frame = ins.frame
        if frame is None:
            raise AposeError("open a live camera, a recording or a dataset first (Data folder)")
        text = self.s_capture_to.value.strip() or f"captures/{time.strftime('%Y%m%d-%H%M%S')}-{frame.im_id}"
        folder = self.app.workspace.resolve(text, "capture folder")
        if isinstance(ins.frames, LiveCamera):
            unit, info = ins.frames.depth_unit_m * 1000.0, {"device": ins.frames.name}
        else:
            unit, info = (0.1 if np.nanmax(frame.depth, initial=0.0) < 6.5 else 1.0), {}
        existing = next(p for p in (folder.parent, *folder.parent.parents) if os.path.lexists(p))
        if not existing.is_dir():
            raise AposeError(f"{existing}: a file, not a folder; type a Capture folder whose parents are folders")
        try:
            folder.parent.mkdir(parents=True, exist_ok=True)
            write_capture(frame, folder, unit, {**info, "source": frame.source})
        except PermissionError:
            raise AposeError(f"{existing}: folder not writable; type another Capture folder") from None
        self.s_capture_to.value = ""
        asm, r = self.app.state.inspect_assembly(), ins.result
        box = last_seen_box(r, frame) if r is not None and r.ok else None
        command = (f"apose estimate {folder} --assembly {asm.path or 'A.yaml'} "
                   f"--step {ins.step}" + (f" --box {','.join(map(str, box))}" if box else " --box X0,Y0,X1,Y1"))
        self.app.notify(client, "Captured", f"frame {frame.im_id} saved to {folder}; to estimate it from a terminal: "
                        f"{command}")

    def stop(self, timeout: float = 10.0) -> None:
        """Stop playing and wait for the player (the studio's Ctrl-C, tests)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
