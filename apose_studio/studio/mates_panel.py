"""The Assembly tab's Mates and Approach folders: faces picked with a click in the 3D view become
mates (two round faces snap coaxial at once; two flat faces offer Contact / Aligned with a gap), the
step's mates listed and edited (offset, angle, flip, delete, lock the turn), and the step's approach
drawn as an arrow on the part. Picking geometry is `picking` (pure), editing is `authoring` (pure).

The picks live in the studio's shared state (the Steps panel steps its gizmo aside while one waits:
PICKS_CHANGED); the selected step, the preview poses and the drawn meshes are read from it. The list
follows DRAFT_CHANGED and STEP_SELECTED."""

from __future__ import annotations

import time

import numpy as np

from apose_studio.assembly.mates import angle_axis, in_base_frame
from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.studio import authoring
from apose_studio.studio.picking import FacePicker, Feature
from apose_studio.studio.state import Event
from apose_studio.studio.widgets import MM_RANGE, esc, pos, wxyz

PICK_COLOURS = {"part": (120, 255, 0), "base": (255, 0, 255)}  # lime and magenta: in no part palette
APPROACH_COLOUR = (255, 110, 0)
HIGHLIGHT_TRIANGLES = 60000  # at most this many triangles of a picked face are sent to the page
DIRECTIONS = {"none": None, "along the mate axis": "mate", "-z": (0, 0, -1), "+z": (0, 0, 1), "-x": (-1, 0, 0),
              "+x": (1, 0, 0), "-y": (0, -1, 0), "+y": (0, 1, 0)}
HELP = ("Click a face of the step's **part** and one of its **base** (picked faces light up: part "
        "<span style='color:#78ff00'>■</span>, base <span style='color:#ff00ff'>■</span>). Two round faces "
        "make a coaxial mate at once; two flat faces offer Contact or Aligned, with the gap below. While a "
        "pick waits for its partner the gizmo steps aside; pick the base first if it is in the way.")


