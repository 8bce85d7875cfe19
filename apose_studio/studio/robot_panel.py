"""The Inspect tab's Robot folder: the cell's hand-eye calibration, where to pick the loose part, and the
pick-and-place targets of the estimate on show in the robot's frame (docs/ROBOT.md).

'Use hand-eye' reads a calibration file (robot.handeye: ours, a bare 4x4, easy_handeye2's); an eye-in-hand
calibration takes the arm's T_robot_flange from the capture's camera.json, else from the file. 'Estimate
pick' finds the step's part where it lies in this frame, prompted by a box or a point around it (the same
registration with the part's own CAD as the base: estimation.estimate_pick). The targets (place, pre-place,
pick, lift: the gripper's TCP by the part's first grasp) are listed here in the robot's frame, in mm and
wxyz, and can be downloaded as the JSON `apose estimate --hand-eye --json` adds; the 3D view (results_view)
draws the robot base's axes and the gripper at each target.

The calibration and the pick estimates live in the shared state (`state.inspect.hand_eye`,
`T_robot_flange`, `pick_estimates`); a change emits RESULT_READY, on which the 3D view and this folder redraw."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from apose_studio.data.dataset import Dataset
from apose_studio.errors import AposeError
from apose_studio.estimation import estimate_pick
from apose_studio.geometry import se3
from apose_studio.registration import doubts
from apose_studio.registration.types import View
from apose_studio.robot.handeye import capture_flange, read_hand_eye
from apose_studio.studio import inspection
from apose_studio.studio.prompt_panel import parse_prompt, prompted_mask
from apose_studio.studio.state import Event
from apose_studio.studio.widgets import esc, pixel_at_ray, send_download

ROWS = (("T_robot_gripper_place", "place"), ("T_robot_gripper_preplace", "pre-place"),
        ("T_robot_gripper_pick", "pick"), ("T_robot_gripper_lift", "lift"), ("T_robot_part", "part placed"),
        ("T_robot_part_pick", "part where it lies"))


def targets_markdown(t, calibration: str = "", pick_prompt: str | None = None) -> str:
    """The targets as a table: position (mm) and quaternion (wxyz) in the robot's frame, with the frame's name,
    the grasp, how many symmetry-equivalent placements there are, and the notes; the calibration file in use
    and the prompt the pick was found with."""
    if t is None:
        return ""
    rows = []
    for key, label in ROWS:
        T = getattr(t, key)
        if T is not None:
            p, q = T[:3, 3] * 1000.0, se3.matrix_to_quat_wxyz(T[:3, :3])
            rows.append(f"| {label} | {p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f} | {q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f} |")
    lines = [f"Robot frame **{esc(t.robot_frame)}**" + (f" ({esc(calibration)})" if calibration else "")]
    if rows:
        lines.append("The gripper's TCP" + (f" by grasp **{esc(t.grasp)}**" if t.grasp else "") + ":\n\n"
                     "| target | t (mm) | q (wxyz) |\n|---|---|---|\n" + "\n".join(rows))
    if pick_prompt and t.pick is not None:
        lines.append(f"Pick found with the prompt {esc(pick_prompt)}")
    if t.gripper_alternatives:
        lines.append(f"{len(t.gripper_alternatives)} other place target(s), one per symmetry-equivalent placement "
                     "(in the download)")
    if t.pick is not None and not t.pick.get("ok"):
        lines.append(f"Pick: {esc(str(t.pick.get('reason', '')))}")
    elif t.pick is not None and not t.pick.get("confident"):
        lines.append(f"Pick not confident: {esc(str(t.pick.get('doubts', '')))}")
    lines += [esc(n) for n in t.notes]
    return "\n\n".join(lines)


class RobotPanel:
    def __init__(self, app):
        self.app = app
        app.events.on(Event.FRAME_CHANGED, self.show_targets)
        app.events.on(Event.RESULT_READY, self.show_targets)

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Robot", expand_by_default=False):
            self.i_hand_eye = gui.add_text("Hand-eye file", "", hint="the camera in the robot's frame: JSON/YAML with "
                                           "T_robot_camera or T_flange_camera, a bare 4x4, or easy_handeye2's calibration")
            b = gui.add_button("Use hand-eye", hint="draw the robot base's axes and list the gripper's targets in its frame")
            b.on_click(self.app.guarded("Hand-eye")(self.on_use_hand_eye))
            self.i_pick = gui.add_text("Pick prompt (px)", "", hint="a box x0,y0,x1,y1 or a point u,v on the loose part in "
                                       "this frame: where the robot picks it")
            b = gui.add_button("Pick at click", hint="then click the loose part in the 3D view: its pixel becomes the pick "
                               "prompt, and the pick is estimated")
            b.on_click(self.app.guarded("Pick at click")(self.on_pick_at_click))
            b = gui.add_button("Drag a pick box", hint="then drag a rectangle around the loose part in the 3D view: its "
                               "box becomes the pick prompt, and the pick is estimated")
            b.on_click(self.app.guarded("Drag a pick box")(self.on_drag_pick_box))
            b = gui.add_button("Estimate pick", hint="find the loose part where it lies (its own CAD as the base)")
            b.on_click(self.app.guarded("Estimate pick")(self.on_estimate_pick))
            self.i_targets = gui.add_markdown("")
            b = gui.add_button("Download targets (JSON)", hint="the targets as `apose estimate --hand-eye --json` "
                               "gives them: 4x4 in metres, both quaternion orders")
            b.on_click(self.app.guarded("Download targets")(self.on_download))

    def on_use_hand_eye(self, client) -> None:
        ins = self.app.state.inspect
        text = self.i_hand_eye.value.strip()
        if not text:
            ins.hand_eye = ins.T_robot_flange = None
            if ins.frame is not None:
                self.app.events.emit(Event.RESULT_READY)
            self.app.notify(client, "Hand-eye", "none: the robot frame is no longer shown")
            return
        try:
            he = read_hand_eye(self.app.workspace.resolve(text, "hand-eye calibration file"))
            flange = None
            if he.kind == "eye_in_hand":
                if ins.frames is not None and not isinstance(ins.frames, Dataset) and ins.frames_path:
                    flange = capture_flange(Path(ins.frames_path))  # the arm's pose when this capture was taken
                if flange is None and he.T_robot_flange is None:
                    raise AposeError(f"{text}: an eye-in-hand calibration needs the arm's T_robot_flange at the capture: "
                                     "put it in the capture's camera.json (key T_robot_flange) or in the calibration file")
        except AposeError as e:  # nothing lost: the calibration in use stays, and the refusal says which it is
            kept = f"\n(the calibration in use stays: {ins.hand_eye.source})" if ins.hand_eye is not None else ""
            raise AposeError(f"{e}{kept}") from None
        ins.hand_eye, ins.T_robot_flange = he, flange
        if ins.frame is not None:  # else drawn when a frame opens (FRAME_CHANGED)
            self.app.events.emit(Event.RESULT_READY)
            self.frame_cell()
        where = "the capture's camera.json" if flange is not None else "the file" if he.kind == "eye_in_hand" else ""
        self.app.notify(client, "Hand-eye", f"{he.kind.replace('_', '-')} calibration, robot frame {he.robot_frame}"
                        + (f"; the arm's pose from {where}" if where else "") + "; the view shows the robot base's axes "
                        "and the object")

    def frame_cell(self) -> None:
        """Every tab's view on the robot base and the object under inspection together (the base is often
        half a metre or more away: off screen from the object's framing)."""
        ins = self.app.state.inspect
        fr, T_world_robot = ins.frame, inspection.T_world_robot(ins)
        if T_world_robot is None:
            return
        r = ins.result
        if r is not None and r.ok:
            obj = r.T_world_part[:3, 3]
        else:  # the frame's middle, at the depth seen there
            h, w = fr.depth.shape
            win = fr.depth[h // 3: 2 * h // 3, w // 3: 2 * w // 3]
            ok = np.isfinite(win) & (win > 0)
            z = float(np.median(win[ok])) if ok.any() else 0.5
            obj = se3.transform_points(fr.T_world_camera, np.array([[0.0, 0.0, z]]))[0]
        robot = T_world_robot[:3, 3]
        centre = (obj + robot) / 2.0
        radius = max(float(np.linalg.norm(obj - robot)) / 2.0 + 0.1, 0.15)
        to_camera = fr.T_world_camera[:3, 3] - centre
        to_camera[2] = max(to_camera[2], 0.6 * float(np.linalg.norm(to_camera[:2])))  # from above the table
        self.app.look_at(centre, radius, to_camera)

    def on_pick_at_click(self, client) -> None:
        """The next click in the 3D view (by this tab) on the loose part: its pixel is the pick prompt."""
        if self.app.state.inspect.frame is None:
            raise AposeError("open a capture or dataset first, then click the loose part")
        self.app.next_pointer(client, "Pick at click", "click",
                              lambda e, c: self.pick_at_ray(e.ray_origin, e.ray_direction, c),
                              "click the loose part in the 3D view")

    def on_drag_pick_box(self, client) -> None:
        """The next rectangle dragged in the 3D view (by this tab) around the loose part: its box is the pick prompt."""
        if self.app.state.inspect.frame is None:
            raise AposeError("open a capture or dataset first, then drag a box around the loose part")
        self.app.next_pointer(client, "Drag a pick box", "rect", self.pick_from_drag,
                              "drag a rectangle around the loose part in the 3D view")

    def pick_from_drag(self, event, client) -> None:
        box = inspection.frame_box_from_drag(self.app.state.inspect.frame, event, "the loose part")
        self.i_pick.value = ",".join(map(str, box))
        self.on_estimate_pick(client)

    def pick_at_ray(self, origin, direction, client) -> None:
        """The scene point the click's ray hits, as a pixel of the frame: the pick prompt; then the pick."""
        self.i_pick.value = pixel_at_ray(self.app.state.inspect.frame, origin, direction)
        self.on_estimate_pick(client)

    def on_estimate_pick(self, client) -> None:
        ins = self.app.state.inspect
        fr = ins.frame
        if fr is None:
            raise AposeError("open a capture or dataset first, then box the loose part in 'Pick prompt (px)'")
        key = ins.pick_key()
        if ins.pick_estimates.pop(key, None) is not None:  # the pick shown came from another prompt: gone, whatever happens next
            self.app.events.emit(Event.RESULT_READY)
        text = self.i_pick.value.strip()
        form = "type a box x0,y0,x1,y1 or a point u,v on the loose part (image pixels, as for the base's Prompt (px))"
        if not text:
            raise AposeError(f"'Pick prompt (px)' is empty: {form}")
        try:
            prompt = parse_prompt(text)
            mask = prompted_mask(ins.prompt_masks, fr, prompt)
        except AposeError as e:  # the prompt readers' own words name the base's prompt and the CLI's flags
            raise AposeError(f"Pick prompt {text[:60]!r}: {form}" + (f" ({e})" if "outside" in str(e) else "")) from None
        if not mask.any():
            raise AposeError(f"Pick prompt {text[:60]!r} gives an empty mask: box the loose part itself")
        ctx = self.app.step_context(ins.step)
        params = self.app.estimate_job(ins.step, [fr.im_id]).params()
        view = View(fr.depth, mask, fr.camera, fr.T_world_camera, rgb=fr.rgb, box=prompt[0])
        r = estimate_pick(view, ctx.part, params)
        ins.pick_estimates[key] = (text, r)
        self.app.events.emit(Event.RESULT_READY)
        if not r.ok:
            self.app.notify(client, "Pick not found", r.reason, error=True)
        elif not r.confident:
            self.app.notify(client, "Pick found, not confident", doubts(r), error=True)
        else:
            self.app.notify(client, "Pick found", "the gripper is drawn where it picks the part"
                            + ("" if ins.hand_eye is not None else "; use a hand-eye file for its pose in the robot's frame"))

    def targets(self):
        """The targets of what is on show (inspection.robot_targets_shown), or None."""
        ins = self.app.state.inspect
        if ins.hand_eye is None or ins.frame is None or ins.step is None:
            return None
        return inspection.robot_targets_shown(ins, self.app.state.inspect_assembly(), self.app.step_context(ins.step))

    def show_targets(self) -> None:
        try:
            t = self.targets()
        except AposeError as e:  # e.g. an eye-in-hand calibration and a frame without the arm's pose
            self.i_targets.content = esc(str(e))
            return
        ins = self.app.state.inspect
        self.i_targets.content = targets_markdown(t, Path(ins.hand_eye.source).name if ins.hand_eye is not None else "",
                                                  ins.pick()[0])

    def on_download(self, client) -> None:
        t = self.targets()
        if t is None:
            raise AposeError("use a hand-eye file first (and Estimate frame): the targets are in the robot's frame")
        if t.T_robot_gripper_place is None and t.T_robot_gripper_pick is None:
            raise AposeError("no target yet: Estimate frame (place) or Estimate pick first")
        if client is None:
            raise AposeError("no browser to send the download to")
        ins = self.app.state.inspect
        fr, r = ins.frame, ins.result
        doc = {"source": ins.frames_path, "step": ins.step, "frame": int(fr.im_id), "hand_eye_file": ins.hand_eye.source,
               "pick_prompt": ins.pick()[0],
               "place": None if r is None else {"ok": bool(r.ok), "confident": bool(r.confident), "reason": r.reason,
                                                "doubts": "" if r.confident or not r.ok else doubts(r)},
               **t.to_json()}
        send_download(client, f"targets_step{ins.step}_frame{ins.frame.im_id}.json", json.dumps(doc, indent=1).encode("utf-8"))

