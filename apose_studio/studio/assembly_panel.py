"""The Assembly tab's File and Parts folders: open, new, save (atomic, asking before it replaces a file
this studio did not open), download; name and units; parts added by path, folder or upload, their
colours and removal. Every path goes through the studio's workspace.

The file the draft came from or was saved to is `state.saved_path`. A part whose mesh must be drawn
anew is MESHES_CHANGED; an opened file DRAFT_OPENED; a save DRAFT_SAVED. Name, units and the parts
table follow DRAFT_CHANGED."""

from __future__ import annotations

import logging
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

from apose_studio.assembly.fileio import atomic_write_bytes, describe_path
from apose_studio.assembly.mesh import supported_extensions
from apose_studio.assembly.model import dump_assembly, load_assembly, save_assembly
from apose_studio.assembly.roi import ROI_KINDS, Roi, region_mesh
from apose_studio.errors import AposeError
from apose_studio.safeio import check_path_text, read_bytes
from apose_studio.studio import authoring
from apose_studio.studio.region_gizmo import WHOLE, RegionGizmo, mm
from apose_studio.studio.state import Event, shared
from apose_studio.studio.widgets import MAX_UPLOAD_BYTES, MM_RANGE, UNITS, VECTOR_MM, esc, hex_colour, send_download
from apose_studio.text import unsafe_char

ROI_CHOICES = (WHOLE, *ROI_KINDS)
REGION_SIZE_MM = {k: (2.0 * v,) * 3 for k, v in MM_RANGE.items()}  # a region's sides, or a sphere's diameter: twice
# the coordinate limit a file's radius may reach (a 9 km sphere in a file had failed the Open as an internal error)  # the Region dropdown: no roi, or its shape

log = logging.getLogger(__name__)


def _same_bytes(path: Path, content: bytes) -> bool:
    """The regular file at `path` holds exactly `content` (a pipe or device there is never the same)."""
    try:
        return path.is_file() and path.stat().st_size == len(content) and read_bytes(path, "a mesh", len(content)) == content
    except AposeError:
        return False