class MatesPanel:
    def __init__(self, app):
        self.app = app
        self.pickers: dict[int, tuple] = {}  # id(mesh) -> (mesh, FacePicker)
        self._warming: set = set()
        app.events.on(Event.DRAFT_CHANGED, self.show_step)
        app.events.on(Event.STEP_SELECTED, lambda index: self.on_step_selected())

    @property
    def picks(self) -> dict[str, tuple[str, Feature]]:
        """"part" / "base" -> (part id, feature in its frame) (`state.picks`)."""
        return self.app.state.picks

    def on_step_selected(self) -> None:
        """Faces picked for another step's mate are dropped: a mate is made of the selected step's faces only."""
        if self.picks:
            self.clear_picks()
        self.show_step()

    def show_step(self) -> None:
        """The selected step's mates listed; its parts' pickers built ahead of the first click."""
        self.refresh()
        i, asm = self.app.state.step_index, self.app.asm
        if i is not None and i < len(asm.steps):
            s = asm.steps[i]
            self.warm_up([p for p in (s.part, *s.base) if p in asm.parts])

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Mates") as self.folder:
            gui.add_markdown(HELP)
            self.picked_md = gui.add_markdown("*nothing picked*")
            self.f_gap = gui.add_number("Gap (mm)", 0.0, step=0.1, **MM_RANGE, hint="contact/aligned: distance along the base's normal")
            self.b_planes = gui.add_button_group("Mate flat faces", ("Contact", "Aligned"))
            self.b_planes.on_click(lambda e: self.app.guarded("Mate")(lambda c: self.on_plane_mate(e.target.value, c))(e))
            b = gui.add_button("Clear picks")
            b.on_click(self.app.guarded("Clear picks")(lambda c: self.clear_picks()))
            self.list_html = gui.add_html("")
            self.f_mate = gui.add_dropdown("Mate", ("—",))
            self.f_value = gui.add_number("Offset (mm) / angle (°)", 0.0, step=0.1, **MM_RANGE)
            self.b_value = gui.add_button("Set offset / angle")
            self.b_value.on_click(self.app.guarded("Set")(self.on_set_value))
            row = gui.add_button_group("Mate actions", ("Flip", "Delete", "Lock turn"))
            row.on_click(lambda e: self.app.guarded(e.target.value)(lambda c: self.on_mate_action(e.target.value, c))(e))
        with gui.add_folder("Approach"):
            self.f_app_dir = gui.add_dropdown("Direction", tuple(DIRECTIONS), initial_value="none")
            self.f_app_len = gui.add_number("Length (mm)", 30.0, min=0.0, max=MM_RANGE["max"], step=1.0)
            b = gui.add_button("Set approach")
            b.on_click(self.app.guarded("Approach")(self.on_set_approach))

    # ------------------------------------------------------------------------------------ picking

    def picker(self, pid: str) -> FacePicker:
        return self._picker_of(self.app.model(pid).mesh)

    def _picker_of(self, mesh) -> FacePicker:
        """The picker of a loaded mesh (models are cached, so a mesh object stands for its part)."""
        held = self.pickers.get(id(mesh))
        if held is None or held[0] is not mesh:  # (the mesh is held too, so its id is not reused)
            held = self.pickers[id(mesh)] = (mesh, FacePicker(mesh))
        return held[1]

    def warm_up(self, pids) -> None:
        """Build the pickers of these parts in the background, so the first click answers at once."""
        todo = [p for p in pids if p not in self._warming]
        if not todo:
            return
        self._warming.update(todo)

        def run():
            for p in todo:
                try:
                    with self.app.lock:
                        mesh = self.app.model(p).mesh
                    self._picker_of(mesh)
                except Exception:  # a part that fails to load says so when it is clicked
                    pass

        self.app.start_thread(run, name="face pickers")

    def listen(self, client) -> None:
        """Clicks anywhere in this tab's 3D view go to `on_click` (not clicks per mesh: a clickable mesh
        in front of the gizmo would take its drags). viser 1.1 keeps the "send me scene clicks" switch
        in the page's 3D view, which starts up seconds after the tab connects (WebGL in software) and
        forgets a switch sent before; so the switch is sent again with the view's camera reports (the
        view is up, or the user is turning it) until the first click comes back."""
        state = {"heard": False, "last": 0.0}

        def on_click(event):
            state["heard"] = True
            self.app.guarded("Pick a face")(lambda c: self.on_click(event))(event)

        def on_camera(_):
            now = time.monotonic()
            if now - state["last"] < 0.5:
                return
            if state["last"]:
                client.scene.remove_click_callback(on_click)
            state["last"] = now
            client.scene.on_click()(on_click)

        client.camera.on_update(on_camera)

    def on_click(self, event) -> None:
        """A click in the 3D view: the nearest shown part its ray meets is the one picked."""
        if self.app.current_view != "Assembly" or self.app.state.step_index is None:
            return
        o, d = np.asarray(event.ray_origin, float), np.asarray(event.ray_direction, float)
        best = None
        for pid in self.app.state.meshes:
            T = self.app.state.T_world_shown(pid)
            if T is None or pid not in self.app.asm.parts:
                continue
            T_part_world = se3.inv(T)
            hit = self.picker(pid).hit(se3.transform_points(T_part_world, o[None])[0], T_part_world[:3, :3] @ d)
            if hit is not None:
                dist = float(np.linalg.norm(se3.transform_points(T, hit[1][None])[0] - o))
                if best is None or dist < best[0]:
                    best = (dist, pid)
        if best is not None:
            self.on_pick(best[1], event)

    def on_pick(self, pid: str, event) -> None:
        i = self.app.state.step_index
        if self.app.current_view != "Assembly" or i is None or i >= len(self.app.asm.steps):
            return
        step = self.app.asm.steps[i]
        side = "part" if pid == step.part else "base" if pid in step.base else None
        if side is None:
            raise AposeError(f"{pid} is not in step {i + 1}; pick a face of {step.part} or of its base "
                             f"({', '.join(step.base)})")
        T_world = self.app.state.T_world_shown(pid)
        if T_world is None:
            return
        T_part_world = se3.inv(T_world)
        origin = se3.transform_points(T_part_world, np.asarray(event.ray_origin, float)[None])[0]
        direction = T_part_world[:3, :3] @ np.asarray(event.ray_direction, float)
        feature = self.picker(pid).pick(origin, direction)
        if feature is None:
            raise AposeError("the click did not meet the part's surface; click squarely on a face")
        if feature.kind == "other":
            raise AposeError(f"that face of {pid} is neither flat nor round (a fillet, a thread or a freeform "
                             "surface); pick a flat face or a round one (a bore, a shaft)")
        self.picks[side] = (pid, feature)
        self.show_picks()
        if len(self.picks) == 2:
            self.maybe_mate(event.client)

    def maybe_mate(self, client) -> None:
        fp, fb = self.picks["part"][1], self.picks["base"][1]
        if fp.is_axis and fb.is_axis:
            self.make_mate("coaxial", client)
        elif fp.is_axis != fb.is_axis:
            self.picks.pop("base")
            self.show_picks()
            raise AposeError("a round face and a flat face make no mate; pick a face of the same kind on the base")

    def on_plane_mate(self, kind: str, client) -> None:
        if len(self.picks) < 2:
            raise AposeError("pick a flat face of the part and one of its base first (click them in the 3D view)")
        if self.picks["part"][1].is_axis or self.picks["base"][1].is_axis:
            raise AposeError(f"{kind} joins two flat faces; the picks are round (they make a coaxial mate)")
        self.make_mate(kind.lower(), client)

    def make_mate(self, kind: str, client) -> None:
        i = self.app.state.step_index
        (pp, fp), (bp, fb) = self.picks["part"], self.picks["base"]
        step = self.app.asm.steps[i] if i is not None and i < len(self.app.asm.steps) else None
        if step is None or pp != step.part or bp not in step.base:  # the step changed since (here or in another tab)
            self.clear_picks()
            raise AposeError(f"the faces were picked on {pp} and {bp}, " + (
                f"not on step {i + 1}'s {step.part} and its base" if step is not None else "and no step is selected")
                + "; pick the faces again")
        mate = authoring.mate_from_picks(self.app.asm, i, kind, bp, fb, fp, float(self.f_gap.value or 0.0) / 1000.0)
        asm = authoring.set_mates(self.app.asm, i, [*self.app.asm.steps[i].mates, mate])
        self.clear_picks()
        self.app.set_assembly(asm, client)  # the typed pose fields follow the draft

    def clear_picks(self) -> None:
        self.picks.clear()
        self.show_picks()

    def show_picks(self) -> None:
        for side in ("part", "base"):
            for name in (f"/assembly/pick_{side}", f"/assembly/axis_{side}"):
                if name in self.app.nodes:
                    self.app.nodes.pop(name).remove()
        lines = []
        for side, (pid, f) in self.picks.items():
            T = self.app.state.T_world_shown(pid)
            if T is None:
                continue
            lines.append(f"- {side}: **{esc(pid)}**, {esc(f.describe())}")
            m = self.app.model(pid)
            shown = f.faces[::-(-len(f.faces) // HIGHLIGHT_TRIANGLES)]  # a huge face lights up in a fine spread
            tris = m.mesh.faces[shown]
            n = m.mesh.face_normals[shown]
            v = (m.mesh.vertices[tris] + 0.002 * m.diameter * n[:, None, :]).reshape(-1, 3)  # just above the face
            name = f"/assembly/pick_{side}"
            h = self.app.ui.scene.add_mesh_simple(name, v.astype(np.float32), np.arange(len(v)).reshape(-1, 3).astype(np.uint32),
                                                      color=PICK_COLOURS[side], position=pos(T), wxyz=wxyz(T))
            self.app.node(name, h)
            if f.is_axis:
                seg = np.array([[f.point - 0.6 * m.diameter * f.direction, f.point + 0.6 * m.diameter * f.direction]])
                name = f"/assembly/axis_{side}"
                self.app.node(name, self.app.ui.scene.add_line_segments(
                    name, seg.astype(np.float32), PICK_COLOURS[side], thickness=0.004 * m.diameter,
                    position=pos(T), wxyz=wxyz(T)))
        self.picked_md.content = "\n".join(lines) if lines else "*nothing picked*"
        self.app.events.emit(Event.PICKS_CHANGED)  # the gizmo hides while a pick waits, so the faces under it can be clicked

    # ------------------------------------------------------------------------------------ the list

    def refresh(self) -> None:
        """The selected step's mates, free degrees of freedom and approach arrow."""
        i = self.app.state.step_index
        asm = self.app.asm
        if i is None or i >= len(asm.steps):
            self.list_html.content = "<i>select a step</i>"
            self.f_mate.options = ("—",)
            self.draw_approach()
            return
        s = asm.steps[i]
        rows = []
        for k, m in enumerate(s.mates):
            on = esc(m.base_part or s.base[0])
            what = {"coaxial": "flipped" if m.flip else "", "contact": f"gap {m.offset * 1000:.2f} mm",
                    "aligned": f"gap {m.offset * 1000:.2f} mm", "angle": f"{m.degrees:.1f}°", "fixed": ""}[m.type]
            rows.append(f"<tr><td>{k + 1}</td><td>{m.type}</td><td>{on}</td><td>{what}</td></tr>")
        if rows:
            free = "; ".join(s.free) if s.free else "the pose is fixed"
            self.list_html.content = ("<table style='font-size:0.8em;width:100%'><tr style='text-align:left'><th>#</th>"
                                      "<th>mate</th><th>on</th><th></th></tr>" + "".join(rows) + "</table>"
                                      f"<div style='font-size:0.8em'>{esc(free)}</div>")
        else:
            self.list_html.content = f"<i style='font-size:0.8em'>step {i + 1} has no mates: its pose is typed</i>"
        options = tuple(f"{k + 1}. {m.type}" for k, m in enumerate(s.mates)) or ("—",)
        if tuple(self.f_mate.options) != options:
            self.f_mate.options = options
        self.draw_approach()

    def selected_mate(self) -> int:
        i = self.app.state.step_index
        if i is None or not self.app.asm.steps[i].mates:
            raise AposeError("the selected step has no mates: pick faces to make one")
        return min(int(str(self.f_mate.value).split(".")[0]) - 1, len(self.app.asm.steps[i].mates) - 1)

    def on_set_value(self, client) -> None:
        i, k = self.app.state.step_index, self.selected_mate()
        m = self.app.asm.steps[i].mates[k]
        v = float(self.f_value.value or 0.0)
        if m.type in ("contact", "aligned"):
            asm = authoring.edit_mate(self.app.asm, i, k, offset=v / 1000.0)
        elif m.type == "angle":
            asm = authoring.edit_mate(self.app.asm, i, k, degrees=v)
        else:
            raise AposeError(f"a {m.type} mate has no offset or angle to set")
        self.app.set_assembly(asm, client)  # the typed pose fields follow the draft

    def on_mate_action(self, action: str, client) -> None:
        i = self.app.state.step_index
        if action == "Lock turn":
            if i is None:
                raise AposeError("select a step first")
            asm = authoring.lock_turn(self.app.asm, i)
        else:
            k = self.selected_mate()
            m = self.app.asm.steps[i].mates[k]
            if action == "Flip":
                if m.type != "coaxial":
                    raise AposeError("only a coaxial mate flips (its axes opposed); a contact is always face to face")
                asm = authoring.edit_mate(self.app.asm, i, k, flip=not m.flip)
            else:
                mates = list(self.app.asm.steps[i].mates)
                del mates[k]
                asm = authoring.set_mates(self.app.asm, i, mates)
        self.app.set_assembly(asm, client)  # the typed pose fields follow the draft

    # ------------------------------------------------------------------------------------ approach

    def on_set_approach(self, client) -> None:
        i = self.app.state.step_index
        if i is None:
            raise AposeError("select a step first")
        choice = DIRECTIONS[self.f_app_dir.value]
        s = self.app.asm.steps[i]
        if choice == "mate":
            axis = angle_axis(in_base_frame(s.mates, s.base[0], self.app.asm.step_view(i + 1).T_base_members))
            if axis is None:
                raise AposeError("no coaxial or contact mate to take the direction from; choose an axis")
            centre = s.T_base_part[:3, 3]  # come in from the side the part is on, towards the base
            choice = -axis if float(axis @ centre) > 0 else axis
        length = float(self.f_app_len.value or 0.0) / 1000.0
        asm = authoring.set_approach(self.app.asm, i, choice, length)
        self.app.set_assembly(asm, client)

    def draw_approach(self) -> None:
        name = "/assembly/approach"
        if name in self.app.nodes:
            self.app.nodes.pop(name).remove()
        i = self.app.state.step_index
        asm = self.app.asm
        if i is None or i >= len(asm.steps) or asm.steps[i].approach is None or self.app.current_view != "Assembly":
            return
        s = asm.steps[i]
        T_world_part = self.app.state.T_world_shown(s.part)
        T_world_base = self.app.state.T_world_shown(s.base[0])
        if T_world_part is None or T_world_base is None:
            return
        m = self.app.model(s.part)
        end = se3.transform_points(T_world_part, m.box_corners().mean(axis=0)[None])[0]
        d = T_world_base[:3, :3] @ s.approach.direction
        start = end - s.approach.distance * d
        side = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        head = 0.2 * s.approach.distance
        segs = np.array([[start, end], [end, end - head * d + 0.5 * head * side], [end, end - head * d - 0.5 * head * side]])
        self.app.node(name, self.app.ui.scene.add_line_segments(
            name, segs.astype(np.float32), APPROACH_COLOUR, thickness=0.01 * m.diameter))
