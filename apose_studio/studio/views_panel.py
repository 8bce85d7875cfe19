"""Inspect tab, *Views (one placement)*: tick frames that show the base at one placement (a dataset
rendered with `--views-per-scene`, or an eye-in-hand camera's looks) and estimate them together
(registration.fusion). Where the result is ambiguous or not confident, the camera to look from next
(registration.next_view) is drawn as an orange frustum labelled "look from here": this panel's fused
estimates and the Inspect panel's ambiguous single frames put it in `state.inspect.advice`, and it is
drawn on RESULT_READY (cleared when the frame changes).

The frame on show comes from the studio's shared state (`state.inspect`): the ticks follow it on
FRAME_CHANGED. A fused estimate goes into the state as the frame's result (RESULT_READY), with the
Inspect panel's settings of the moment (`Studio.estimate_job`)."""

from __future__ import annotations

import numpy as np

from apose_studio.data.dataset import Dataset
from apose_studio.errors import AposeError
from apose_studio.estimation import estimate_frames, frame_mask
from apose_studio.evaluate import score_frame
from apose_studio.geometry import se3
from apose_studio.registration.next_view import next_view
from apose_studio.registration.types import View
from apose_studio.studio.state import Event

ORANGE = (255, 140, 0)


class ViewsPanel:
    def __init__(self, app):
        self.app = app
        self.ticks: dict[int, object] = {}  # im_id -> checkbox
        app.events.on(Event.FRAME_CHANGED, self.refresh)
        app.events.on(Event.RESULT_READY, self.draw_advice)  # a result may come with advice (`state.inspect.advice`)
        app.events.on(Event.FRAME_PLAYED, lambda im_id: self.draw_advice())  # ... and a played frame (Sequence)

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Views (one placement)", expand_by_default=False) as self.folder:
            self.i_info = gui.add_markdown("Open a dataset rendered with `--views-per-scene`: the frames of the shown "
                                           "frame's placement appear here to tick.")
            self.b_estimate = gui.add_button("Estimate views together",
                                             hint="one estimate from the ticked frames (known camera poses)")
            self.b_estimate.on_click(self.app.guarded("Estimate views")(self.on_estimate))

    def refresh(self) -> None:
        """The checkboxes for the shown frame's placement (called when the frame changes)."""
        for h in self.ticks.values():
            h.remove()
        self.ticks = {}
        self.app.state.inspect.advice = None
        self.draw_advice()
        ins = self.app.state.inspect
        if not isinstance(ins.frames, Dataset) or ins.frame is None:
            self.i_info.content = "Open a dataset rendered with `--views-per-scene` to fuse its views."
            return
        step = ins.step
        group = next((ids for ids in ins.frames.placements(step).values() if ins.frame.im_id in ids), [ins.frame.im_id])
        lo, hi = self.i_info.order, self.b_estimate.order  # the checkboxes go between the two
        with self.folder:
            for k, im_id in enumerate(group):
                self.ticks[im_id] = self.app.ui.gui.add_checkbox(f"frame {im_id}", True,
                                                                     order=lo + (k + 1) * (hi - lo) / (len(group) + 1))
        self.i_info.content = (f"placement of frame {ins.frame.im_id}: {len(group)} frame(s)" if len(group) > 1 else
                               "this frame's placement has no other view in the dataset")

    def ticked(self) -> list[int]:
        return [i for i, h in self.ticks.items() if h.value]

    def on_estimate(self, client) -> None:
        ins = self.app.state.inspect
        ids = self.ticked()
        if ins.frames is None or not ids:
            raise AposeError("open a dataset and tick at least one frame of the placement")
        step = ins.step
        job = self.app.estimate_job(step, ids)
        if job.crop is not None or job.prompt is not None:
            raise AposeError("fusing views uses the Mask setting per frame; choose gt, depth or box (not a crop or prompt)")
        ctx = self.app.step_context(step)
        params = job.params()
        frames = [self.app.state.load_frame(step, i) for i in ids]
        views = [View.of(f, frame_mask(f, job.mask)) for f in frames]
        r = estimate_frames(views, ctx, params, job.prior)
        ins.frame = frames[0]
        ins.result = r
        ins.score = score_frame(frames[0], r, ctx.part, None, ctx.base.symmetries) if frames[0].T_world_part is not None else None
        ins.advice = next_view(r, ctx.base, [v.T_world_camera for v in views], views[0].camera) if r.ok else None
        self.app.events.emit(Event.RESULT_READY)
        if not r.ok:
            self.app.notify(client, "Views not fused" if "not fused" in r.reason else "Estimation failed", r.reason,
                            error=True)
        elif ins.advice is not None:
            self.app.notify(client, "Estimated, look again", f"{len(ids)} view(s): {ins.advice.why}; the orange "
                            "frustum shows where from", error=True)
        else:
            self.app.notify(client, "Estimated", f"{len(ids)} view(s) fused, confident")

    def draw_advice(self) -> None:
        """The advised camera as a frustum labelled "look from here" (removed when there is no advice)."""
        for name in ("/inspect/next_view", "/inspect/next_view_label"):
            if name in self.app.nodes:
                self.app.nodes.pop(name).remove()
        advice = self.app.state.inspect.advice
        if advice is None or self.app.state.inspect.frame is None:
            return
        T_world_camera, cam = advice.T_world_camera, self.app.state.inspect.frame.camera
        scene = self.app.ui.scene
        wxyz = tuple(float(v) for v in se3.matrix_to_quat_wxyz(T_world_camera[:3, :3]))
        pos = tuple(float(v) for v in T_world_camera[:3, 3])
        fov = 2 * np.arctan(cam.height / (2 * cam.fy))
        self.app.node("/inspect/next_view", scene.add_camera_frustum(
            "/inspect/next_view", fov=float(fov), aspect=cam.width / cam.height, scale=0.06, wxyz=wxyz, position=pos,
            color=ORANGE))
        self.app.node("/inspect/next_view_label", scene.add_label("/inspect/next_view_label", "look from here",
                                                                  position=pos, font_screen_scale=0.9))
