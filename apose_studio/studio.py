"""The studio: a viser web GUI over the core. Tab "Assembly" authors assembly files, tab "Inspect"
shows datasets, captures and registrations.

Design: the GUI is an edge. Editing goes through `authoring` (pure, returns new Assemblies), drawing
through `inspection` (pure). Every callback runs through `_guarded`, so bad input becomes a
notification to the browser that caused it and the server keeps serving. The state is shared by all
browser tabs (one studio, one draft); notifications go to the tab that acted.
"""

from __future__ import annotations

import html
import logging
import threading
import time
import traceback
from dataclasses import dataclass
from functools import wraps
from pathlib import Path

import numpy as np

from . import authoring, inspection, se3
from .assembly import Assembly, dump_assembly, load_assembly, save_assembly
from .errors import AposeError, AssemblyError
from .fileio import describe_path
from .mesh import PartModel, load_part, supported_extensions
from .webguard import Workspace

log = logging.getLogger(__name__)

MAX_UPLOAD_BYTES = 200 * 1024 * 1024  # a CAD part above this is almost surely the wrong file
UNITS = ("m", "cm", "mm", "in")
PRESETS = ("default", "paper")
VIEWS = ("Assembly", "Inspect")
ACTIVE = "● "  # marks the 3D view on show in the button group
LAYERS = ("scene cloud", "target cloud", "source cloud", "boxes", "part at estimate", "labels", "camera")


def esc(text) -> str:
    """User- or file-derived text made safe to place in HTML or markdown (part ids, file names, messages)."""
    return html.escape(str(text), quote=True)


def _legend_html() -> str:
    items = "".join(f"<span style='white-space:nowrap;margin-right:10px'><span style='display:inline-block;width:14px;"
                    f"height:4px;vertical-align:middle;background:{_hex([c / 255 for c in rgb])}'></span> {esc(name)}</span>"
                    for name, rgb in inspection.LEGEND)
    return f"<div style='font-size:0.8em;line-height:1.8'>{items}</div>"


def _hex(color) -> str:
    return "#" + "".join(f"{int(round(255 * c)):02x}" for c in color)


def _wxyz(T: np.ndarray) -> tuple:
    return tuple(float(v) for v in se3.matrix_to_quat_wxyz(T[:3, :3]))


def _pos(T: np.ndarray) -> tuple:
    return tuple(float(v) for v in T[:3, 3])


