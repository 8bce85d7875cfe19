"""Drawing a part's region (its roi) in the 3D view with the mouse: *Drag region* puts two handles on the part
chosen in the Parts folder, the region's centre and a box's corner (a sphere's point on its surface along the
part's x). Dragging the centre moves the region, dragging the corner resizes it (a box about its centre); the
region's outline (orange) and the Region fields follow the drag, and letting go sets the region as *Set region*
does: one undoable edit, refused where the region holds none of the part's surface (the fields keep what was
dragged). Typed Region fields move the handles. The handles live under `/assembly/region_edit`, in the part's
frame, at the part's place in the preview (`state.preview`)."""

from __future__ import annotations

import numpy as np

from apose_studio.assembly.roi import Roi
from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.studio import authoring, inspection
from apose_studio.studio.state import Event
from apose_studio.studio.widgets import pos, wxyz

ROOT = "/assembly/region_edit"
SNAP_M = 0.0005  # a handle moves by whole 0.5 mm, as the part gizmo by its default translation snap
WHOLE = "whole part"  # the Region (roi) dropdown's choice of no region
EDGE_COLOUR = inspection.AMBER  # the region as dragged, beside the cyan of the region set


def mm(values) -> tuple[float, ...]:
    """Metres as the Region fields show them: millimetres, to the micrometre."""
    return tuple(round(float(v) * 1000.0, 3) for v in values)


def sphere_segments(centre: np.ndarray, radius: float, n: int = 48) -> np.ndarray:
    """(3n, 2, 3) line segments of a sphere's three great circles (about x, y and z) round `centre`."""
    t = np.linspace(0.0, 2 * np.pi, n + 1)
    c, s = np.cos(t), np.sin(t)
    z = np.zeros_like(t)
    rings = [np.stack(a, axis=1) for a in ((c, s, z), (z, c, s), (s, z, c))]
    pts = [np.asarray(centre, float) + radius * r for r in rings]
    return np.concatenate([np.stack([p[:-1], p[1:]], axis=1) for p in pts])


