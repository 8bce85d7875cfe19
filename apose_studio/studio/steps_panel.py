"""The Assembly tab's Steps and Preview folders, and the assembly in the 3D view: the steps table, the
step's part, base and pose (typed, or dragged with the gizmo), the preview up to a step, exploded
along insertion directions, and the sequence played for demos.

The selected step, the preview poses and the part meshes live in the studio's shared state (the
Mates panel picks faces on them); this panel writes them. It redraws on DRAFT_CHANGED, drops meshes
on MESHES_CHANGED, shows an opened file assembled on DRAFT_OPENED, re-reads the saved path on
DRAFT_SAVED and moves the gizmo aside on PICKS_CHANGED; a selection it makes is STEP_SELECTED."""

from __future__ import annotations

import logging
import threading
from dataclasses import replace

import numpy as np

from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.studio import authoring, inspection
from apose_studio.studio.state import Event, shared
from apose_studio.studio.widgets import VECTOR_DEG, VECTOR_MM, esc, pos, shaded, wxyz

REGION_LIFT_M = 0.0004  # a part's region faces are drawn this far out along their normals, over the part's own

log = logging.getLogger(__name__)


class StepsPanel:
    step_index = shared("step_index", "the selected step, 0-based (`state.step_index`)")

    def __init__(self, app):
        self.app = app
        self._syncing = False
        self._drag_before = None  # the draft when a gizmo drag started
        self._drag_dropped = False  # another tab changed the draft during this drag: its rest is ignored
        self._step_written: tuple = (None, None)  # (step index, Step label) the server last wrote into the Step field
        self._player: threading.Thread | None = None  # Play sequence: one at a time per tab
        self._stop_play = threading.Event()
        app.events.on(Event.DRAFT_CHANGED, self.on_draft_changed)
        app.events.on(Event.MESHES_CHANGED, lambda pid: self.drop_meshes(pid))
        app.events.on(Event.DRAFT_OPENED, self.on_draft_opened)
        app.events.on(Event.DRAFT_SAVED, self.refresh_status)
        app.events.on(Event.PICKS_CHANGED, self.place_gizmo)
        app.events.on(Event.REGION_HANDLES, self.place_gizmo)

    @property
    def mesh_handles(self) -> dict[str, object]:
        """The parts' meshes in the 3D view (`state.meshes`)."""
        return self.app.state.meshes

    @property
    def _preview(self) -> dict[str, np.ndarray]:
        """Each previewed part's T_world_part (`state.preview`)."""
        return self.app.state.preview

    def on_draft_changed(self) -> None:
        self.refresh_steps()
        self.refresh_assembly_scene()

    def preview_up_to_selected(self) -> None:
        """The preview assembled up to the selected step, as selecting it does (another tab's edit moved it)."""
        if self.step_index is not None:
            self.f_upto.value = self.step_index + 1

    def on_draft_opened(self) -> None:
        self.f_upto.value = len(self.app.asm.steps)  # an opened file shows assembled

    def drop_meshes(self, pid: str | None = None) -> None:
        """Remove a part's mesh from the 3D view (every part's with None); the next refresh adds it anew."""
        for p in [pid] if pid is not None else list(self.mesh_handles):
            if p in self.mesh_handles:
                self.mesh_handles.pop(p).remove()

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Steps") as self.steps_folder:
            self.steps_html = gui.add_html("")
            self.f_step = gui.add_dropdown("Step", ("—",))
            self.f_step.on_update(self.app.guarded("Select step")(self.on_select_step))
            row = gui.add_button_group("Step actions", ("Add", "Delete", "Up", "Down"))
            row.on_click(self.on_step_action)
            self.f_step_part = gui.add_dropdown("Part to place", ("—",))
            self.f_step_part.on_update(self.app.guarded("Part to place")(self.on_step_part))
            self.f_base_frame = gui.add_dropdown("Pose relative to", ("—",), hint="the base part whose frame the pose "
                                                 "below is in; choosing another keeps the part where it is")
            self.f_base_frame.on_update(self.app.guarded("Pose relative to")(self.on_base_frame))
            self.base_folder = gui.add_folder("Base parts (in place)", expand_by_default=True)
            self.base_boxes: dict[str, object] = {}  # candidate part id -> its checkbox in base_folder
            self.f_t = gui.add_vector3("Translation (mm)", (0.0, 0.0, 0.0), step=0.1, **VECTOR_MM)
            self.f_r = gui.add_vector3("Rotation xyz (°)", (0.0, 0.0, 0.0), step=0.1, **VECTOR_DEG)
            self.f_t.on_update(self.app.guarded("Translation")(self.on_typed_pose))
            self.f_r.on_update(self.app.guarded("Rotation")(self.on_typed_pose))
            self.f_snap_mm = gui.add_number("Snap (mm)", 0.5, min=0.0, max=1000.0, step=0.1, hint="0 = off")
            self.f_snap_deg = gui.add_number("Snap (°)", 5.0, min=0.0, max=360.0, step=1.0, hint="0 = off")
        with gui.add_folder("Preview"):
            self.f_upto = gui.add_slider("Assembled up to step", 0, 1, 1, 0)
            self.f_upto.on_update(self.app.guarded("Preview")(lambda c: self.refresh_assembly_scene()))
            self.f_explode = gui.add_slider("Explode", 0.0, 1.0, 0.05, 0.0)
            self.f_explode.on_update(self.app.guarded("Preview")(lambda c: self.on_explode()))
            b = gui.add_button("Play sequence")
            b.on_click(self.app.guarded("Play")(self.on_play_sequence))
        self.status_md = gui.add_markdown("")

    def on_step_action(self, event) -> None:
        action = event.target.value
        self.app.guarded(f"{action} step")(lambda c: self.step_action(action, c))(event)

    def step_action(self, action: str, client) -> None:
        i = self.step_index
        if action == "Add":
            asm = authoring.add_step(self.app.asm, self.new_step_beside())
            self.step_index = len(asm.steps) - 1
        else:
            if i is None:
                raise AposeError("select a step first")
            if action == "Delete":
                asm = authoring.delete_step(self.app.asm, i)
                self.step_index = min(i, len(asm.steps) - 1) if asm.steps else None
            else:
                asm = authoring.move_step(self.app.asm, i, -1 if action == "Up" else 1)
                self.step_index = int(np.clip(i + (-1 if action == "Up" else 1), 0, len(asm.steps) - 1))
        self.app.set_assembly(asm, client)
        if self.step_index is not None:
            self.f_upto.value = self.step_index + 1

    def new_step_beside(self):
        """The default next step with its part set down beside its base (not inside it), facing the same
        way, so its faces can be clicked for mates."""
        step = authoring.default_new_step(self.app.asm)
        try:
            r_base, r_part = (self.app.model(p).diameter / 2 for p in (step.base[0], step.part))
        except AposeError:
            return step

        return replace(step, T_base_part=se3.make_T(t=np.array([1.3 * (r_base + r_part), 0.0, 0.0])))

    def T_world_shown(self, pid: str):
        """Where a part is drawn now (`state.T_world_shown`)."""
        return self.app.state.T_world_shown(pid)

    def on_select_step(self, client) -> None:
        if self._syncing or not self.app.asm.steps:
            return
        before = self.step_index
        self.step_index = int(self.f_step.value.split(".")[0]) - 1
        if client is not None and self.app.current_view != "Assembly":
            self.app.show_view("Assembly")  # a step chosen to edit is shown, not the inspection beside its fields
        self.refresh_steps()
        self.app.events.emit(Event.STEP_SELECTED, index=self.step_index)
        self.f_upto.value = self.step_index + 1
        if client is not None and before != self.step_index and self.app.tab is None:
            # a studio on the server's GUI (not a tab's own) has one set of fields for every tab: the other tabs'
            # fields now edit this step too; say so there, before a value typed into them moves a part their user
            # did not pick
            s = self.app.asm.steps[self.step_index]
            self.app.notify(None, "Step changed in another tab",
                            f"another tab selected step {self.step_index + 1} ({s.part}): the Step fields here show it "
                            "too (every tab shares one selection)", others_of=client)

    def on_step_part(self, client) -> None:
        if self._syncing or self.step_index is None:
            return
        self.app.set_assembly(authoring.edit_step(self.app.asm, self.step_index, part=self.f_step_part.value), client)

    def on_base_box(self, client) -> None:
        """A base part ticked or unticked: the step's base is its frame part, then the ticked others."""
        if self._syncing or self.step_index is None:
            return
        s = self.app.asm.steps[self.step_index]
        others = [p for p, box in self.base_boxes.items() if box.value and p != s.base[0]]
        self.app.set_assembly(authoring.edit_step(self.app.asm, self.step_index, base=[s.base[0], *others]), client)

    def on_base_frame(self, client) -> None:
        """Another base part as the pose's frame: the step's pose is expressed in it, so the part stays where
        it is; the former frame part stays in the base."""
        if self._syncing or self.step_index is None:
            return
        asm, i = self.app.asm, self.step_index
        s, new = asm.steps[i], self.f_base_frame.value
        if new == s.base[0] or new not in asm.parts:
            return
        base = [new, *[b for b in s.base if b != new]]
        T = s.T_base_part
        if asm.root_of(new) == asm.root_of(s.base[0]):  # T_new_part = inv(T_root_new) T_root_old T_old_part
            T = np.linalg.inv(asm.T_root_part(new)) @ asm.T_root_part(s.base[0]) @ s.T_base_part
        self.app.set_assembly(authoring.edit_step(asm, i, base=base, T_base_part=T), client)

    def base_candidates(self, i: int) -> list[str]:
        """The parts step `i`'s part may rest on: those in place before it (not placed by any step, or placed
        by an earlier one), its own part excluded."""
        asm = self.app.asm
        placed_later = {s.part for s in asm.steps[i:]}
        return [p for p in asm.parts if p not in placed_later]

    def refresh_base_boxes(self, i: int | None) -> None:
        """One checkbox per part step `i` may rest on (rebuilt when that list changes), ticked for its base;
        the frame part's ticked and fixed (choose another frame above to drop it)."""
        candidates = self.base_candidates(i) if i is not None else []
        if list(self.base_boxes) != candidates:
            for box in self.base_boxes.values():
                box.remove()
            with self.base_folder:
                self.base_boxes = {p: self.app.ui.gui.add_checkbox(p, False) for p in candidates}
            for box in self.base_boxes.values():
                box.on_update(self.app.guarded("Base parts")(self.on_base_box))
        base = self.app.asm.steps[i].base if i is not None else ()
        for p, box in self.base_boxes.items():
            box.value = p in base
            box.disabled = bool(base) and p == base[0]
        self.f_base_frame.options = candidates or ["—"]
        if base and base[0] in candidates:
            self.f_base_frame.value = base[0]

    def on_typed_pose(self, client) -> None:
        if self._syncing or self.step_index is None:
            return
        T = authoring.pose_from_typed(self.f_t.value, self.f_r.value)
        before = self.app.asm
        self.app.history.record(before, typing=("pose", self.step_index, id(self.app)))  # a number's keystrokes: one undo step
        self.set_pose(T, client, sync_fields=False, gizmo=True)  # the fields are the user's; the gizmo follows them
        self.warn_if_far(T, client) or self.warn_if_through(client)
        self.settle_mates(before, client)

    FAR_FACTOR = 10.0  # a typed pose this many times the base's and part's sizes away from the base looks mistyped

    def warn_if_through(self, client) -> bool:
        """A typed pose that puts the part through one of its base parts is kept, but said (the draft is still
        valid: the file format does not know solids). True when it warned."""
        i = self.step_index
        try:
            models = {p: self.app.model(p) for p in (self.app.asm.steps[i].part, *self.app.asm.steps[i].base)}
        except AposeError:
            return False  # a part that does not load says so itself
        hits = authoring.penetrations(self.app.asm, i, models)
        if hits:
            s = self.app.asm.steps[i]
            where = "; ".join(f"{b}: {share:.0%} of its surface, up to {depth * 1000:.3g} mm deep" for b, share, depth
                              in hits)
            self.app.notify(client, "Parts go through each other", f"step {i + 1} puts {s.part} inside {where}. "
                            "The pose is kept; check the typed values (or drag the part out).", error=True)
        return bool(hits)

    def warn_if_far(self, T_base_part: np.ndarray, client) -> bool:
        """A typed translation far beyond the sizes of the part and its base (1000 typed for 100 mm, a value
        in the wrong unit) is kept, but said: the view framed on it shows little else. True when it warned."""
        s = self.app.asm.steps[self.step_index]
        try:
            size = sum(self.app.model(p).diameter for p in (s.base[0], s.part))
        except AposeError:
            return False  # a part that does not load says so itself
        far = float(np.linalg.norm(T_base_part[:3, 3]))
        if far <= self.FAR_FACTOR * size:
            return False
        self.app.notify(client, "Pose looks wrong", f"step {self.step_index + 1} puts {s.part} {far * 1000:.4g} mm "
                        f"from the origin of {s.base[0]}, {far / size:.0f}x the two parts' sizes "
                        f"({size * 1000:.4g} mm): is a value in the wrong unit? The fields are in mm.", error=True)
        return True

    def settle_mates(self, before, client) -> None:
        """After a typed pose or a drag: a pose that breaks the step's mates asks whether to drop them or
        to snap back to what they give."""
        i = self.step_index
        if i is None or not authoring.broken_mates(self.app.asm, i, self.app.asm.steps[i].T_base_part):
            return
        clients = [client] if client is not None else self.app.pages()
        asked_on = self.app.asm  # the answer applies to this draft only: another tab may edit it meanwhile

        def still_asked(modal) -> None:
            modal.close()
            if self.app.asm is not asked_on:
                raise AposeError(f"the draft changed while this question was open (another edit, maybe in another "
                                 f"tab); nothing was done. Select step {i + 1} again and check its pose and mates")

        for c in clients:
            with c.gui.add_modal("This move breaks the step's mates") as modal:
                c.gui.add_markdown(f"Step {i + 1} is placed by {len(self.app.asm.steps[i].mates)} mate(s); the new pose "
                                   "does not keep them.")
                drop = c.gui.add_button("Drop the mates (keep the new pose)")
                back = c.gui.add_button("Snap back")

            def on_drop(e, modal=modal):
                def act(cl):
                    still_asked(modal)
                    self.app.set_assembly(authoring.set_mates(self.app.asm, i, []), cl, record=False)
                self.app.guarded("Drop mates")(act)(e)

            def on_back(e, modal=modal):
                def act(cl):
                    still_asked(modal)
                    self.app.set_assembly(before, cl, record=False)
                    self.sync_typed_pose()
                self.app.guarded("Snap back")(act)(e)

            drop.on_click(on_drop)
            back.on_click(on_back)

    def set_pose(self, T: np.ndarray, client, sync_fields: bool = True, gizmo: bool | None = None) -> None:
        """The selected step's part at T (T_base_part). `sync_fields`: rewrite the typed pose fields from it;
        `gizmo`: put the gizmo on it (default: as `sync_fields`). A typed pose moves the gizmo but leaves
        the fields as typed; mid-drag neither moves (the gizmo stays where the hand puts it)."""
        self.app.asm = authoring.edit_step(self.app.asm, self.step_index, T_base_part=T)
        self.app.problems = authoring.problems(self.app.asm)
        if not [p for p in self.app.problems if p.key != "steps"]:
            self.app.valid_asm = self.app.asm
        if sync_fields:
            self.sync_typed_pose()
        self.refresh_status()
        self.refresh_assembly_scene(gizmo=sync_fields if gizmo is None else gizmo)

    def on_gizmo(self, event) -> None:
        """A drag of the gizmo (viser's TransformControlsEvent: phase start / update / end, the pose in
        event.target). The part follows every update; the typed fields are rewritten at the end."""
        if event.phase == "start":
            self._drag_dropped = False
        if self._drag_dropped:  # the rest of a drag that another tab's edit stopped
            if event.phase == "end":
                self._drag_dropped = False
                self.refresh_assembly_scene(gizmo=True)  # the gizmo back on the part
            return
        if self._syncing or self.step_index is None or not self.app.asm.steps:
            return
        g = event.target
        step = self.app.asm.steps[self.step_index]
        T_world_base = self._preview[step.base[0]]
        T = se3.inv(T_world_base) @ se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(g.wxyz)), np.asarray(g.position))
        if event.phase == "start" or self._drag_before is None:
            self._drag_before = self.app.asm
            self.app.history.record(self._drag_before)
        T = authoring.snap_pose(T, float(self.f_snap_mm.value or 0), float(self.f_snap_deg.value or 0),
                                since=self._drag_before.steps[self.step_index].T_base_part)
        self.set_pose(T, None, sync_fields=event.phase == "end")
        if event.phase == "end":
            before, self._drag_before = self._drag_before, None
            self.settle_mates(before, event.client)

    def drop_drag(self) -> bool:
        """Another tab changed the draft during a drag of this tab's gizmo: the drag stops where it is (the part
        stays where it was put; its updates until the mouse is let go are ignored), so that it never goes on
        over a step that moved or was deleted meanwhile. True when a drag was stopped."""
        if self._drag_before is None:
            return False
        self._drag_before, self._drag_dropped = None, True
        return True

    def make_pose_fields(self, t, e) -> None:
        """(Re)create the typed pose inputs holding `t` (mm) and `e` (°).

        A value the server pushes into an existing number input is shown, but the browser's input
        (Mantine's NumberInput in viser 1.1) keeps its own idea of the last value typed, and drops the
        next edit that it takes for no change: after "Add" step, typed translations vanished. Fresh
        inputs have no such memory, so the server never writes into these two; it replaces them, in
        the same place in the panel."""
        t = tuple(round(float(v), 4) for v in t)
        e = tuple(round(float(v), 4) for v in e)
        if tuple(self.f_t.value) == t and tuple(self.f_r.value) == e:
            return
        gui = self.app.ui.gui
        orders = (self.f_t.order, self.f_r.order)
        self.f_t.remove()
        self.f_r.remove()
        with self.steps_folder:
            self.f_t = gui.add_vector3("Translation (mm)", t, step=0.1, order=orders[0], **VECTOR_MM)
            self.f_r = gui.add_vector3("Rotation xyz (°)", e, step=0.1, order=orders[1], **VECTOR_DEG)
        self.f_t.on_update(self.app.guarded("Translation")(self.on_typed_pose))
        self.f_r.on_update(self.app.guarded("Rotation")(self.on_typed_pose))

    def sync_typed_pose(self) -> None:
        if self.step_index is None:
            return
        self.make_pose_fields(*authoring.typed_pose(self.app.asm.steps[self.step_index].T_base_part))

    def on_play_sequence(self, client) -> None:
        """Play the assembly for a demo: each step's part comes in along its approach (when it has one), held by
        the gripper where the part has a grasp."""
        if self._player is not None and self._player.is_alive():  # a press while it plays stops it
            self.stop_play()
            self.app.notify(client, "Play", "stopped")
            return
        asm = self.app.valid_asm
        n = len(asm.steps)
        if n == 0:
            raise AposeError("nothing to play: add steps first")
        stop = self._stop_play = threading.Event()

        def upto(k: int) -> None:  # under the lock: another tab's edit may change the steps meanwhile
            with self.app.lock:
                self.f_upto.value = min(k, int(self.f_upto.max))

        def play():
            upto(0)
            if stop.wait(0.6):
                return
            for k, s in enumerate(asm.steps, start=1):
                upto(k)
                h = self.mesh_handles.get(s.part)
                with self.app.lock:
                    T_end, T_base = self._preview.get(s.part), self._preview.get(s.base[0])
                if s.approach is not None and h is not None and T_end is not None and T_base is not None:
                    for a in np.linspace(1.0, 0.0, 16):
                        T_now = s.approach.start(T_end, T_base) * a + T_end * (1 - a)  # a translation: blending is exact
                        h.position = pos(T_now)
                        with self.app.lock:  # the Grasps folder draws the gripper bringing it in
                            self.app.events.emit(Event.PLAYED, pid=s.part, T_world_part=T_now)
                        if stop.wait(0.04):
                            break
                elif T_end is not None:
                    with self.app.lock:
                        self.app.events.emit(Event.PLAYED, pid=s.part, T_world_part=T_end)
                if stop.wait(0.5):
                    break
            with self.app.lock:
                self.app.events.emit(Event.PLAYED, pid=None, T_world_part=None)
                if stop.is_set():  # stopped: the preview as the selection has it
                    self.preview_up_to_selected()

        self._player = self.app.start_thread(play, name="play sequence")

    def stop_play(self) -> None:
        """Stop Play sequence (a press while it plays, the tab closing); it ends within 0.04 s of its next frame."""
        self._stop_play.set()

    def refresh_steps(self) -> None:
        asm = self.app.asm
        self._syncing = True
        try:
            self.f_step_part.options = list(asm.parts) or ["—"]
            steps = [f"{i + 1}. {s.part}" for i, s in enumerate(asm.steps)] or ["—"]
            same_list = tuple(self.f_step.options) == tuple(steps)
            self.f_step.options = steps
            if self.step_index is not None:
                s = asm.steps[self.step_index]
                # a step the user chose in the page whose callback still waits for the lock (this drawing is for
                # another tab's edit, or an earlier action of this tab's) is not written over: the callback reads it
                chosen_meanwhile = (same_list and self._step_written[0] == self.step_index
                                    and self.f_step.value != self._step_written[1] and self.f_step.value in steps)
                if not chosen_meanwhile:
                    self.f_step.value = steps[self.step_index]
                    self._step_written = (self.step_index, steps[self.step_index])
                self.f_step_part.value = s.part
                self.make_pose_fields(*authoring.typed_pose(s.T_base_part))
            self.f_upto.max = max(len(asm.steps), 1)
            if self.f_upto.value > self.f_upto.max:  # viser keeps a value beyond a lowered max (steps deleted)
                self.f_upto.value = self.f_upto.max
            self.refresh_base_boxes(self.step_index)
        finally:
            self._syncing = False
        self.refresh_status()

    def refresh_status(self) -> None:
        bad = authoring.problem_steps(self.app.problems)
        rows = []
        for i, s in enumerate(self.app.asm.steps):
            style = "background:#fde2e2;" if i in bad else ("background:#e3ecfc;" if i == self.step_index else "")
            mark = "⚠ " if i in bad else ("▶ " if i == self.step_index else "")
            t = s.T_base_part[:3, 3] * 1000
            rows.append(f"<tr style='{style}'><td>{mark}{i + 1}</td><td>{esc(s.part)}</td><td>{esc(', '.join(s.base))}</td>"
                        f"<td>({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f})</td></tr>")
        body = "".join(rows) or "<tr><td colspan=4><i>no steps yet: press Add</i></td></tr>"
        self.steps_html.content = (
            "<table style='font-size:0.8em;width:100%;border-collapse:collapse'>"
            "<tr style='text-align:left'><th>#</th><th>part</th><th>on base</th><th>t (mm)</th></tr>" + body + "</table>")
        st = self.app.state
        if st.saved_path is None:
            saved = " Not saved yet."
        elif self.app.asm is st.saved_draft:  # as on disk: opened and not changed, or saved
            saved = (f" Opened from {esc(st.saved_path)}; no changes." if st.saved_how == "opened"
                     else f" Saved as {esc(st.saved_path)}.")
        else:
            saved = f" **Unsaved changes** ({'opened from' if st.saved_how == 'opened' else 'last saved as'} " \
                    f"{esc(st.saved_path)})."
        if not self.app.problems:
            self.status_md.content = f"✅ **Valid**: {len(self.app.asm.parts)} parts, {len(self.app.asm.steps)} steps.{saved}"
        else:
            lines = "\n".join(f"- {esc(p.key or 'file')}: {esc(p.what)}" for p in self.app.problems[:6])
            self.status_md.content = (f"⚠ **{len(self.app.problems)} problem(s)**; saving is off until fixed:\n{lines}"
                                      f"\n\n{saved.strip()}")

    def refresh_assembly_scene(self, gizmo: bool = True) -> None:
        """Meshes at their preview poses; the gizmo on the selected step's part."""
        asm = self.app.valid_asm
        diam = {}
        for p in asm.parts:
            try:
                diam[p] = self.app.model(p, asm).diameter
            except AposeError:
                pass
        upto = min(int(self.f_upto.value), len(asm.steps))
        explode = float(self.f_explode.value)
        centres = {p: self.app.model(p, asm).box_corners().mean(axis=0) for p in diam}
        self.app.state.preview = authoring.preview_poses(asm, upto, diam, explode, centres)
        show = self.app.current_view == "Assembly"
        for name in [n for n in self.app.nodes if n.startswith("/assembly/step_label")]:
            self.app.nodes.pop(name).remove()
        if explode > 0:  # the exploded view names each step at its part
            for i, st in enumerate(asm.steps[:upto]):
                if st.part in self._preview:
                    where = se3.transform_points(self._preview[st.part], centres[st.part][None])[0]
                    name = f"/assembly/step_label_{i}"
                    self.app.node(name, self.app.ui.scene.add_label(name, f"{i + 1}. {st.part}", position=tuple(where),
                                                                 anchor="bottom-center", font_screen_scale=0.8))
        shown_bodies: set = set()
        for pid in asm.parts:
            if pid not in diam:
                continue
            body = authoring.body_of(asm, pid)
            if body is not None and self._preview.get(pid) is not None:
                if body in shown_bodies:  # another region of a part drawn already (seats of one head): drawn once
                    if pid in self.mesh_handles:
                        self.mesh_handles.pop(pid).remove()
                    continue
                shown_bodies.add(body)
            h = self.mesh_handles.get(pid)
            if h is None:
                m = self.app.model(pid, asm)
                color = tuple(int(255 * c) for c in m.color)
                h = self.app.ui.scene.add_mesh_simple(f"/parts/{pid}", *shaded(m.mesh), color=color, flat_shading=False)
                self.mesh_handles[pid] = h
            T = self._preview.get(pid)
            h._apose_visible = T is not None
            h.visible = show and T is not None
            if T is not None:
                h.position, h.wxyz = pos(T), wxyz(T)
        for pid in [p for p in self.mesh_handles if p not in asm.parts]:
            self.mesh_handles.pop(pid).remove()
        self.draw_regions(asm)
        if gizmo:
            self.place_gizmo()
        elif self.step_index is not None and self.step_index < len(asm.steps):  # the dragged part follows the hand
            step = asm.steps[self.step_index]
            if step.part in self.mesh_handles and step.base[0] in self._preview:
                T = self._preview[step.base[0]] @ self.app.asm.steps[self.step_index].T_base_part
                self.mesh_handles[step.part].position, self.mesh_handles[step.part].wxyz = pos(T), wxyz(T)

    def draw_regions(self, asm) -> None:
        """Each shown part's region (its roi): the box's edges (a sphere's bounding box) and the faces in it, cyan
        over the part: what registration matches when the part is a base (the seats of one head all on it:
        authoring.preview_poses lays regions of one mesh on one spot)."""
        for name in [n for n in self.app.nodes if n.startswith("/assembly/roi")]:
            self.app.nodes.pop(name).remove()
        for pid, part in asm.parts.items():
            T = self._preview.get(pid)
            if part.roi is None or T is None:
                continue
            region = self.app.model(pid, asm).region.copy()
            region.vertices = region.vertices + REGION_LIFT_M * region.vertex_normals  # drawn over the part, not in it
            seg = inspection.box_segments(part.roi.corners(), np.eye(4)).astype(np.float32)
            name = f"/assembly/roi_{pid}"
            self.app.node(name, self.app.ui.scene.add_line_segments(
                name, seg, inspection.CYAN, thickness=3.0, thickness_units="screen", wxyz=wxyz(T), position=pos(T)))
            name = f"/assembly/roi_faces_{pid}"
            self.app.node(name, self.app.ui.scene.add_mesh_simple(
                name, *shaded(region), color=inspection.CYAN, opacity=0.6, wxyz=wxyz(T), position=pos(T)))
            top = part.roi.corners().max(axis=0)  # which seat is which: its name over its region
            where = se3.transform_points(T, np.array([[part.roi.center[0], part.roi.center[1], top[2]]]))[0]
            name = f"/assembly/roi_label_{pid}"
            self.app.node(name, self.app.ui.scene.add_label(name, pid, position=tuple(where), anchor="bottom-center",
                                                                font_screen_scale=0.8))

    def preview_radius(self) -> float:
        ds = [self.app.model(p, self.app.valid_asm).diameter for p in self._preview if p in self.app.valid_asm.parts]
        return max(ds or [0.1]) / 2.0

    def on_explode(self) -> None:
        self.refresh_assembly_scene()
        self.app.frame_camera_on_assembly()  # the whole assembly stays in view as it spreads out

    def place_gizmo(self) -> None:
        asm = self.app.valid_asm
        i = self.step_index
        editable = (i is not None and i < len(asm.steps) and asm.steps[i].part == self.app.asm.steps[i].part
                    and float(self.f_explode.value) == 0.0 and asm.steps[i].base[0] in self._preview
                    and not self.app.state.picks  # a picked face waits for its partner: the gizmo steps aside
                    and not self.app.state.region_handles)  # ... and while a region's handles are on show
        if not editable:
            for name in ("/assembly/gizmo", "/assembly/base_frame"):
                if name in self.app.nodes:
                    self.app.nodes.pop(name).remove()
            return
        step = asm.steps[i]
        T_world_base = self._preview[step.base[0]]
        T = T_world_base @ step.T_base_part
        d = self.app.model(step.part, asm).diameter
        frame = self.app.nodes.get("/assembly/base_frame")
        if frame is None:
            frame = self.app.node("/assembly/base_frame", self.app.ui.scene.add_frame(
                "/assembly/base_frame", axes_length=0.3 * d, axes_radius=0.01 * d))
        frame.position, frame.wxyz = pos(T_world_base), wxyz(T_world_base)
        g = self.app.nodes.get("/assembly/gizmo")
        if g is None:
            g = self.app.node("/assembly/gizmo", self.app.ui.scene.add_transform_controls(
                "/assembly/gizmo", scale=max(0.6 * d, 0.25 * self.preview_radius()), depth_test=False))  # on top of the parts
            g.on_update(lambda e: self.app.guarded("Move part")(lambda c: self.on_gizmo(e))(e))
        self._syncing = True
        try:
            g.position, g.wxyz = pos(T), wxyz(T)
        finally:
            self._syncing = False
        if step.part in self.mesh_handles:  # the part shows where the draft puts it, even past the slider
            h = self.mesh_handles[step.part]
            h._apose_visible = True
            h.visible = self.app.current_view == "Assembly"
            h.position, h.wxyz = pos(T), wxyz(T)