class Studio:
    """One studio on one viser server. `assembly` and `dataset` are optional paths opened at start;
    `workspace` holds the folders whose files the page may name (default: see `default_workspace`)."""

    def __init__(self, server, assembly: str | Path | None = None, dataset: str | Path | None = None,
                 cache: inspection.ResultCache | None = None, workspace: Workspace | None = None):
        import viser  # noqa: F401  (imported here so the core never needs it)

        self.server = server
        self.workspace = workspace if workspace is not None else default_workspace(assembly, dataset)
        self.lock = threading.RLock()  # one edit at a time, whichever tab it comes from
        self.busy = threading.Lock()  # one estimation at a time
        self.asm: Assembly = authoring.new_assembly()
        self.valid_asm: Assembly = self.asm  # last draft without problems: what the preview shows
        self.models: dict[tuple, PartModel] = {}  # (mesh path, units, colour) -> PartModel
        self.mesh_handles: dict[str, object] = {}
        self.nodes: dict[str, object] = {}  # scene nodes by name (tests look here)
        self.step_index: int | None = None  # selected step, 0-based
        self.problems: list = authoring.problems(self.asm)  # the empty draft is not saveable either
        self._syncing = False
        self.frames = None  # a Dataset or a capture Frame
        self.frames_path: str | None = None
        self.frame = None
        self.cache = cache if cache is not None else inspection.ResultCache()
        self.contexts: dict = {}  # (assembly identity, step) -> StepContext
        self.result = None
        self.score = None
        self.stages: list = []
        self.saved_path: Path | None = None
        self.current_view = "Assembly"
        self._notice_timer: threading.Timer | None = None
        self._last_notice = ""
        self._preview: dict = {}
        self._part_models: dict = {}  # id(assembly) -> its PartModels, for the Inspect tab
        self._pending_save: Path | None = None  # a file that Save would replace, waiting for "Replace"
        with self.lock:  # a page that connects while the start-up files load waits for them
            self._build_gui()
            server.on_client_connect(self._on_connect)
            self._limit_uploads()
            if assembly is not None:
                self._open_assembly(Path(assembly))
            if dataset is not None:
                self._open_frames(str(dataset))

    # ------------------------------------------------------------------------------------ plumbing

    def notify(self, client, title: str, body: str, error: bool = False) -> None:
        """Tell the tab that acted (or every tab when no one did)."""
        (log.warning if error else log.info)("%s: %s", title, body)
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            try:
                c.add_notification(title, body, auto_close_seconds=None if error else 4.0,
                                   color="red" if error else "green")
            except Exception:  # a tab that just closed
                pass

    def _guarded(self, title: str):
        """Decorator for callbacks: AposeError -> its message; anything else -> a short report. Never raises."""
        def wrap(fn):
            @wraps(fn)
            def run(event=None):
                client = getattr(event, "client", None)
                try:
                    with self.lock:
                        fn(client)
                except AssemblyError as e:
                    lines = [str(p) for p in e.problems[:6]]
                    more = f"\n(+{len(e.problems) - 6} more)" if len(e.problems) > 6 else ""
                    self.notify(client, title, "\n".join(lines) + more, error=True)
                except AposeError as e:
                    self.notify(client, title, str(e), error=True)
                except Exception as e:  # a bug: say so, keep serving
                    log.error("%s failed:\n%s", title, traceback.format_exc())
                    self.notify(client, title, f"internal error ({type(e).__name__}: {e}); the server log has details",
                                error=True)
            return run
        return wrap

    def _on_connect(self, client) -> None:
        client.camera.up_direction = (0.0, 0.0, 1.0)

    def _limit_uploads(self) -> None:
        """Refuse an over-size upload when it starts, not after the server has buffered it all."""
        try:
            from viser import _messages

            gui = self.server.gui

            def check(client_id, message) -> None:
                if message.size_bytes > MAX_UPLOAD_BYTES:
                    gui._current_file_upload_states.pop(message.transfer_uuid, None)
                    client = self.server.get_clients().get(client_id)
                    self.notify(client, "Upload refused",
                                f"{message.filename} is {message.size_bytes / 2**20:.0f} MB; the limit is "
                                f"{MAX_UPLOAD_BYTES / 2**20:.0f} MB. Put the file on the server and type its path instead.",
                                error=True)

            gui._websock_interface.register_handler(_messages.FileTransferStartUpload, check)
        except Exception:  # viser changed its internals: the size is still checked after the upload
            log.info("early upload size check unavailable; checking after upload")

    # ----------------------------------------------------------------------------------------- GUI

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_layout="fixed", control_width="large", show_share_button=False,
                            brand_color=(40, 90, 230))
        self.server.scene.set_up_direction("+z")
        self.view = gui.add_button_group("3D view", VIEWS)
        self.view.on_click(lambda e: self._guarded("3D view")(lambda c: self._on_view_button(e.target.value))(e))
        tabs = gui.add_tab_group()
        with tabs.add_tab("Assembly"):
            self._build_assembly_tab()
        with tabs.add_tab("Inspect"):
            self._build_inspect_tab()
        self.server.scene.add_grid("/grid", width=1.0, height=1.0, cell_size=0.01, section_size=0.1,
                                   plane="xy", position=(0.0, 0.0, -0.0005))
        self._show_view("Assembly")

    def _on_view_button(self, label: str) -> None:
        which = label.removeprefix(ACTIVE)
        self._show_view(which)
        if which == "Inspect":
            self._frame_camera_on_frame()
        else:
            self._frame_camera_on_assembly()

    def _show_view(self, which: str) -> None:
        self.current_view = which
        self.view.options = tuple(ACTIVE + v if v == which else v for v in VIEWS)
        for name, handle in list(self.nodes.items()):
            if name.startswith("/assembly") or name.startswith("/inspect"):
                want = name.startswith("/assembly") == (which == "Assembly")
                handle.visible = want and getattr(handle, "_apose_visible", True)
        for pid, h in self.mesh_handles.items():
            h.visible = which == "Assembly" and getattr(h, "_apose_visible", True)

    def _node(self, name: str, handle, visible: bool = True):
        handle._apose_visible = visible
        handle.visible = visible and name.startswith("/" + self.current_view.lower())
        self.nodes[name] = handle
        return handle

    def _build_assembly_tab(self) -> None:
        gui = self.server.gui
        with gui.add_folder("File"):
            self.f_path = gui.add_text("Assembly file", "", hint="path on the server; relative mesh paths resolve against its folder")
            row = gui.add_button_group("File actions", ("Open", "New", "Save", "Download"))
            row.on_click(self._on_file_action)
            self.f_name = gui.add_text("Name", self.asm.name)
            self.f_units = gui.add_dropdown("Units", UNITS, initial_value=self.asm.units,
                                            hint="unit of mesh coordinates and translations in the file")
            self.f_name.on_update(self._guarded("Rename")(self._on_name))
            self.f_units.on_update(self._guarded("Units")(self._on_units))
        with gui.add_folder("Parts"):
            self.parts_html = gui.add_html("")
            self.f_mesh = gui.add_text("Mesh path or folder", "", hint=f"on the server: {', '.join(supported_extensions())}")
            b = gui.add_button("Add part(s)")
            b.on_click(self._guarded("Add part")(self._on_add_parts))
            self.upload = gui.add_upload_button("Upload mesh", hint=f"up to {MAX_UPLOAD_BYTES // 2**20} MB; saved beside the assembly file")
            self.upload.on_upload(self._guarded("Upload")(self._on_upload))
            self.f_part = gui.add_dropdown("Part", ("—",))
            self.f_part.on_update(self._guarded("Part")(lambda c: self._show_part_colour()))
            self.f_color = gui.add_rgb("Colour", (230, 158, 0))
            self.f_color.on_update(self._guarded("Colour")(self._on_color))
            b = gui.add_button("Remove part", color="red")
            b.on_click(self._guarded("Remove part")(self._on_remove_part))
        with gui.add_folder("Steps") as self.steps_folder:
            self.steps_html = gui.add_html("")
            self.f_step = gui.add_dropdown("Step", ("—",))
            self.f_step.on_update(self._guarded("Select step")(self._on_select_step))
            row = gui.add_button_group("Step actions", ("Add", "Delete", "Up", "Down"))
            row.on_click(self._on_step_action)
            self.f_step_part = gui.add_dropdown("Part to place", ("—",))
            self.f_step_part.on_update(self._guarded("Part to place")(self._on_step_part))
            self.f_base = gui.add_text("Base parts", "", hint="comma-separated part ids; the first is the frame of the pose")
            self.f_base.on_update(self._guarded("Base parts")(self._on_base))
            self.f_t = gui.add_vector3("Translation (mm)", (0.0, 0.0, 0.0), step=0.1)
            self.f_r = gui.add_vector3("Rotation xyz (°)", (0.0, 0.0, 0.0), step=0.1)
            self.f_t.on_update(self._guarded("Translation")(self._on_typed_pose))
            self.f_r.on_update(self._guarded("Rotation")(self._on_typed_pose))
            self.f_snap_mm = gui.add_number("Snap (mm)", 0.5, min=0.0, step=0.1, hint="0 = off")
            self.f_snap_deg = gui.add_number("Snap (°)", 5.0, min=0.0, step=1.0, hint="0 = off")
        with gui.add_folder("Preview"):
            self.f_upto = gui.add_slider("Assembled up to step", 0, 1, 1, 0)
            self.f_upto.on_update(self._guarded("Preview")(lambda c: self._refresh_assembly_scene()))
            self.f_explode = gui.add_slider("Explode", 0.0, 1.0, 0.05, 0.0)
            self.f_explode.on_update(self._guarded("Preview")(lambda c: self._on_explode()))
            b = gui.add_button("Play sequence")
            b.on_click(self._guarded("Play")(self._on_play_sequence))
        self.status_md = gui.add_markdown("")

    def _build_inspect_tab(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Data"):
            self.i_path = gui.add_text("Dataset or capture", "", hint="a folder from `apose render`, or rgb.png + depth.png + camera.json")
            b = gui.add_button("Open data")
            b.on_click(self._guarded("Open data")(lambda c: self._on_open_data(c)))
            self.i_step = gui.add_dropdown("Inspect step", ("—",))
            self.i_step.on_update(self._guarded("Step")(lambda c: self._on_frame_changed()))
            self.i_frame = gui.add_slider("Frame", 0, 1, 1, 0)
            self.i_frame.on_update(self._guarded("Frame")(lambda c: self._on_frame_changed()))
        with gui.add_folder("Estimate"):
            self.i_preset = gui.add_dropdown("Preset", PRESETS, initial_value="default")
            from .evaluate import MASK_SOURCES

            self.i_mask = gui.add_dropdown("Mask", MASK_SOURCES, initial_value=MASK_SOURCES[0],
                                           hint="gt: the dataset's masks; depth: table removal + 3D clustering; or a trained model")
            self.i_model = gui.add_text("Mask model (.pt)", "", hint="a model from `apose train-seg` for this assembly")
            b = gui.add_button("Use model")
            b.on_click(self._guarded("Mask model")(self._on_use_model))
            self.i_crop = gui.add_checkbox("Crop box", False, hint="limit depth masks to a box you drag around the base object")
            self.i_crop_size = gui.add_vector3("Crop size (mm)", (150.0, 150.0, 100.0), min=(1.0, 1.0, 1.0), step=5.0)
            self.i_crop.on_update(self._guarded("Crop box")(lambda c: self._show_crop()))
            self.i_crop_size.on_update(self._guarded("Crop box")(lambda c: self._show_crop()))
            self.i_upright = gui.add_checkbox("Upright", True,
                                              hint="where a table is seen, search first the yaw of the base standing on it as "
                                              "modelled, then freely if that fits poorly (preset default)")
            self.i_prior = gui.add_checkbox("Orientation prior", False, hint="take the CAD orientation as the base's (the paper's assumption)")
            for w in (self.i_preset, self.i_mask, self.i_prior, self.i_upright):
                w.on_update(self._guarded("Estimator")(lambda c: self._on_frame_changed()))
            row = gui.add_button_group("Run", ("Estimate frame", "Estimate step"))
            row.on_click(self._on_estimate)
            self.i_progress = gui.add_progress_bar(0.0, visible=False)
        with gui.add_folder("Registration replay"):
            self.i_stage = gui.add_slider("Stage", 0, 1, 1, 0, disabled=True)
            self.i_stage.on_update(self._guarded("Stage")(lambda c: self._show_stage()))
            b = gui.add_button("Play registration")
            b.on_click(self._guarded("Play registration")(self._on_play_registration))
            self.i_stage_md = gui.add_markdown("")
        with gui.add_folder("Result"):
            self.i_legend = gui.add_html(_legend_html())
            self.i_metrics = gui.add_markdown("")
            self.i_pose = gui.add_markdown("")
            b = gui.add_button("Download pose (JSON)", hint="T_world_part, T_camera_part and T_world_base of the estimate")
            b.on_click(self._guarded("Download pose")(self._on_download_pose))
            self.i_image = gui.add_image(np.zeros((48, 64, 3), np.uint8), label="RGB")
            self.i_full = gui.add_checkbox("Full image", False, hint="show the whole RGB image instead of the part around the object")
            self.i_full.on_update(self._guarded("Full image")(lambda c: self._draw_overlay()))
        with gui.add_folder("Layers", expand_by_default=False):
            self.layers = {k: gui.add_checkbox(k, True) for k in LAYERS}
            for w in self.layers.values():
                w.on_update(self._guarded("Layers")(lambda c: self._apply_layers()))

    # ------------------------------------------------------------------------------- assembly side

    def model(self, pid: str, asm: Assembly | None = None) -> PartModel:
        """A part's loaded mesh and derived geometry, cached by file, unit, colour and index."""
        asm = asm if asm is not None else self.asm
        part = asm.parts[pid]
        key = (str(part.mesh), asm.units, part.color, list(asm.parts).index(pid))
        if key not in self.models:
            self.models[key] = load_part(part, asm.units, key[3])
        return self.models[key]

    def _set_assembly(self, asm: Assembly, client=None, quiet: bool = False) -> None:
        """Adopt a new draft: validate, remember the last valid one, refresh every view of it."""
        self.asm = asm
        self.problems = authoring.problems(asm)
        hard = [p for p in self.problems if p.key != "steps"]  # "no steps yet" is not an error
        if not hard:
            self.valid_asm = asm
        elif not quiet:
            self._notice_problems_later(client)
        if self.step_index is not None and self.step_index >= len(asm.steps):
            self.step_index = len(asm.steps) - 1 if asm.steps else None
        self._refresh_assembly_widgets()
        self._refresh_assembly_scene()

    def _notice_problems_later(self, client, delay: float = 0.8) -> None:
        """Notify about a draft's problems once typing pauses (a text field updates on every key)."""
        if self._notice_timer is not None:
            self._notice_timer.cancel()

        def fire():
            with self.lock:
                hard = [p for p in self.problems if p.key != "steps"]
                text = "\n".join(f"{p.key}: {p.what}" for p in hard[:4])
                if hard and text != self._last_notice:
                    self._last_notice = text
                    self.notify(client, "Assembly has problems", text, error=True)
                elif not hard:
                    self._last_notice = ""

        self._notice_timer = threading.Timer(delay, fire)
        self._notice_timer.daemon = True
        self._notice_timer.start()

    def _open_assembly(self, path: Path, client=None) -> None:
        asm = load_assembly(path)
        for pid in asm.parts:  # load every mesh now: a bad one is reported before anything changes
            self.model(pid, asm)
        for h in self.mesh_handles.values():
            h.remove()
        self.mesh_handles.clear()
        self.step_index = 0 if asm.steps else None
        self.saved_path = asm.path
        self.f_path.value = str(asm.path)
        self._set_assembly(asm, client)
        self.f_upto.value = len(asm.steps)
        self._frame_camera_on_assembly()
        self._warn_units(client)

    def _warn_units(self, client) -> None:
        warnings = [w for w in (self.model(p).unit_warning for p in self.asm.parts) if w]
        if warnings:
            self.notify(client, "Units look wrong", "\n".join(warnings), error=True)

    def _frame_camera_on_assembly(self) -> None:
        """Frame every part shown in the preview (exploded or not)."""
        spheres = []
        for pid, T in self._preview.items():
            try:
                m = self.model(pid, self.valid_asm)
            except (AposeError, KeyError):
                continue
            spheres.append((se3.transform_points(T, m.box_corners()).mean(axis=0), m.diameter / 2.0))
        if not spheres:
            return
        centres = np.array([c for c, _ in spheres])
        centre = (centres.min(axis=0) + centres.max(axis=0)) / 2.0
        radius = max(float(np.linalg.norm(c - centre)) + r for c, r in spheres)
        self._look_at(centre, radius, np.array([1.0, -1.0, 0.75]))

    def _on_file_action(self, event) -> None:
        action = event.target.value
        handler = {"Open": self._on_open, "New": self._on_new, "Save": self._on_save, "Download": self._on_download}[action]
        self._guarded(action)(handler)(event)

    def _on_open(self, client) -> None:
        text = self.f_path.value.strip()
        if not text:
            raise AposeError("type the path of an assembly file (on the server) into 'Assembly file' first")
        self._open_assembly(self.workspace.resolve(text, "assembly file"), client)
        self.notify(client, "Opened", f"{self.asm.name}: {len(self.asm.parts)} parts, {len(self.asm.steps)} steps")

    def _on_new(self, client) -> None:
        """A new, empty draft that Save will write to the path typed in 'Assembly file' (a .yaml file that
        does not exist yet, or a folder to hold untitled.yaml); an existing file is never a new one's target."""
        text = self.f_path.value.strip()
        target = self.workspace.resolve(text or "untitled.yaml", "assembly file")
        if target.is_dir():
            target = target / "untitled.yaml"
        if target.suffix.lower() not in (".yaml", ".yml"):
            raise AposeError(f"{target.name}: a new assembly is saved as a .yaml file; type a path ending in .yaml")
        if target.exists():
            raise AposeError(f"{target} already exists: press Open to edit it, or type a new file name for the new "
                             "assembly into 'Assembly file'")
        if not target.parent.is_dir():
            raise AposeError(f"{target.parent}: folder does not exist; create it or type another path")
        for h in self.mesh_handles.values():
            h.remove()
        self.mesh_handles.clear()
        self.step_index = None
        name = target.stem
        self.valid_asm = authoring.new_assembly(name, self.f_units.value, target.parent)  # an empty preview
        self._set_assembly(authoring.new_assembly(name, self.f_units.value, target.parent), client, quiet=True)
        self.saved_path = None
        self.f_path.value = str(target)
        self.notify(client, "New assembly", f"{name}: add parts, then steps; Save writes {target}")

    def _save_target(self) -> Path:
        text = self.f_path.value.strip()
        if not text:
            raise AposeError("type where to save into 'Assembly file' (a .yaml path on the server)")
        path = self.workspace.resolve(text, "assembly file")
        if path.suffix.lower() not in (".yaml", ".yml"):
            raise AposeError(f"{path.name}: save as a .yaml file")
        if not path.parent.is_dir():
            raise AposeError(f"{path.parent}: folder does not exist; create it or pick another path")
        if path.exists() and not path.is_file():
            raise AposeError(f"{path}: {describe_path(path, 'a .yaml file')}")
        return path

    def _require_valid(self) -> None:
        if self.problems:
            raise AssemblyError(self.problems)

    def _on_save(self, client, confirmed: bool = False) -> None:
        """Save the draft (never an invalid one). Replacing a file the studio did not open or save asks
        first; the replaced version is kept as NAME.yaml.bak."""
        self._require_valid()
        path = self._save_target()
        if path.exists() and path != self.saved_path and not confirmed:
            self._ask_replace(client, path)
            return
        path = save_assembly(self.asm, path, backup=True)
        self.saved_path = path
        self.asm = load_assembly(path)  # what is on disk is what the studio now edits (paths re-anchored)
        self.valid_asm = self.asm
        self._refresh_status()
        bak = path.with_name(path.name + ".bak")
        self.notify(client, "Saved", str(path) + (f" (previous version: {bak.name})" if bak.exists() else ""))

    def _ask_replace(self, client, path: Path) -> None:
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
            if self.f_path.value.strip() and self._save_target() == path:
                self._on_save(event.client, confirmed=True)
            else:
                raise AposeError("the path in 'Assembly file' changed meanwhile; press Save again")

        yes.on_click(lambda e: self._guarded("Save")(lambda c: replace(e))(e))
        no.on_click(lambda e: modal.close())

    def _on_download(self, client) -> None:
        self._require_valid()
        folder = self._save_target().parent if self.f_path.value.strip() else authoring.folder_of(self.asm)
        text = dump_assembly(self.asm, folder)
        if client is None:
            raise AposeError("no browser to send the download to")
        client.send_file_download(f"{self.asm.name}.yaml", text.encode("utf-8"))

    def _on_name(self, client) -> None:
        if self._syncing:
            return
        from dataclasses import replace

        name = self.f_name.value.strip()
        if not name:
            raise AposeError("the assembly needs a name")
        self._set_assembly(replace(self.asm, name=name), client)

    def _on_units(self, client) -> None:
        if self._syncing or self.f_units.value == self.asm.units:
            return
        from dataclasses import replace

        for h in self.mesh_handles.values():
            h.remove()
        self.mesh_handles.clear()
        self._set_assembly(replace(self.asm, units=self.f_units.value), client)
        self._warn_units(client)

    def _add_mesh_file(self, path: Path, client) -> str:
        asm, pid = authoring.add_part(self.asm, path)
        model = self.model(pid, asm)  # raises MeshError before anything changes
        self._set_assembly(asm, client, quiet=True)
        if model.unit_warning:
            self.notify(client, "Units look wrong", model.unit_warning, error=True)
        return pid

    def _on_add_parts(self, client) -> None:
        text = self.f_mesh.value.strip()
        if not text:
            raise AposeError("type a mesh path or a folder of meshes (on the server) into 'Mesh path or folder'")
        path = self.workspace.resolve(text, "mesh")
        if path.is_dir():
            files = sorted(p for p in path.iterdir() if p.suffix.lower() in supported_extensions() and p.is_file())
            if not files:
                raise AposeError(f"{path}: no meshes here ({', '.join(supported_extensions())})")
        elif path.is_file():
            files = [path]
        else:
            raise AposeError(f"{path}: {describe_path(path, 'a mesh file or a folder of meshes')}")
        added, failed = [], []
        for f in files:
            try:
                added.append(self._add_mesh_file(f, client))
            except AposeError as e:
                failed.append(str(e))
        if added:
            self.notify(client, "Parts added", ", ".join(added))
        if failed:
            self.notify(client, "Some meshes were not added", "\n".join(failed[:5]), error=True)
        self._frame_camera_on_assembly()

    def _on_upload(self, client) -> None:
        f = self.upload.value
        if f is None:
            return
        if len(f.content) > MAX_UPLOAD_BYTES:
            raise AposeError(f"{f.name} is {len(f.content) / 2**20:.0f} MB; the limit is {MAX_UPLOAD_BYTES // 2**20} MB")
        name = Path(f.name).name
        if Path(name).suffix.lower() not in supported_extensions():
            raise AposeError(f"{name}: not a mesh format the studio reads ({', '.join(supported_extensions())})")
        folder = self.workspace.resolve(authoring.folder_of(self.asm) / "meshes", "assembly file")
        folder.mkdir(parents=True, exist_ok=True)
        target = folder / name
        k = 2
        while target.exists() and target.read_bytes() != f.content:
            target = folder / f"{Path(name).stem}_{k}{Path(name).suffix}"
            k += 1
        if not target.exists():
            tmp = target.with_name(f".{target.name}.part")
            tmp.write_bytes(f.content)
            tmp.replace(target)
        try:
            pid = self._add_mesh_file(target, client)
        except AposeError:
            target.unlink(missing_ok=True)  # a corrupt upload leaves nothing behind
            raise
        self.notify(client, "Part uploaded", f"{pid} ← {name} (saved as {target})")

    def _show_part_colour(self) -> None:
        """The Colour field shows the selected part's colour."""
        if self.f_part.value not in self.asm.parts:
            return
        rgb = tuple(int(round(255 * c)) for c in self.model(self.f_part.value).color)
        if tuple(self.f_color.value) != rgb:
            self._syncing = True
            try:
                self.f_color.value = rgb
            finally:
                self._syncing = False

    def _on_color(self, client) -> None:
        if self._syncing or self.f_part.value not in self.asm.parts:
            return
        pid = self.f_part.value
        rgb = tuple(c / 255.0 for c in self.f_color.value)
        if pid in self.mesh_handles:
            self.mesh_handles.pop(pid).remove()
        self._set_assembly(authoring.set_part_color(self.asm, pid, rgb), client)

    def _on_remove_part(self, client) -> None:
        pid = self.f_part.value
        if pid not in self.asm.parts:
            raise AposeError("choose a part to remove")
        asm = authoring.remove_part(self.asm, pid)
        if pid in self.mesh_handles:
            self.mesh_handles.pop(pid).remove()
        self._set_assembly(asm, client)

    # steps

    def _on_step_action(self, event) -> None:
        action = event.target.value
        self._guarded(f"{action} step")(lambda c: self._step_action(action, c))(event)

    def _step_action(self, action: str, client) -> None:
        i = self.step_index
        if action == "Add":
            asm = authoring.add_step(self.asm)
            self.step_index = len(asm.steps) - 1
        else:
            if i is None:
                raise AposeError("select a step first")
            if action == "Delete":
                asm = authoring.delete_step(self.asm, i)
                self.step_index = min(i, len(asm.steps) - 1) if asm.steps else None
            else:
                asm = authoring.move_step(self.asm, i, -1 if action == "Up" else 1)
                self.step_index = int(np.clip(i + (-1 if action == "Up" else 1), 0, len(asm.steps) - 1))
        self._set_assembly(asm, client)
        if self.step_index is not None:
            self.f_upto.value = self.step_index + 1

    def _on_select_step(self, client) -> None:
        if self._syncing or not self.asm.steps:
            return
        self.step_index = int(self.f_step.value.split(".")[0]) - 1
        self._refresh_assembly_widgets()
        self.f_upto.value = self.step_index + 1

    def _on_step_part(self, client) -> None:
        if self._syncing or self.step_index is None:
            return
        self._set_assembly(authoring.edit_step(self.asm, self.step_index, part=self.f_step_part.value), client)

    def _on_base(self, client) -> None:
        if self._syncing or self.step_index is None:
            return
        base = [b.strip() for b in self.f_base.value.split(",") if b.strip()]
        if not base:
            raise AposeError("a step needs at least one base part")
        self._set_assembly(authoring.edit_step(self.asm, self.step_index, base=base), client)

    def _on_typed_pose(self, client) -> None:
        if self._syncing or self.step_index is None:
            return
        T = authoring.pose_from_typed(self.f_t.value, self.f_r.value)
        self._set_pose(T, client, sync_fields=False)

    def _set_pose(self, T: np.ndarray, client, sync_fields: bool = True) -> None:
        self.asm = authoring.edit_step(self.asm, self.step_index, T_base_part=T)
        self.problems = authoring.problems(self.asm)
        if not [p for p in self.problems if p.key != "steps"]:
            self.valid_asm = self.asm
        if sync_fields:
            self._sync_typed_pose()
        self._refresh_status()
        self._refresh_assembly_scene(gizmo=sync_fields)  # mid-drag, the gizmo stays where the hand puts it

    def _on_gizmo(self, event) -> None:
        """A drag of the gizmo (viser's TransformControlsEvent: phase start / update / end, the pose in
        event.target). The part follows every update; the typed fields are rewritten at the end."""
        if self._syncing or self.step_index is None or not self.asm.steps:
            return
        g = event.target
        step = self.asm.steps[self.step_index]
        T_world_base = self._preview[step.base[0]]
        T = se3.inv(T_world_base) @ se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(g.wxyz)), np.asarray(g.position))
        T = authoring.snap_pose(T, float(self.f_snap_mm.value or 0), float(self.f_snap_deg.value or 0))
        self._set_pose(T, None, sync_fields=event.phase == "end")

    def _make_pose_fields(self, t, e) -> None:
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
        gui = self.server.gui
        orders = (self.f_t.order, self.f_r.order)
        self.f_t.remove()
        self.f_r.remove()
        with self.steps_folder:
            self.f_t = gui.add_vector3("Translation (mm)", t, step=0.1, order=orders[0])
            self.f_r = gui.add_vector3("Rotation xyz (°)", e, step=0.1, order=orders[1])
        self.f_t.on_update(self._guarded("Translation")(self._on_typed_pose))
        self.f_r.on_update(self._guarded("Rotation")(self._on_typed_pose))

    def _sync_typed_pose(self) -> None:
        if self.step_index is None:
            return
        self._make_pose_fields(*authoring.typed_pose(self.asm.steps[self.step_index].T_base_part))

    def _on_play_sequence(self, client) -> None:
        n = len(self.valid_asm.steps)
        if n == 0:
            raise AposeError("nothing to play: add steps first")

        def play():
            for k in range(n + 1):
                self.f_upto.value = k
                time.sleep(0.8)

        threading.Thread(target=play, daemon=True).start()

    # refreshers

    def _refresh_assembly_widgets(self) -> None:
        asm = self.asm
        self._syncing = True
        try:
            self.f_name.value = asm.name
            self.f_units.value = asm.units
            parts = list(asm.parts) or ["—"]
            self.f_part.options = parts
            self.f_step_part.options = parts
            steps = [f"{i + 1}. {s.part}" for i, s in enumerate(asm.steps)] or ["—"]
            self.f_step.options = steps
            if self.step_index is not None:
                s = asm.steps[self.step_index]
                self.f_step.value = steps[self.step_index]
                self.f_step_part.value = s.part
                self.f_base.value = ", ".join(s.base)
                self._make_pose_fields(*authoring.typed_pose(s.T_base_part))
            self.f_upto.max = max(len(asm.steps), 1)
        finally:
            self._syncing = False
        self._show_part_colour()
        self._refresh_parts_table()
        self._refresh_status()

    def _refresh_parts_table(self) -> None:
        rows = []
        for pid, part in self.asm.parts.items():
            try:
                m = self.model(pid)
            except AposeError as e:
                rows.append(f"<tr><td>{esc(pid)}</td><td colspan=4 style='color:#c00'>{esc(e)}</td></tr>")
                continue
            size = " × ".join(f"{v * 1000:.1f}" for v in m.size)
            warn = f"<br><span style='color:#c60'>⚠ {esc(m.unit_warning)}</span>" if m.unit_warning else ""
            rows.append(f"<tr><td><span style='display:inline-block;width:10px;height:10px;background:{_hex(m.color)};"
                        f"border-radius:2px'></span> {esc(pid)}</td><td>{esc(part.mesh.name)}</td><td>{esc(self.asm.units)}</td>"
                        f"<td>{size}{warn}</td></tr>")
        body = "".join(rows) or "<tr><td colspan=4><i>no parts yet: add a mesh path, a folder, or upload</i></td></tr>"
        self.parts_html.content = (
            "<table style='font-size:0.8em;width:100%;border-collapse:collapse'>"
            "<tr style='text-align:left'><th>part</th><th>file</th><th>unit</th><th>size (mm)</th></tr>" + body + "</table>")

    def _refresh_status(self) -> None:
        bad = authoring.problem_steps(self.problems)
        rows = []
        for i, s in enumerate(self.asm.steps):
            style = "background:#fde2e2;" if i in bad else ("background:#e3ecfc;" if i == self.step_index else "")
            mark = "⚠ " if i in bad else ("▶ " if i == self.step_index else "")
            t = s.T_base_part[:3, 3] * 1000
            rows.append(f"<tr style='{style}'><td>{mark}{i + 1}</td><td>{esc(s.part)}</td><td>{esc(', '.join(s.base))}</td>"
                        f"<td>({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f})</td></tr>")
        body = "".join(rows) or "<tr><td colspan=4><i>no steps yet: press Add</i></td></tr>"
        self.steps_html.content = (
            "<table style='font-size:0.8em;width:100%;border-collapse:collapse'>"
            "<tr style='text-align:left'><th>#</th><th>part</th><th>on base</th><th>t (mm)</th></tr>" + body + "</table>")
        if not self.problems:
            saved = f" Saved as {esc(self.saved_path)}." if self.saved_path else ""
            self.status_md.content = f"✅ **Valid**: {len(self.asm.parts)} parts, {len(self.asm.steps)} steps.{saved}"
        else:
            lines = "\n".join(f"- {esc(p.key or 'file')}: {esc(p.what)}" for p in self.problems[:6])
            self.status_md.content = f"⚠ **{len(self.problems)} problem(s)**; saving is off until fixed:\n{lines}"

    def _refresh_assembly_scene(self, gizmo: bool = True) -> None:
        """Meshes at their preview poses; the gizmo on the selected step's part."""
        asm = self.valid_asm
        diam = {}
        for p in asm.parts:
            try:
                diam[p] = self.model(p, asm).diameter
            except AposeError:
                pass
        upto = min(int(self.f_upto.value), len(asm.steps))
        explode = float(self.f_explode.value)
        centres = {p: self.model(p, asm).box_corners().mean(axis=0) for p in diam}
        self._preview = authoring.preview_poses(asm, upto, diam, explode, centres)
        show = self.current_view == "Assembly"
        for name in [n for n in self.nodes if n.startswith("/assembly/step_label")]:
            self.nodes.pop(name).remove()
        if explode > 0:  # the exploded view names each step at its part
            for i, st in enumerate(asm.steps[:upto]):
                if st.part in self._preview:
                    where = se3.transform_points(self._preview[st.part], centres[st.part][None])[0]
                    name = f"/assembly/step_label_{i}"
                    self._node(name, self.server.scene.add_label(name, f"{i + 1}. {st.part}", position=tuple(where),
                                                                 anchor="bottom-center", font_screen_scale=0.8))
        for pid in asm.parts:
            if pid not in diam:
                continue
            h = self.mesh_handles.get(pid)
            if h is None:
                m = self.model(pid, asm)
                color = tuple(int(255 * c) for c in m.color)
                h = self.server.scene.add_mesh_simple(f"/parts/{pid}", m.mesh.vertices.astype(np.float32),
                                                      m.mesh.faces.astype(np.uint32), color=color, flat_shading=False)
                self.mesh_handles[pid] = h
            T = self._preview.get(pid)
            h._apose_visible = T is not None
            h.visible = show and T is not None
            if T is not None:
                h.position, h.wxyz = _pos(T), _wxyz(T)
        for pid in [p for p in self.mesh_handles if p not in asm.parts]:
            self.mesh_handles.pop(pid).remove()
        if gizmo:
            self._place_gizmo()
        elif self.step_index is not None and self.step_index < len(asm.steps):  # the dragged part follows the hand
            step = asm.steps[self.step_index]
            if step.part in self.mesh_handles and step.base[0] in self._preview:
                T = self._preview[step.base[0]] @ self.asm.steps[self.step_index].T_base_part
                self.mesh_handles[step.part].position, self.mesh_handles[step.part].wxyz = _pos(T), _wxyz(T)

    def _preview_radius(self) -> float:
        ds = [self.model(p, self.valid_asm).diameter for p in self._preview if p in self.valid_asm.parts]
        return max(ds or [0.1]) / 2.0

    def _on_explode(self) -> None:
        self._refresh_assembly_scene()
        self._frame_camera_on_assembly()  # the whole assembly stays in view as it spreads out

    def _place_gizmo(self) -> None:
        asm = self.valid_asm
        i = self.step_index
        editable = (i is not None and i < len(asm.steps) and asm.steps[i].part == self.asm.steps[i].part
                    and float(self.f_explode.value) == 0.0 and asm.steps[i].base[0] in self._preview)
        if not editable:
            for name in ("/assembly/gizmo", "/assembly/base_frame"):
                if name in self.nodes:
                    self.nodes.pop(name).remove()
            return
        step = asm.steps[i]
        T_world_base = self._preview[step.base[0]]
        T = T_world_base @ step.T_base_part
        d = self.model(step.part, asm).diameter
        frame = self.nodes.get("/assembly/base_frame")
        if frame is None:
            frame = self._node("/assembly/base_frame", self.server.scene.add_frame(
                "/assembly/base_frame", axes_length=0.3 * d, axes_radius=0.01 * d))
        frame.position, frame.wxyz = _pos(T_world_base), _wxyz(T_world_base)
        g = self.nodes.get("/assembly/gizmo")
        if g is None:
            g = self._node("/assembly/gizmo", self.server.scene.add_transform_controls(
                "/assembly/gizmo", scale=max(0.6 * d, 0.25 * self._preview_radius()), depth_test=False))  # on top of the parts
            g.on_update(lambda e: self._guarded("Move part")(lambda c: self._on_gizmo(e))(e))
        self._syncing = True
        try:
            g.position, g.wxyz = _pos(T), _wxyz(T)
        finally:
            self._syncing = False
        if step.part in self.mesh_handles:  # the part shows where the draft puts it, even past the slider
            h = self.mesh_handles[step.part]
            h._apose_visible = True
            h.visible = self.current_view == "Assembly"
            h.position, h.wxyz = _pos(T), _wxyz(T)

    # -------------------------------------------------------------------------------- inspect side

    def _on_open_data(self, client) -> None:
        try:
            text = self.i_path.value.strip()
            if not text:
                raise AposeError("type a dataset folder (from `apose render`) or a capture folder into 'Dataset or capture'")
            self._open_frames(str(self.workspace.resolve(text, "dataset or capture")), client)
        except AposeError as e:
            if self.frames_path is not None:  # say what stays on screen
                raise AposeError(f"{e}\n(still showing the data opened before: {self.frames_path})") from None
            raise

    def _open_frames(self, text: str, client=None) -> None:
        from .dataset import Dataset, open_frames

        frames = open_frames(Path(text).expanduser())
        if isinstance(frames, Dataset):
            steps = [f"{s}. {frames.assembly.steps[s - 1].part}" for s in frames.steps]
        else:
            if not self.valid_asm.steps:
                raise AposeError("a capture needs an assembly: open one in the Assembly tab first")
            steps = [f"{i + 1}. {s.part}" for i, s in enumerate(self.valid_asm.steps)]
        self.frames, self.frames_path = frames, str(Path(text).expanduser().resolve())
        self.result = self.score = None
        self.i_path.value = self.frames_path
        self._syncing = True
        try:
            self.i_step.options = steps
            self.i_step.value = steps[0]
        finally:
            self._syncing = False
        self._show_view("Inspect")
        self._on_frame_changed()
        self._frame_camera_on_frame()

    def _look_at(self, centre: np.ndarray, radius: float, direction: np.ndarray) -> None:
        """Every tab's camera (and a new tab's) looking at a sphere from `direction`, the sphere filling
        most of the view."""
        direction = np.asarray(direction, float) / max(np.linalg.norm(direction), 1e-9)
        clients = list(self.server.get_clients().values())
        for c in clients + [None]:
            cam = c.camera if c is not None else self.server.initial_camera
            fov = float(getattr(cam, "fov", 0.0) or np.radians(50.0))
            eye = centre + direction * (radius / np.sin(fov / 2.0)) * 1.1
            cam.position, cam.look_at = tuple(float(v) for v in eye), tuple(float(v) for v in centre)

    def _frame_camera_on_frame(self) -> None:
        """Frame the object under inspection (its mask, else the estimate's points, else the middle of the
        depth image), seen from beside and above the dataset's camera so its frustum does not block the view."""
        fr = self.frame
        if fr is None:
            return
        from .registration import project_to_cloud

        mask = fr.base_mask()
        if not mask.any() and self.result is not None and len(self.result.target_cloud):
            pts = self.result.target_cloud
        else:
            if not mask.any():
                h, w = fr.depth.shape
                mask = np.zeros_like(mask)
                mask[h // 3: 2 * h // 3, w // 3: 2 * w // 3] = True
            pts = project_to_cloud(fr.depth, mask & np.isfinite(fr.depth) & (fr.depth > 0), fr.camera, fr.T_world_camera)
        if not len(pts):
            return
        centre = np.median(pts, axis=0)
        radius = max(float(np.percentile(np.linalg.norm(pts - centre, axis=1), 95)), 0.02)
        to_camera = fr.T_world_camera[:3, 3] - centre
        direction = se3.axis_angle_matrix([0.0, 0.0, 1.0], np.radians(35.0)) @ to_camera
        direction[2] = max(direction[2], 0.6 * np.linalg.norm(direction[:2]))  # from above the table
        self._look_at(centre, 1.3 * radius, direction)

    def _inspect_assembly(self) -> Assembly:
        from .dataset import Dataset

        return self.frames.assembly if isinstance(self.frames, Dataset) else self.valid_asm

    def _current_step(self) -> int:
        return int(str(self.i_step.value).split(".")[0])

    def _job(self, step: int, ids: list[int]) -> "EstimateJob":
        """Everything an estimate depends on, read from the widgets now: a later click in any tab (another
        dataset, another preset) cannot change what a running estimate is computed with or cached under."""
        crop = None
        if self.i_mask.value == "depth" and self.i_crop.value and "/inspect/crop" in self.nodes:  # the box is part of the mask
            g = self.nodes["/inspect/crop"]
            crop = (se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(g.wxyz)), np.asarray(g.position)),
                    np.asarray(self.i_crop_size.value, dtype=float) / 1000.0)
        asm = self._inspect_assembly()
        return EstimateJob(self.frames, self.frames_path, asm, self._inspect_models(), step, tuple(ids),
                           self.i_preset.value, bool(self.i_upright.value), self.i_mask.value, bool(self.i_prior.value),
                           crop)

    def _cache_key(self, step: int, im_id: int) -> tuple:
        return self._job(step, [im_id]).key(self.cache, im_id)

    def _load_frame(self, step: int, im_id: int, frames=None, asm: Assembly | None = None):
        from .dataset import Dataset

        frames = self.frames if frames is None else frames
        if isinstance(frames, Dataset):
            return frames.frame(step, im_id)
        frames.base = (asm or self.valid_asm).steps[step - 1].base
        return frames

    def _on_frame_changed(self) -> None:
        from .dataset import Dataset

        if self._syncing or self.frames is None:
            return
        step = self._current_step()
        if isinstance(self.frames, Dataset):
            ids = self.frames.image_ids(step)
            self._syncing = True
            try:
                self.i_frame.max = max(len(ids) - 1, 1)
                self.i_frame.disabled = len(ids) <= 1
                if self.i_frame.value > len(ids) - 1:
                    self.i_frame.value = 0
            finally:
                self._syncing = False
            im_id = ids[int(self.i_frame.value)]
        else:
            im_id = 0
        self.frame = self._load_frame(step, im_id)
        cached = self.cache.get(self._cache_key(step, im_id))
        self.result, self.score = cached if cached is not None else (None, None)
        self._draw_frame()

    def _inspect_models(self) -> dict:
        from .mesh import load_parts

        asm = self._inspect_assembly()
        if id(asm) not in self._part_models:
            self._part_models = {id(asm): load_parts(asm)}  # keep one assembly's meshes, not every draft's
        return self._part_models[id(asm)]

    def _context(self, step: int):
        from .evaluate import StepContext

        asm = self._inspect_assembly()
        key = (id(asm), step)
        if key not in self.contexts:
            self.contexts[key] = StepContext(asm, self._inspect_models(), step)
        return self.contexts[key]

    def _estimate(self, job: "EstimateJob", im_id: int):
        """Estimate one frame of `job` and cache it under the job's key (runs without the studio lock)."""
        from .evaluate import StepContext, estimate_and_score
        from .registration import resolve_params

        ctx = StepContext(job.assembly, job.models, job.step)
        frame = self._load_frame(job.step, im_id, job.frames, job.assembly)
        extra = {"upright": job.upright} if job.preset == "default" else {}
        params = resolve_params(job.preset, job.assembly.registration, **extra)
        mask = None
        if job.crop is not None:
            from .segment import depth_mask

            keep = inspection.pixels_in_box(frame.depth, frame.camera, frame.T_world_camera, *job.crop)
            mask = depth_mask(frame.depth, frame.camera, keep=keep)
        result, score = estimate_and_score(frame, ctx, params, job.mask, job.prior, trace_iterations=True, mask=mask)
        self.cache.put(job.key(self.cache, im_id), (result, score))
        return result, score

    def _show_crop(self) -> None:
        """The crop box: a gizmo with a wireframe box as its child, first placed on the base object's
        likely spot (the depth point at the image centre)."""
        for name in ("/inspect/crop/box",):
            if name in self.nodes:
                self.nodes.pop(name).remove()
        if not self.i_crop.value or self.frame is None:
            if "/inspect/crop" in self.nodes:
                self.nodes.pop("/inspect/crop").remove()
            return
        size = np.asarray(self.i_crop_size.value, dtype=float) / 1000.0
        g = self.nodes.get("/inspect/crop")
        if g is None:
            fr = self.frame
            h, w = fr.depth.shape
            win = fr.depth[h // 2 - 20:h // 2 + 20, w // 2 - 20:w // 2 + 20]
            z = float(np.median(win[np.isfinite(win) & (win > 0)])) if (np.isfinite(win) & (win > 0)).any() else 0.5
            centre = se3.transform_points(fr.T_world_camera, np.array([[0.0, 0.0, z]]))[0]
            g = self._node("/inspect/crop", self.server.scene.add_transform_controls(
                "/inspect/crop", scale=float(size.max()), position=tuple(centre)))
        import trimesh

        box = trimesh.creation.box(size)
        self._node("/inspect/crop/box", self.server.scene.add_mesh_simple(
            "/inspect/crop/box", box.vertices.astype(np.float32), box.faces.astype(np.uint32), color=(255, 170, 0),
            wireframe=True))

    def _on_use_model(self, client) -> None:
        from .evaluate import check_mask_source

        text = self.i_model.value.strip()
        if not text:
            raise AposeError("type the path of a model file (.pt) from `apose train-seg` into 'Mask model (.pt)'")
        path = check_mask_source(str(self.workspace.resolve(text, "mask model")), self._inspect_assembly())
        options = list(self.i_mask.options)
        if path not in options:
            self.i_mask.options = options + [path]
        self.i_mask.value = path
        self.notify(client, "Mask model", f"using {Path(path).name} for masks")

    def _on_estimate(self, event) -> None:
        which = event.target.value
        self._guarded(which)(lambda c: self._run_estimation(which == "Estimate step", c))(event)

    def _run_estimation(self, whole_step: bool, client) -> None:
        from .dataset import Dataset

        if self.frames is None:
            raise AposeError("open a dataset or capture first")
        if not self.busy.acquire(blocking=False):
            raise AposeError("an estimation is already running; wait for it to finish")
        try:
            step = self._current_step()
            if whole_step and isinstance(self.frames, Dataset):
                ids = self.frames.image_ids(step)
            else:
                ids = [self.frame.im_id]
            job = self._job(step, ids)  # the settings of this moment, whatever other tabs do meanwhile
        except BaseException:
            self.busy.release()
            raise
        self.lock.release()  # estimation is long: let other tabs edit meanwhile
        try:
            self.i_progress.visible = True
            self.i_progress.value = 0.0
            failed, unsure, t0 = [], [], time.perf_counter()
            for k, im_id in enumerate(ids):
                cached = self.cache.get(job.key(self.cache, im_id))
                result = cached[0] if cached is not None else self._estimate(job, im_id)[0]
                if not result.ok:
                    failed.append(f"frame {im_id}: {result.reason}")
                elif not result.confident:
                    unsure.append(f"frame {im_id}: coverage {result.coverage:.0%}")
                self.i_progress.value = 100.0 * (k + 1) / len(ids)
            dt = time.perf_counter() - t0
        finally:
            self.lock.acquire()
            self.busy.release()
            self.i_progress.visible = False
        self._on_frame_changed()
        self._frame_camera_on_frame()
        if failed:
            self.notify(client, "Estimation failed", esc("\n".join(failed[:5])), error=True)
        elif unsure:
            self.notify(client, "Estimated, low confidence", "the model explains too little of the target (likely "
                        "wrong): " + esc("; ".join(unsure[:5])), error=True)
        else:
            self.notify(client, "Estimated", f"{len(ids)} frame(s) in {dt:.1f} s")

    def _draw_frame(self) -> None:
        """The frame and its estimate in the 3D view (each thing in its legend colour, labelled) and the
        RGB overlay in the panel."""
        fr = self.frame
        scene = self.server.scene
        cam = fr.camera
        asm = self._inspect_assembly()
        part_model = self._inspect_models()[asm.steps[self._current_step() - 1].part]
        small = fr.rgb[::2, ::2] if fr.rgb.shape[1] > 400 else fr.rgb
        fov = 2.0 * np.arctan2(cam.height / 2.0, cam.fy)
        Tc = fr.T_world_camera
        self._node("/inspect/camera", scene.add_camera_frustum("/inspect/camera", fov=float(fov), aspect=cam.width / cam.height,
                                                               scale=0.03, image=small, format="jpeg", jpeg_quality=80,
                                                               wxyz=_wxyz(Tc), position=_pos(Tc), color=(60, 60, 60)))
        pts, cols = inspection.scene_cloud(fr.depth, fr.rgb, cam, Tc)
        stride = max(1, int(np.ceil(np.sqrt(fr.depth.size / 60000))))
        # about one pixel's footprint at the scene's depth: dense, but never blobs that hide the boxes
        footprint = 0.5 * float(np.median(se3.transform_points(se3.inv(Tc), pts)[:, 2])) / cam.fx * stride if len(pts) else 0.001
        self._node("/inspect/scene", scene.add_point_cloud("/inspect/scene", pts, cols, point_size=footprint,
                                                           point_shape="circle"))
        for name in [n for n in self.nodes if n.startswith(("/inspect/box_", "/inspect/label_", "/inspect/ghost"))] + [
                "/inspect/target", "/inspect/source"]:
            if name in self.nodes:
                self.nodes.pop(name).remove()
        r = self.result
        corners = part_model.box_corners()
        d = part_model.diameter
        labels = []
        if fr.T_world_part is not None:  # truth: amber, dashed, a little outside so it never z-fights the estimate
            seg = inspection.dashed(inspection.box_segments(inspection.inflate(corners, 0.03), fr.T_world_part))
            self._node("/inspect/box_gt", scene.add_line_segments("/inspect/box_gt", seg.astype(np.float32), inspection.AMBER,
                                                                  thickness=4.0, thickness_units="screen"))
            labels.append(("truth", se3.transform_points(fr.T_world_part, corners).min(axis=0), "top-right"))
        if r is not None and r.ok:
            seg = inspection.box_segments(corners, r.T_world_part)
            self._node("/inspect/box_est", scene.add_line_segments("/inspect/box_est", seg.astype(np.float32), inspection.GREEN,
                                                                   thickness=3.0, thickness_units="screen"))
            labels.append(("estimate", se3.transform_points(r.T_world_part, corners).max(axis=0), "bottom-left"))
            alts = [c.T_world_part for c in r.alternatives]
            if alts:
                seg = np.concatenate([inspection.box_segments(corners, T) for T in alts])
                self._node("/inspect/box_alt", scene.add_line_segments("/inspect/box_alt", seg.astype(np.float32),
                                                                       inspection.MAGENTA, thickness=2.0, thickness_units="screen"))
                labels.append(("alternative", se3.transform_points(alts[0], corners).max(axis=0), "bottom-left"))
            mesh = part_model.mesh
            self._node("/inspect/ghost", scene.add_mesh_simple(
                "/inspect/ghost", mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32), color=inspection.GREEN,
                opacity=0.45, wxyz=_wxyz(r.T_world_part), position=_pos(r.T_world_part)))
        if r is not None and len(r.target_cloud):
            tgt = inspection.thin(r.target_cloud, 20000).astype(np.float32)
            self._node("/inspect/target", scene.add_point_cloud("/inspect/target", tgt, inspection.RED, point_size=d / 120,
                                                                point_shape="circle"))
            labels.append(("target cloud", tgt[np.argmax(tgt[:, 2])], "bottom-right"))
        for k, (text, where, anchor) in enumerate(labels):
            name = f"/inspect/label_{k}"
            self._node(name, scene.add_label(name, text, position=tuple(float(v) for v in where), anchor=anchor,
                                             font_screen_scale=0.8))
        self.stages = inspection.replay(r) if (r is not None and r.ok) else []
        self._syncing = True
        try:
            self.i_stage.max = max(len(self.stages) - 1, 1)
            self.i_stage.value = max(len(self.stages) - 1, 0)
            self.i_stage.disabled = len(self.stages) < 2
        finally:
            self._syncing = False
        self._show_stage()
        self.i_metrics.content = inspection.metrics_markdown(self.score, r)
        self.i_pose.content = inspection.pose_markdown(inspection.pose_report(r, Tc)) if (r is not None and r.ok) else ""
        self._draw_overlay()
        self._apply_layers()

    def _draw_overlay(self) -> None:
        """The RGB image with the boxes drawn, cropped around the object unless 'Full image' is ticked."""
        fr, r = self.frame, self.result
        if fr is None:
            return
        asm = self._inspect_assembly()
        corners = self._inspect_models()[asm.steps[self._current_step() - 1].part].box_corners()
        boxes = []  # earlier boxes are drawn thicker: truth under estimate
        if fr.T_world_part is not None:
            boxes.append((fr.T_world_part, inspection.AMBER))
        if r is not None and r.ok:
            boxes.append((r.T_world_part, inspection.GREEN))
            boxes += [(c.T_world_part, inspection.MAGENTA) for c in r.alternatives]
        image = inspection.draw_boxes(fr.rgb, fr.camera, fr.T_world_camera, corners, boxes)
        if not self.i_full.value:
            uv = np.concatenate([inspection.project_points(se3.transform_points(T, corners), fr.T_world_camera, fr.camera)[0]
                                 for T, _ in boxes]) if boxes else np.zeros((0, 2))
            if not boxes:  # no boxes: around the base object, if its mask is known
                vs, us = np.nonzero(fr.base_mask())
                uv = np.stack([us, vs], axis=1)[:: max(1, len(us) // 500)]
            x0, y0, x1, y1 = inspection.crop_window(fr.rgb.shape[:2], uv)
            image = image[y0:y1, x0:x1]
        self.i_image.image = image
        truth = ", truth (amber)" if fr.T_world_part is not None else ""
        self.i_image.label = f"RGB: estimate (green){truth}" if boxes else "RGB"

    def _on_download_pose(self, client) -> None:
        import json

        r = self.result
        if r is None or not r.ok or self.frame is None:
            raise AposeError("no estimate on this frame yet: press Estimate frame first")
        report = inspection.pose_report(r, self.frame.T_world_camera)
        report.update({"source": self.frames_path, "step": self._current_step(), "frame": int(self.frame.im_id),
                       "units": "metres (matrices), mm (translation_mm)"})
        if client is None:
            raise AposeError("no browser to send the download to")
        client.send_file_download(f"pose_step{self._current_step()}_frame{self.frame.im_id}.json",
                                  json.dumps(report, indent=1).encode("utf-8"))

    def _show_stage(self) -> None:
        if self._syncing:
            return
        if not self.stages:
            self.i_stage_md.content = "" if self.result is None else "_no registration trace (estimation failed)_"
            return
        k = int(np.clip(self.i_stage.value, 0, len(self.stages) - 1))
        s = self.stages[k]
        d = self._inspect_models()[self._inspect_assembly().steps[self._current_step() - 1].part].diameter
        self._node("/inspect/source", self.server.scene.add_point_cloud(
            "/inspect/source", s.source_world, inspection.BLUE, point_size=d / 120, point_shape="circle"),
            visible=bool(self.layers["source cloud"].value))
        self.i_stage_md.content = (f"**{s.name}** ({k + 1}/{len(self.stages)}): fitness {s.fitness:.3f}, "
                                   f"inlier RMSE {s.inlier_rmse * 1000:.2f} mm")

    def _on_play_registration(self, client) -> None:
        if len(self.stages) < 2:
            raise AposeError("estimate this frame first; then the registration can be replayed")
        n = len(self.stages)

        def play():
            for k in range(n):
                self.i_stage.value = k
                time.sleep(max(0.08, 2.5 / n))

        threading.Thread(target=play, daemon=True).start()

    def _apply_layers(self) -> None:
        which = {"/inspect/scene": "scene cloud", "/inspect/target": "target cloud", "/inspect/source": "source cloud",
                 "/inspect/box_gt": "boxes", "/inspect/box_est": "boxes", "/inspect/box_alt": "boxes",
                 "/inspect/ghost": "part at estimate", "/inspect/camera": "camera"}
        which.update({n: "labels" for n in self.nodes if n.startswith("/inspect/label_")})
        for name, layer in which.items():
            if name in self.nodes:
                h = self.nodes[name]
                h._apose_visible = bool(self.layers[layer].value)
                h.visible = h._apose_visible and self.current_view == "Inspect"


@dataclass(frozen=True)
class EstimateJob:
    """What one press of Estimate computes, fixed when it is pressed (see Studio._job)."""

    frames: object  # a Dataset or a capture Frame
    frames_path: str
    assembly: Assembly
    models: dict
    step: int
    ids: tuple[int, ...]
    preset: str
    upright: bool
    mask: str
    prior: bool
    crop: tuple | None  # (T_world_box, size in metres) for depth masks, or None

    def key(self, cache: inspection.ResultCache, im_id: int) -> tuple:
        mask = self.mask
        if self.crop is not None:
            mask = (mask, tuple(np.round(self.crop[0], 4).ravel()), tuple(np.round(self.crop[1], 4)))
        preset = self.preset + (" free" if not self.upright and self.preset == "default" else "")
        return cache.key(self.frames_path, self.step, im_id, preset, mask, self.prior)


def default_workspace(assembly=None, dataset=None, root=None) -> Workspace:
    """The folders the page may name: `root` if given, else the current directory, or the assembly
    file's folder when the file lies outside it; a dataset given at start is always readable."""
    if root is None:
        cwd = Path.cwd().resolve()
        folder = Path(assembly).expanduser().resolve().parent if assembly is not None else cwd
        root = cwd if folder.is_relative_to(cwd) else folder
    return Workspace.of(root, dataset)


def serve(assembly=None, dataset=None, host: str = "127.0.0.1", port: int = 8080, cache=None, root=None,
          token: str | None = None):
    """Start the studio in the background; returns (server, studio). `server.stop()` ends it.

    Only the studio's own page may connect (Origin check). Bound beyond loopback, the page and its
    websocket need `token` (made up when None); `studio.url` is the address to open."""
    from .webguard import is_loopback_bind, new_token, start_viser, studio_url

    if not 0 < int(port) < 65536:
        raise AposeError(f"--port {port}: expected a port number from 1 to 65535")
    if token is None and not is_loopback_bind(host):
        token = new_token()
    server = start_viser(host, port, token)
    try:
        studio = Studio(server, assembly, dataset, cache, default_workspace(assembly, dataset, root))
    except BaseException:
        server.stop()
        raise
    studio.url = studio_url(host, server.get_port(), token)
    return server, studio
