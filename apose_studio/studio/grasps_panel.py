"""The Assembly tab's Grasps folder: how the robot's gripper holds the selected step's part.

Pick a face of the step's part (as for a mate: the Mates folder's picks), choose where the gripper comes
from, and *Grasp at picked face* adds a grasp across the part there (`robot.grasping.grasp_at_face`: a flat
face and the face opposite, or across a round face). The step's grasps are listed; the chosen one is drawn
as a parallel-jaw gripper at the place (and, where the step has an approach, at the pre-place, fainter),
in the gripper's own colour. Grasps are saved in the assembly file (`parts.<id>.grasps`) and undone like
any edit."""

from __future__ import annotations

import numpy as np

from apose_studio.errors import AposeError
from apose_studio.robot.grasping import APPROACHES, grasp_at_face, gripper_mesh
from apose_studio.studio import authoring, inspection
from apose_studio.studio.state import Event
from apose_studio.studio.widgets import pos, wxyz

GRIPPER_COLOUR = inspection.GRIPPER
NONE = "—"
CARRY = "/assembly/gripper/carry"  # the gripper that carries each part in Play sequence


class GraspsPanel:
    def __init__(self, app):
        self.app = app
        app.events.on(Event.DRAFT_CHANGED, self.refresh)
        app.events.on(Event.STEP_SELECTED, lambda index: self.refresh())
        app.events.on(Event.PLAYED, lambda pid, T_world_part: self.drop() if pid is None else self.carry(pid, T_world_part))

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Grasps", expand_by_default=False) as self.folder:
            gui.add_markdown("Pick a face of the step's **part** (Mates folder), choose where the gripper comes "
                             "from, then *Grasp at picked face*: the jaws close on a flat face and the one "
                             "opposite, or across a round face.")
            self.f_from = gui.add_dropdown("Gripper comes", tuple(APPROACHES), initial_value="from +z")
            b = gui.add_button("Grasp at picked face")
            b.on_click(self.app.guarded("Grasp")(self.on_add))
            self.f_grasp = gui.add_dropdown("Grasp", (NONE,))
            self.f_grasp.on_update(self.app.guarded("Grasp")(lambda c: self.draw()))
            self.info = gui.add_markdown("")
            b = gui.add_button("Delete grasp")
            b.on_click(self.app.guarded("Delete grasp")(self.on_delete))

    def step_part(self) -> str:
        i, asm = self.app.state.step_index, self.app.asm
        if i is None or i >= len(asm.steps):
            raise AposeError("select a step first: grasps belong to the part it places")
        return asm.steps[i].part

    def on_add(self, client) -> None:
        pid = self.step_part()
        pick = self.app.state.picks.get("part")
        if pick is None or pick[0] != pid:
            raise AposeError(f"pick a face of {pid} first (click it in the 3D view)")
        f = pick[1]
        grasp = grasp_at_face(self.app.model(pid).mesh, f.kind, f.point, f.direction, f.radius,
                              APPROACHES[self.f_from.value], "grasp")
        gripper = self.app.asm.gripper
        if gripper is not None and gripper.max_width is not None and grasp.width > gripper.max_width:
            raise AposeError(f"the part is {grasp.width * 1000:.1f} mm across there, more than the gripper opens "
                             f"({gripper.max_width * 1000:.0f} mm); pick a narrower place")
        asm = authoring.add_grasp(self.app.asm, pid, grasp)
        self.app.set_assembly(asm, client)
        self.f_grasp.value = asm.parts[pid].grasps[-1].name
        self.app.notify(client, "Grasp added", f"{asm.parts[pid].grasps[-1].name} on {pid}: the jaws open "
                        f"{grasp.width * 1000:.1f} mm; saved with the assembly")

    def on_delete(self, client) -> None:
        pid = self.step_part()
        if self.f_grasp.value == NONE:
            raise AposeError(f"{pid} has no grasp to delete")
        self.app.set_assembly(authoring.delete_grasp(self.app.asm, pid, self.f_grasp.value), client)

    def refresh(self) -> None:
        i, asm = self.app.state.step_index, self.app.asm
        grasps = asm.parts[asm.steps[i].part].grasps if i is not None and i < len(asm.steps) and \
            asm.steps[i].part in asm.parts else ()
        options = tuple(g.name for g in grasps) or (NONE,)
        if tuple(self.f_grasp.options) != options:
            self.f_grasp.options = options
        if self.f_grasp.value not in options:
            self.f_grasp.value = options[0]
        self.draw()

    def chosen(self):
        """(part id, grasp) chosen for the selected step, or None."""
        i, asm = self.app.state.step_index, self.app.asm
        if i is None or i >= len(asm.steps) or asm.steps[i].part not in asm.parts:
            return None
        pid = asm.steps[i].part
        g = next((g for g in asm.parts[pid].grasps if g.name == self.f_grasp.value), None)
        return None if g is None else (pid, g)

    def draw(self) -> None:
        for name in ("/assembly/gripper/place", "/assembly/gripper/preplace"):
            if name in self.app.nodes:
                self.app.nodes.pop(name).remove()
        chosen = self.chosen()
        if chosen is None:
            self.info.content = ""
            return
        pid, g = chosen
        s = self.app.asm.steps[self.app.state.step_index]
        T_world_part = self.app.state.T_world_shown(pid)
        if T_world_part is None:
            return
        t = g.T_part_gripper[:3, 3] * 1000
        self.info.content = (f"<small>TCP at ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) mm in {pid}'s frame, opening "
                             f"{'—' if g.width is None else f'{g.width * 1000:.1f} mm'}</small>")
        mesh = gripper_mesh(g.width, self.app.asm.gripper)
        poses = {"place": T_world_part @ g.T_part_gripper}
        T_world_base = self.app.state.T_world_shown(s.base[0])
        if s.approach is not None and T_world_base is not None:
            poses["preplace"] = s.approach.start(T_world_part, T_world_base) @ g.T_part_gripper
        for what, T in poses.items():
            name = f"/assembly/gripper/{what}"
            h = self.app.ui.scene.add_mesh_simple(
                name, np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32), color=GRIPPER_COLOUR,
                opacity=1.0 if what == "place" else 0.35, flat_shading=True,
                wxyz=wxyz(T), position=pos(T))
            self.app.node(name, h)

    def carry(self, pid: str, T_world_part: np.ndarray) -> None:
        """Play sequence: the gripper holding part `pid` (by its first grasp) at T_world_part; nothing when the
        part has no grasp."""
        part = self.app.valid_asm.parts.get(pid)
        if part is None or not part.grasps:
            self.drop()
            return
        g = part.grasps[0]
        T = T_world_part @ g.T_part_gripper
        h = self.app.nodes.get(CARRY)
        if h is None or getattr(h, "_apose_for", None) != (pid, g.name):
            self.drop()
            mesh = gripper_mesh(g.width, self.app.valid_asm.gripper)
            h = self.app.ui.scene.add_mesh_simple(CARRY, np.asarray(mesh.vertices, np.float32),
                                                      np.asarray(mesh.faces, np.uint32), color=GRIPPER_COLOUR,
                                                      flat_shading=True, wxyz=wxyz(T), position=pos(T))
            h._apose_for = (pid, g.name)
            self.app.node(CARRY, h)
        else:
            h.wxyz, h.position = wxyz(T), pos(T)

    def drop(self) -> None:
        if CARRY in self.app.nodes:
            self.app.nodes.pop(CARRY).remove()