class AssemblyPanel:
    saved_path = shared("saved_path", "the file the draft was opened from or last saved to (`state.saved_path`)")
    saved_draft = shared("saved_draft", "the draft as opened or last saved (`state.saved_draft`)")

    def __init__(self, app):
        self.app = app
        self._syncing = False
        self._pending_save: Path | None = None  # a file that Save would replace, waiting for "Replace"
        self._shown_path = ""  # what the Assembly file field was last set to here (not typed)
        self.region_gizmo = RegionGizmo(app, self)  # Drag region: the region's handles in the 3D view
        app.events.on(Event.DRAFT_CHANGED, self.refresh_files)
        app.events.on(Event.DRAFT_OPENED, self.show_file)  # another tab's Open or Save names the file here too
        app.events.on(Event.DRAFT_SAVED, self.show_file)

    def show_file(self) -> None:
        """The Assembly file field names the file the draft was opened from or saved to, unless this tab's user
        typed another path there since (their next Open, New or Save acts on what they typed)."""
        if self.saved_path is None or self.f_path.value == str(self.saved_path):
            return
        if self.f_path.value.strip() in ("", self._shown_path):
            self.f_path.value = self._shown_path = str(self.saved_path)

    def drop_region_drag(self) -> bool:
        """Drag region's drag stopped by another tab's edit (RegionGizmo.drop_drag)."""
        return self.region_gizmo.drop_drag()

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("File"):
            self.f_path = gui.add_text("Assembly file", "", hint="path on the server; relative mesh paths resolve against its folder")
            row = gui.add_button_group("File actions", ("Open", "New", "Save", "Download"))
            row.on_click(self.on_file_action)
            self.f_name = gui.add_text("Name", self.app.asm.name)
            self.f_units = gui.add_dropdown("Units", UNITS, initial_value=self.app.asm.units,
                                            hint="unit of mesh coordinates and translations in the file")
            self.f_name.on_update(self.app.guarded("Rename")(self.on_name))
            self.f_units.on_update(self.app.guarded("Units")(self.on_units))
        with gui.add_folder("Parts") as self.parts_folder:
            self.parts_html = gui.add_html("")
            self.f_mesh = gui.add_text("Mesh path or folder", "", hint=f"on the server: {', '.join(supported_extensions())}")
            b = gui.add_button("Add part(s)")
            b.on_click(self.app.guarded("Add part")(self.on_add_parts))
            self.upload = gui.add_upload_button("Upload mesh", hint=f"up to {MAX_UPLOAD_BYTES // 2**20} MB; saved beside the assembly file")
            self.upload.on_upload(self.app.guarded("Upload")(self.on_upload))
            self.f_part = gui.add_dropdown("Part", ("—",))
            self.f_part.on_update(self.app.guarded("Part")(self.on_part_chosen))
            self.f_color = gui.add_rgb("Colour", (230, 158, 0))
            self.f_color.on_update(self.app.guarded("Colour")(self.on_color))
            self.f_roi = gui.add_dropdown("Region (roi)", ROI_CHOICES, hint="as a base, only this region of the part is "
                                          "registered (a seat on an engine head); drawn cyan on the part")
            self.f_roi.on_update(self.on_region_typed)
            self.f_roi_centre = self.f_roi_size = None
            self.make_region_fields((0.0, 0.0, 0.0), (50.0, 50.0, 50.0))
            b = gui.add_button("Set region")
            b.on_click(self.app.guarded("Set region")(self.on_roi))
            self.region_gizmo.build(gui)
            b = gui.add_button("Remove part", color="red")
            b.on_click(self.app.guarded("Remove part")(self.on_remove_part))

    def open_assembly(self, path: Path, client=None, confine: bool = True) -> None:
        """Open an assembly file. `confine`: its meshes must lie in the workspace, as typed paths must (the
        page's Open); a file named on the command line at start is the user's own choice and is not confined."""
        asm = self.app.desk.open(path, confine)  # the draft, its meshes loaded first, the undo history cleared
        self.app.events.emit(Event.MESHES_CHANGED, pid=None)
        self.app.state.step_index = 0 if asm.steps else None
        self.f_path.value = self._shown_path = str(asm.path)
        self.app.set_assembly(asm, client, record=False)
        self.app.events.emit(Event.DRAFT_OPENED)
        self.app.frame_camera_on_assembly()
        self.warn_units(client)

    def warn_units(self, client) -> None:
        warnings = [w for w in (self.app.model(p).unit_warning for p in self.app.asm.parts) if w]
        if warnings:
            self.app.notify(client, "Units look wrong", "\n".join(warnings), error=True)

    def on_file_action(self, event) -> None:
        action = event.target.value
        handler = {"Open": self.on_open, "New": self.on_new, "Save": self.on_save, "Download": self.on_download}[action]
        self.app.guarded(action)(handler)(event)

    def on_open(self, client) -> None:
        text = self.f_path.value.strip()
        if not text:
            raise AposeError("type the path of an assembly file (on the server) into 'Assembly file' first")
        self.open_assembly(self.app.workspace.resolve(text, "assembly file"), client)
        self.app.notify(client, "Opened", f"{self.app.asm.name}: {len(self.app.asm.parts)} parts, {len(self.app.asm.steps)} steps")

    def on_new(self, client) -> None:
        """A new, empty draft that Save will write to the path typed in 'Assembly file' (a .yaml file that
        does not exist yet, or a folder to hold untitled.yaml); an existing file is never a new one's target."""
        text = self.f_path.value.strip()
        target = self.app.workspace.resolve(text or "untitled.yaml", "assembly file")
        if target.is_dir():
            target = target / "untitled.yaml"
        if target.suffix.lower() not in (".yaml", ".yml"):
            raise AposeError(f"{target.name}: a new assembly is saved as a .yaml file; type a path ending in .yaml")
        if target.exists():
            raise AposeError(f"{target} already exists: press Open to edit it, or type a new file name for the new "
                             "assembly into 'Assembly file'")
        if not target.parent.is_dir():
            raise AposeError(f"{target.parent}: folder does not exist; create it or type another path")
        self.app.events.emit(Event.MESHES_CHANGED, pid=None)
        self.app.state.step_index = None
        name = target.stem
        self.app.valid_asm = authoring.new_assembly(name, self.f_units.value, target.parent)  # an empty preview
        self.app.history.clear()  # a new file starts its own history
        self.saved_path = self.saved_draft = None
        self.app.set_assembly(authoring.new_assembly(name, self.f_units.value, target.parent), client, quiet=True,
                              record=False)
        self.f_path.value = self._shown_path = str(target)
        self.app.notify(client, "New assembly", f"{name}: add parts, then steps; Save writes {target}")

    def save_target(self) -> Path:
        text = self.f_path.value.strip()
        if not text:
            raise AposeError("type where to save into 'Assembly file' (a .yaml path on the server)")
        path = self.app.workspace.resolve(text, "assembly file")
        if path.suffix.lower() not in (".yaml", ".yml"):
            raise AposeError(f"{path.name}: save as a .yaml file")
        if not path.parent.is_dir():
            raise AposeError(f"{path.parent}: folder does not exist; create it or pick another path")
        if path.exists() and not path.is_file():
            raise AposeError(f"{path}: {describe_path(path, 'a .yaml file')}")
        return path

    def on_save(self, client, confirmed: bool = False) -> None:
        """Save the draft (never an invalid one). Replacing a file the studio did not open or save asks
        first; the replaced version is kept as NAME.yaml.bak."""
        self.app.require_valid()
        path = self.save_target()
        if path.exists() and path != self.saved_path and not confirmed:
            self.ask_replace(client, path)
            return
        path = save_assembly(self.app.asm, path, backup=True)
        self.saved_path, self.app.state.saved_how = path, "saved"
        self.app.asm = load_assembly(path)  # what is on disk is what the studio now edits (paths re-anchored)
        self.app.valid_asm = self.saved_draft = self.app.asm
        self.app.events.emit(Event.DRAFT_SAVED)
        bak = path.with_name(path.name + ".bak")
        self.app.notify(client, "Saved", str(path) + (f" (previous version: {bak.name})" if bak.exists() else ""))

    def ask_replace(self, client, path: Path) -> None:
        """A dialog in the tab that pressed Save: replace a file this studio did not open, or not."""
        if client is None:
            raise AposeError(f"{path} exists and was not opened here; open it first, or save under another name")
        with client.gui.add_modal("Replace file?") as modal:
            client.gui.add_markdown(f"**{esc(path)}** exists, and this studio did not open it. Replace it with the "
                                    f"draft? The current file is kept as {esc(path.name)}.bak.")
            yes = client.gui.add_button("Replace", color="red")
            no = client.gui.add_button("Cancel")

        def replace(event) -> None:
            modal.close()
            if self.f_path.value.strip() and self.save_target() == path:
                self.on_save(event.client, confirmed=True)
            else:
                raise AposeError("the path in 'Assembly file' changed meanwhile; press Save again")

        yes.on_click(lambda e: self.app.guarded("Save")(lambda c: replace(e))(e))
        no.on_click(lambda e: modal.close())

    def on_download(self, client) -> None:
        self.app.require_valid()
        folder = self.save_target().parent if self.f_path.value.strip() else authoring.folder_of(self.app.asm)
        text = dump_assembly(self.app.asm, folder)
        send_download(client, f"{self.app.asm.name}.yaml", text.encode("utf-8"))

    def on_name(self, client) -> None:
        if self._syncing:
            return

        name = self.f_name.value.strip()
        bad = unsafe_char(name)
        if not name or bad:
            self.refresh_files()  # the field shows the name the draft keeps, not the refused one
            why = "the assembly needs a name" if not name else f"a name cannot hold the invisible character {bad}"
            raise AposeError(f"{why}; it stays {self.app.asm.name!r}")
        self.app.set_assembly(replace(self.app.asm, name=name), client)

    def on_units(self, client) -> None:
        if self._syncing or self.f_units.value == self.app.asm.units:
            return

        self.app.events.emit(Event.MESHES_CHANGED, pid=None)
        self.app.set_assembly(replace(self.app.asm, units=self.f_units.value), client)
        if self.app.current_view == "Assembly":  # the parts changed size by 10-1000x: the old zoom shows nothing
            self.app.frame_camera_on_assembly()
        self.warn_units(client)

    def add_mesh_file(self, path: Path, client) -> str:
        """Add a mesh as a part (a STEP file with several solids as a part per solid); returns the ids."""
        asm, pids = authoring.add_mesh_parts(self.app.asm, path)
        models = [self.app.model(pid, asm) for pid in pids]  # raises MeshError before anything changes
        self.app.set_assembly(asm, client, quiet=True)
        for model in models:
            if model.unit_warning:
                self.app.notify(client, "Units look wrong", model.unit_warning, error=True)
        return ", ".join(pids)

    def on_add_parts(self, client) -> None:
        text = self.f_mesh.value.strip()
        if not text:
            raise AposeError("type a mesh path or a folder of meshes (on the server) into 'Mesh path or folder'")
        path = self.app.workspace.resolve(text, "mesh")
        already: list[str] = []
        if path.is_dir():
            files = sorted(p for p in path.iterdir() if p.suffix.lower() in supported_extensions() and p.is_file())
            if not files:
                raise AposeError(f"{path}: no meshes here ({', '.join(supported_extensions())})")
            # a folder added again adds what is new in it; one file typed again is a second part from it
            used = {part.mesh.resolve(): pid for pid, part in self.app.asm.parts.items()}
            part_of = {f: used.get(f.resolve()) for f in files}
            already = [f"{f.name} (as {pid})" for f, pid in part_of.items() if pid is not None]
            files = [f for f, pid in part_of.items() if pid is None]
            if not files:
                self.app.notify(client, "Nothing new in the folder",
                                f"every mesh in {path} is a part already: " + ", ".join(already[:8]))
                return
        elif path.is_file():
            files = [path]
        else:
            raise AposeError(f"{path}: {describe_path(path, 'a mesh file or a folder of meshes')}")
        added, failed = [], []
        for f in files:
            try:
                added.append(self.add_mesh_file(self.app.workspace.resolve(f, "mesh"), client))  # a link may lead out
            except AposeError as e:
                failed.append(str(e))
        if added:
            self.app.notify(client, "Parts added", ", ".join(added) + (
                f"; already parts, not added again: {', '.join(already[:8])}" if already else ""))
        if failed:
            self.app.notify(client, "Some meshes were not added", "\n".join(failed[:5]), error=True)
        self.app.frame_camera_on_assembly()

    def on_upload(self, client) -> None:
        f = self.upload.value
        if f is None:
            return
        if len(f.content) > MAX_UPLOAD_BYTES:
            raise AposeError(f"{f.name} is {len(f.content) / 2**20:.0f} MB; the limit is {MAX_UPLOAD_BYTES // 2**20} MB")
        name = Path(check_path_text(f.name, "the uploaded file's name")).name  # no ESC, newline or bidi in a file we create
        if Path(name).suffix.lower() not in supported_extensions():
            raise AposeError(f"{name}: not a mesh format the studio reads ({', '.join(supported_extensions())})")
        folder = self.app.workspace.resolve(authoring.folder_of(self.app.asm) / "meshes", "assembly file")
        folder.mkdir(parents=True, exist_ok=True)
        if name in ("", ".", "..") or name.startswith(".") or "\x00" in name or len(name) > 200:
            raise AposeError(f"{name[:60]!r}: not a file name to save an upload under; rename the file")
        target = folder / name
        k = 2
        while (target.exists() or target.is_symlink()) and not _same_bytes(target, f.content):
            target = folder / f"{Path(name).stem}_{k}{Path(name).suffix}"
            k += 1
            if k > 1000:
                raise AposeError(f"{folder}: holds 1000 other files named like {name}; tidy the folder")
        wrote = not target.exists()
        if wrote:
            atomic_write_bytes(target, f.content)
        try:
            pid = self.add_mesh_file(target, client)
        except AposeError:
            if wrote:
                target.unlink(missing_ok=True)  # a corrupt upload leaves nothing behind (a file already there stays)
            raise
        self.app.notify(client, "Part uploaded", f"{pid} ← {name} (saved as {target})")

    def on_part_chosen(self, client) -> None:
        """Part chosen: its colour and region in the fields; with Drag region ticked, its handles (a part without a
        region is offered a box to start from)."""
        self.show_part_colour()
        self.region_gizmo.chosen()
        self.region_gizmo.offer(client)
        self.region_gizmo.place()
        self.region_gizmo.frame_cameras()

    def show_part_colour(self) -> None:
        """The Colour and Region fields show the selected part's."""
        if self.f_part.value not in self.app.asm.parts:
            return
        roi = self.app.asm.parts[self.f_part.value].roi
        if roi is None:  # no region: the fields hold the box Drag region would start from, not another part's
            self.show_region_fields("box", *self.region_gizmo.offered_box(self.f_part.value))
            self.f_roi.value = ROI_CHOICES[0]
        else:
            self.show_region_fields(roi.kind, roi.center, roi.size if roi.kind == "box" else (2.0 * roi.radius,) * 3)
        rgb = tuple(int(round(255 * c)) for c in self.app.model(self.f_part.value).color)
        if tuple(self.f_color.value) != rgb:
            self._syncing = True
            try:
                self.f_color.value = rgb
            finally:
                self._syncing = False

    def make_region_fields(self, centre_mm, size_mm) -> None:
        """(Re)create the Region centre and size inputs holding these values (mm), in their place in the Parts
        folder: recreated, not written into, for the reason steps_panel.make_pose_fields gives."""
        old = (self.f_roi_centre, self.f_roi_size)
        orders = None if old[0] is None else (old[0].order, old[1].order)
        gui = self.app.ui.gui
        with self.parts_folder if orders is not None else nullcontext():  # the first time: in build's `with`
            centre = gui.add_vector3("Region centre (mm)", tuple(centre_mm), step=0.5, **VECTOR_MM,
                                     hint="in the part's own frame", order=orders and orders[0])
            try:
                size = gui.add_vector3("Region size (mm)", tuple(size_mm), step=0.5, **REGION_SIZE_MM,
                                       hint="a box's full sides; a sphere's diameter is the first number",
                                       order=orders and orders[1])
            except ValueError:
                centre.remove()
                raise
        if orders is not None:  # the old ones go once the new ones stand: a value they refuse leaves the old in place
            old[0].remove()
            old[1].remove()
        self.f_roi_centre, self.f_roi_size = centre, size
        for f in (self.f_roi_centre, self.f_roi_size):
            f.on_update(self.on_region_typed)

    def show_region_fields(self, kind: str, centre, size, fresh: bool = False) -> None:
        """The Region fields showing a region (kind, centre and size in metres; a sphere's size is its diameter
        three times); not set on the part until Set region (or a drag's end). `fresh`: recreated even when they
        show these values (a drag wrote into them as it went)."""
        self.f_roi.value = kind
        c, s = mm(centre), mm(size)
        if fresh or tuple(self.f_roi_centre.value) != c or tuple(self.f_roi_size.value) != s:
            self.make_region_fields(c, s)

    def on_region_typed(self, event) -> None:
        """A Region field changed in the page: Drag region's handles follow it (values the server writes do not
        come here: their event has no client)."""
        if event.client is not None:
            self.app.guarded("Region")(lambda c: self.region_gizmo.place())(event)

    def on_color(self, client) -> None:
        if self._syncing or self.f_part.value not in self.app.asm.parts:
            return
        pid = self.f_part.value
        rgb = tuple(c / 255.0 for c in self.f_color.value)
        self.app.events.emit(Event.MESHES_CHANGED, pid=pid)
        self.app.set_assembly(authoring.set_part_color(self.app.asm, pid, rgb), client)

    def on_roi(self, client) -> None:
        """Set region: the selected part's roi from the Region fields (none: the whole part). A region that holds
        none of the part's surface is refused, saying where the part lies."""
        pid = self.f_part.value
        if pid not in self.app.asm.parts:
            raise AposeError("choose a part first (Part), then its region")
        kind = self.f_roi.value
        roi = None
        if kind != ROI_CHOICES[0]:
            centre = tuple(float(v) / 1000.0 for v in self.f_roi_centre.value)
            size = tuple(float(v) / 1000.0 for v in self.f_roi_size.value)
            if min(size if kind == "box" else size[:1]) <= 0:
                raise AposeError(f"Region size: {'every side' if kind == 'box' else 'the diameter'} must be above 0 mm")
            roi = Roi("box", centre, size=size) if kind == "box" else Roi("sphere", centre, radius=size[0] / 2)
            region_mesh(self.app.model(pid).mesh, roi, f"part {pid!r}")  # refused here, before the draft changes
        self.app.events.emit(Event.MESHES_CHANGED, pid=pid)
        self.app.set_assembly(authoring.set_part_roi(self.app.asm, pid, roi), client)
        self.app.notify(client, "Region", f"{pid}: the whole part" if roi is None else
                        f"{pid}: {self.app.model(pid).region.area * 1e4:.1f} cm² of its surface in its {kind} (drawn cyan)")

    def on_remove_part(self, client) -> None:
        pid = self.f_part.value
        if pid not in self.app.asm.parts:
            raise AposeError("choose a part to remove")
        asm = authoring.remove_part(self.app.asm, pid)
        self.app.events.emit(Event.MESHES_CHANGED, pid=pid)
        self.app.set_assembly(asm, client)

    def refresh_files(self) -> None:
        asm = self.app.asm
        self._syncing = True
        try:
            self.f_name.value = asm.name
            self.f_units.value = asm.units
            self.f_part.options = list(asm.parts) or ["—"]
        finally:
            self._syncing = False
        self.show_part_colour()
        self.refresh_parts_table()

    def refresh_parts_table(self) -> None:
        rows = []
        for pid, part in self.app.asm.parts.items():
            try:
                m = self.app.model(pid)
            except AposeError as e:
                rows.append(f"<tr><td>{esc(pid)}</td><td colspan=4 style='color:#c00'>{esc(e)}</td></tr>")
                continue
            size = " × ".join(f"{v * 1000:.1f}" for v in m.size)
            if m.region is not None:  # what registers when the part is a base: its region, drawn cyan
                size += ("<br><span style='color:#08a;white-space:nowrap' title='the span of the surface in the region'>"
                         "region: " + " × ".join(f"{v * 1000:.1f}" for v in m.region.extents) + "</span>")
            warn = f"<br><span style='color:#c60'>⚠ {esc(m.unit_warning)}</span>" if m.unit_warning else ""
            rows.append(f"<tr><td style='white-space:nowrap'><span style='display:inline-block;width:10px;height:10px;background:{hex_colour(m.color)};"
                        f"border-radius:2px'></span> {esc(pid)}</td><td>{esc(part.mesh.name)}</td><td>{esc(self.app.asm.units)}</td>"
                        f"<td>{size}{warn}</td></tr>")
        body = "".join(rows) or "<tr><td colspan=4><i>no parts yet: add a mesh path, a folder, or upload</i></td></tr>"
        self.parts_html.content = (
            "<table style='font-size:0.8em;width:100%;border-collapse:collapse'>"
            "<tr style='text-align:left'><th>part</th><th>file</th><th>unit</th><th>size (mm)</th></tr>" + body + "</table>")