class RegionGizmo:
    """The *Drag region* checkbox of the Parts folder and the handles it shows. `files` is the Parts folder's
    panel (assembly_panel.AssemblyPanel): its Part, Region (roi) and Region fields and its *Set region*."""

    def __init__(self, app, files):
        self.app, self.files = app, files
        self._centre = self._corner = None  # the handles' places (part frame, metres) while shown
        self._from = None  # where the dragged handle stood when its drag started
        self._dropped = False  # another tab changed the draft during this drag: its rest is ignored
        self._side = None  # which corner the last drag left the corner handle at (signs from the centre)

    def build(self, gui) -> None:
        self.f_drag = gui.add_checkbox("Drag region", False, hint="handles on the chosen part: its region's centre "
                                       "(moves it) and a corner (resizes it); letting go sets the region")
        self.f_drag.on_update(self.app.guarded("Drag region")(self.on_toggle))
        self.app.events.on(Event.DRAFT_CHANGED, self.place)  # Undo, a moved part, another part chosen
        self.app.events.on(Event.MESHES_CHANGED, lambda pid: self.place())

    def on_toggle(self, client) -> None:
        self.offer(client)
        self.place()
        self.frame_cameras()

    def frame_cameras(self) -> None:
        """The cameras on the region being dragged, its handles within reach (on a 324 mm head a seat's arrows had
        been a few pixels long)."""
        want = self.wanted()
        if want is None or self._centre is None or self.app.current_view != "Assembly":
            return
        pid, T = want
        size = np.asarray(self.files.f_roi_size.value, float) / 1000.0
        radius = max(float(np.linalg.norm(size)) / 2, 0.15 * self.app.model(pid).diameter)
        self.app.look_at(se3.transform_points(T, self._centre[None])[0], 2.0 * radius, np.array([1.0, -1.0, 0.75]))

    def chosen(self) -> None:
        """Another part chosen: its corner handle starts on the +x+y+z corner."""
        self._side = None

    def offer(self, client) -> None:
        """Drag region ticked on a part without a region: its fields show a box to start from (offered_box, not
        set yet), said so."""
        pid = self.files.f_part.value
        if not (self.f_drag.value and pid in self.app.asm.parts and self.app.asm.parts[pid].roi is None):
            return
        self.files.show_region_fields("box", *self.offered_box(pid))
        self.app.notify(client, "Drag region", f"{pid}: a box round the part's top half to start from; drag its "
                        "handles (centre: moves it, corner: resizes it), letting go sets it as the part's region")

    def offered_box(self, pid: str) -> tuple[np.ndarray, np.ndarray]:
        """(centre, size), metres, part frame: a box round the part's top half, its full width and depth and the
        upper half of its height, a snap past its faces: it holds the part's top faces whatever its shape (a box
        round the middle alone can lie wholly inside the solid, and be refused as it stands)."""
        lo, hi = np.asarray(self.app.model(pid).mesh.bounds, float)
        size = hi - lo + 2 * SNAP_M
        size[2] = (hi[2] - lo[2]) / 2 + 2 * SNAP_M
        centre = (lo + hi) / 2
        centre[2] = hi[2] - (hi[2] - lo[2]) / 4
        return np.round(centre / SNAP_M) * SNAP_M, np.maximum(np.round(size / SNAP_M) * SNAP_M, 2 * SNAP_M)

    def reach(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi), part frame: the handles stay within the part's box grown by its diameter each way (a region
        farther out holds none of it; a page's drag of 9 km had made the Region fields refuse their values)."""
        m = self.app.model(self.files.f_part.value)
        lo, hi = np.asarray(m.mesh.bounds, float)
        return lo - m.diameter, hi + m.diameter

    def wanted(self) -> tuple[str, np.ndarray] | None:
        """(the part, its T_world_part in the preview) when the handles are to be shown, else None."""
        pid = self.files.f_part.value
        if not self.f_drag.value or pid not in self.app.asm.parts or self.files.f_roi.value == WHOLE:
            return None
        T = self.app.state.preview.get(pid)
        return None if T is None else (pid, T)

    def place(self) -> None:
        """Show the handles where the Region fields say (or take them away)."""
        want = self.wanted()
        if want is None:
            self.remove()
            return
        pid, T = want
        kind = self.files.f_roi.value
        centre = np.asarray(self.files.f_roi_centre.value, float) / 1000.0
        size = np.asarray(self.files.f_roi_size.value, float) / 1000.0
        self._centre, self._corner = authoring.roi_handles(kind, centre, size, self._side)
        scene = self.app.ui.scene
        frame = self.app.nodes.get(ROOT)
        if frame is None:
            frame = self.app.node(ROOT, scene.add_frame(ROOT, show_axes=False))
        frame.position, frame.wxyz = pos(T), wxyz(T)
        d = self.app.model(pid).diameter  # the arrows: about the region's size, never lost on the part or filling the view
        scale = float(np.clip(0.6 * np.max(np.abs(size)), 0.06 * d, 0.2 * d))
        for which, where in (("centre", self._centre), ("corner", self._corner)):  # (set here, no update callback runs)
            name = f"{ROOT}/{which}"
            g = self.app.nodes.get(name)
            if g is None or abs(g._impl.props.scale - scale) > 1e-9:
                if g is not None:
                    self.app.nodes.pop(name).remove()
                g = self.app.node(name, scene.add_transform_controls(
                    name, scale=scale, disable_rotations=True, depth_test=False))
                g.on_update(lambda e, which=which: self.app.guarded("Drag region")(lambda c: self.on_handle(e, which))(e))
            g.position = tuple(where)
        self.draw_outline(kind)
        self.handles_shown(True)

    def drop_drag(self) -> bool:
        """Another tab changed the draft during a drag of a handle: the drag stops (nothing is set; the updates
        until the mouse is let go are ignored), so that it never sets a region on a part that changed or went
        meanwhile. True when a drag was stopped."""
        if self._from is None:
            return False
        self._from, self._dropped = None, True
        return True

    def remove(self) -> None:
        for name in sorted((n for n in self.app.nodes if n == ROOT or n.startswith(ROOT + "/")), reverse=True):
            self.app.nodes.pop(name).remove()  # the handles and outline before their frame
        self._centre = self._corner = None
        self.handles_shown(False)

    def handles_shown(self, shown: bool) -> None:
        if self.app.state.region_handles != shown:
            self.app.state.region_handles = shown
            self.app.events.emit(Event.REGION_HANDLES)  # the step's gizmo steps aside, or comes back

    def draw_outline(self, kind: str) -> None:
        size = authoring.roi_from_handles(kind, self._centre, self._corner, 2 * SNAP_M)
        if kind == "box":
            seg = inspection.box_segments(Roi("box", tuple(self._centre), size=tuple(size)).corners(), np.eye(4))
        else:
            seg = sphere_segments(self._centre, size[0] / 2)
        seg = seg.astype(np.float32)
        for which, where in (("centre", self._centre), ("corner", self._corner)):  # which handle is which
            name = f"{ROOT}/label_{which}"
            label = self.app.nodes.get(name)
            if label is None:
                label = self.app.node(name, self.app.ui.scene.add_label(
                    name, f"region {which}", position=(0.0, 0.0, 0.0), anchor="top-left", font_screen_scale=0.8))
            label.position = tuple(where)
        name = f"{ROOT}/outline"
        old = self.app.nodes.pop(name, None)
        if old is not None:
            old.remove()
        self.app.node(name, self.app.ui.scene.add_line_segments(name, seg, EDGE_COLOUR, thickness=3.0,
                                                                    thickness_units="screen"))

    def on_handle(self, event, which: str) -> None:
        """A drag of a handle (phase start / update / end): the outline follows every update; at the end the
        Region fields are written and the region set (files.on_roi), one undoable edit."""
        if event.phase == "start":
            self._dropped = False
        if self._dropped:  # the rest of a drag that another tab's edit stopped
            if event.phase == "end":
                self._dropped = False
                self.place()  # the handles back on the region as it is
            return
        if self.wanted() is None or self._centre is None:
            return
        if event.phase == "start" or self._from is None:
            self._from = self._centre if which == "centre" else self._corner
        raw = np.asarray(event.target.position, float)
        p = self._from + np.round((raw - self._from) / SNAP_M) * SNAP_M  # moved by whole snaps, as the part gizmo
        lo, hi = self.reach()
        p = np.clip(p, lo, hi)
        kind = self.files.f_roi.value
        if which == "centre":
            self._corner, self._centre = np.clip(self._corner + (p - self._centre), lo, hi), p
            other = self.app.nodes.get(f"{ROOT}/corner")
            if other is not None:
                other.position = tuple(self._corner)
        else:
            self._corner = p
        self.draw_outline(kind)
        size = authoring.roi_from_handles(kind, self._centre, self._corner, 2 * SNAP_M)
        if event.phase != "end":  # the fields follow the drag (written into; recreated once it ends)
            self.files.f_roi_centre.value, self.files.f_roi_size.value = mm(self._centre), mm(size)
            return
        self._from = None
        self._side = self._corner - self._centre  # the corner stays where it was let go (dragged past the centre too)
        self.files.show_region_fields(kind, self._centre, size, fresh=True)
        try:
            self.files.on_roi(event.client)
        except AposeError as e:  # the region stays as it was: its fields and handles back there
            self.files.show_part_colour()
            self.place()
            raise AposeError(f"not set: {e}; the region is as it was") from None
