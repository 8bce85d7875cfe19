"""The studio app: one tab's studio on a viser server (its selection, inspected frame and 3D view, over the
draft every tab shares: desk.py) and the event hub its panels talk through, the guarded door every
callback goes through, notifications, the 3D view's two scenes, and `serve()`.

Design: the GUI is an edge. Each folder of controls belongs to a panel class in its own module
(assembly_panel, steps_panel, mates_panel, inspect_panel, prompt_panel, views_panel, results_view)
that owns its widgets with their callbacks beside them; editing goes through `authoring` (pure,
returns new Assemblies), drawing through `inspection` (pure). Every callback runs through
`Studio.guarded`, so bad input becomes a notification to the browser that caused it and the server
keeps serving. `serve()` gives each browser tab a studio of its own on the tab's GUI and scene, over one
`Desk` (the draft, its history, the models, the cache, the lock); notifications go to the tab that acted.

Panels talk through the app, never to each other: what one panel writes and others read is in
`Studio.state` (`state.StudioState`), and what others must react to is an `Event` on `Studio.events`
that they subscribe to (in their constructors, so in the order the panels are made below). A panel
reads and calls the app (`self.app.state`, `self.app.events`, `self.app.model(...)`, ...), never
another panel's attributes or widgets (tests/studio/test_panel_boundaries.py checks it). A new panel
arrives as a new module, one line in `__init__` and one in `build_gui`.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from functools import wraps
from pathlib import Path

import numpy as np

from apose_studio.assembly.mesh import PartModel
from apose_studio.assembly.model import Assembly
from apose_studio.errors import AposeError, AssemblyError, os_error_text
from apose_studio.geometry import se3
from apose_studio.safeio import reads_within
from apose_studio.studio import authoring, inspection
from apose_studio.studio.assembly_panel import AssemblyPanel
from apose_studio.studio.desk import Desk
from apose_studio.studio.grasps_panel import GraspsPanel
from apose_studio.studio.inspect_panel import EstimateJob, InspectPanel
from apose_studio.studio.mates_panel import MatesPanel
from apose_studio.studio.prompt_panel import PromptPanel
from apose_studio.studio.results_view import ResultsView
from apose_studio.studio.robot_panel import RobotPanel
from apose_studio.studio.sequence_panel import SequencePanel
from apose_studio.studio.state import Event, Events, StudioState, shared
from apose_studio.studio.steps_panel import StepsPanel
from apose_studio.studio.views_panel import ViewsPanel
from apose_studio.studio.viser_adapter import limit_uploads, screen_messages
from apose_studio.studio.webguard import Workspace, check_token, new_token, start_viser, studio_url
from apose_studio.studio.widgets import ACTIVE, MAX_UPLOAD_BYTES, VIEWS, send_download
from apose_studio.text import shorten_values

log = logging.getLogger(__name__)
RENDER_TIMEOUT_S = 30.0  # for a page's image of its 3D view (software WebGL takes ~1 s)


class Studio:
    """One studio on one viser server. `assembly` and `dataset` are optional paths opened at start;
    `workspace` holds the folders whose files the page may name (default: see `default_workspace`).

    Panels (each owns its folders; only the app calls them): `files` (File, Parts), `steps` (Steps,
    Preview), `mates` (Mates, Approach), `grasps` (Grasps), `inspect` (Data, Estimate), `prompt` (Prompt), `views` (Views),
    `results` (replay, Result, Layers), `robot` (Robot), `sequence` (Sequence). Shared: `state` (the data) and `events` (the hub)."""

    files: AssemblyPanel
    steps: StepsPanel
    mates: MatesPanel
    grasps: GraspsPanel
    inspect: InspectPanel
    prompt: PromptPanel
    views: ViewsPanel
    robot: RobotPanel
    sequence: SequencePanel
    results: ResultsView
    state: StudioState
    events: Events

    def __init__(self, server, assembly: str | Path | None = None, dataset: str | Path | None = None,
                 cache: inspection.ResultCache | None = None, workspace: Workspace | None = None,
                 obj_map: list[str] | None = None, *, desk: Desk | None = None, tab=None):
        import viser  # noqa: F401  (imported here so the core never needs it)

        self.server = server
        self.tab = tab  # the tab this studio is drawn in (its own GUI and scene), or None: the server's, shared
        self.ui = tab if tab is not None else server  # where the widgets and the 3D scene go
        self.desk = desk if desk is not None else Desk(
            server, workspace if workspace is not None else default_workspace(assembly, dataset), cache)
        self.state = StudioState.empty(self.desk.draft)
        self.seen_asm = self.state.asm  # the draft as this tab last drew it (Desk.spread)
        self.events = Events(tap=lambda event, payload: self.desk.record(self, event, payload))
        self.nodes: dict[str, object] = {}  # scene nodes by name (tests look here)
        self._errors_shown: dict[int, list] = {}  # client id -> its error notifications still on screen
        self._error_titles: dict[int, str] = {}  # id() of such a notification -> the action that raised it
        self.current_view = "Assembly"
        self._notice_timer: threading.Timer | None = None
        self._last_notice = ""
        self.files = AssemblyPanel(self)
        self.steps = StepsPanel(self)
        self.mates = MatesPanel(self)
        self.grasps = GraspsPanel(self)
        self.inspect = InspectPanel(self)
        self.sequence = SequencePanel(self)
        self.prompt = PromptPanel(self)
        self.views = ViewsPanel(self)  # before results: a frame change refreshes the views, then draws
        self.results = ResultsView(self)
        self.robot = RobotPanel(self)  # after results: its targets are listed once the view is drawn
        with self.lock:  # a page that connects while the start-up files load waits for them
            if tab is None:  # one studio on the server's GUI: it guards the server itself
                screen_messages(server, lambda *a, **k: self.notify(*a, **k))  # before any page's message is handled
            self.build_gui(inspect_first=dataset is not None)
            if tab is None:
                server.on_client_connect(self.on_connect)
            limit_uploads(self.ui.gui, self.desk.upload_states, MAX_UPLOAD_BYTES,
                          lambda cid, *a, **k: self.notify(self._client(cid), *a, **k))
            if tab is not None:
                self.show_draft()
            elif assembly is not None:  # named on the command line: the user's own files, not the page's
                self.files.open_assembly(Path(assembly), confine=False)
                self.workspace = self.workspace.trusting(*(p.mesh.parent for p in self.asm.parts.values()))
            if obj_map:  # a BOP scene's obj_ids (`apose studio --obj-map`), read when it opens
                self.inspect.i_obj_map.value = ", ".join(obj_map)
            if dataset is not None:
                self.inspect.open_frames(str(dataset), confine=False)
                frames = self.inspect.frames
                if getattr(frames, "assembly", None) is not None:
                    self.workspace = self.workspace.trusting(*(p.mesh.parent for p in frames.assembly.parts.values()))

    lock = property(lambda self: self.desk.lock, doc="one edit at a time, whichever tab it comes from (the desk's)")
    busy = property(lambda self: self.desk.busy, doc="one estimation at a time (the desk's)")
    history = property(lambda self: self.desk.history, doc="the draft's undo history (the desk's)")
    models = property(lambda self: self.desk.models, doc="loaded PartModels (the desk's)")
    cache = property(lambda self: self.desk.cache, doc="estimates by frame and settings (the desk's)")
    workspace = property(lambda self: self.desk.workspace, lambda self, w: setattr(self.desk, "workspace", w),
                         doc="the folders the page may name (the desk's)")

    asm = shared("asm", "the draft (`state.asm`)")
    valid_asm = shared("valid_asm", "the last draft without problems, what the preview shows (`state.valid_asm`)")
    problems = shared("problems", "the draft's problems (`state.problems`)")

    def notify(self, client, title: str, body: str, error: bool = False, others_of=None, keep: bool = False) -> None:
        """Tell the tab that acted (or every tab when no one did). An error stays until closed, but only until
        the tab's next message: an old error beside a newer success reads as if the success had failed.
        `others_of`: tell every tab but that one (what another tab's action changed here), in yellow, kept
        as an error is. `keep`: a success kept the same way (a result to read, such as a step's summary). A long value
        in `body` (a field's text quoted back: the page may send a megabyte) is shortened, as the CLI's messages are."""
        body = shorten_values(body)
        (log.warning if error else log.info)("%s: %s", title, body)
        if others_of is not None:
            if self.tab is not None:  # the other tabs have studios of their own
                for other in list(self.desk.views.values()):
                    if other is not self:
                        other.show_notice(other.pages(), title, body, error, True, "yellow")
                return
            clients = [c for c in self.pages() if c.client_id != others_of.client_id]
        else:
            clients = [client] if client is not None else self.pages()
        self.show_notice(clients, title, body, error, error or keep or others_of is not None,
                         "red" if error else "yellow" if others_of is not None else "green")

    def pages(self) -> list:
        """The tabs this studio is drawn in: its own, or (on the server's GUI) every connected one."""
        return [self.tab] if self.tab is not None else list(self.server.get_clients().values())

    def _client(self, client_id):
        return self.server.get_clients().get(client_id)

    def show_notice(self, clients, title: str, body: str, error: bool, lasting: bool, colour: str) -> None:
        for c in clients:
            try:
                for old in self._errors_shown.pop(c.client_id, []):
                    self._error_titles.pop(id(old), None)
                    old.remove()
                handle = c.add_notification(title, body, auto_close_seconds=None if lasting else 4.0, color=colour)
                if lasting:
                    self._errors_shown.setdefault(c.client_id, []).append(handle)
                    if error:
                        self._error_titles[id(handle)] = title
            except Exception:  # a tab that just closed
                pass

    def guarded(self, title: str):
        """Decorator for callbacks: AposeError -> its message; anything else -> a short report. Never raises."""
        def wrap(fn):
            @wraps(fn)
            def run(event=None):
                client = getattr(event, "client", None)
                cid = getattr(client, "client_id", None)
                if cid is not None and not self._admit(cid, client, title):
                    return
                try:
                    with self.lock, reads_within(self.workspace.readable):  # no page action reads outside it
                        if cid is not None and cid not in self.server.get_clients():
                            return  # the tab closed while this waited: nobody is asking any more
                        before = list(self._errors_shown.get(cid, [])) if cid is not None else []
                        try:
                            fn(client)
                        finally:
                            self.desk.spread(self)  # the other tabs draw the draft as this action left it
                        self.close_errors_of(client, title, before)
                except AssemblyError as e:
                    lines = [str(p) for p in e.problems[:6]]
                    more = f"\n(+{len(e.problems) - 6} more)" if len(e.problems) > 6 else ""
                    self.notify(client, title, "\n".join(lines) + more, error=True)
                except AposeError as e:
                    self.notify(client, title, str(e), error=True)
                except OSError as e:  # the system refused (a read-only folder, a full disk): what and what to do
                    also = " (or Download the file)" if title == "Save" else ""
                    self.notify(client, title, os_error_text(e) + also, error=True)
                except Exception as e:  # a bug: say so, keep serving
                    log.error("%s failed:\n%s", title, traceback.format_exc())
                    self.notify(client, title, f"internal error ({type(e).__name__}: {e}); the server log has details",
                                error=True)
                finally:
                    if cid is not None:
                        with self.desk.pending_lock:
                            if cid in self.desk.pending:
                                self.desk.pending[cid] -= 1
            return run
        return wrap

    def _admit(self, cid: int, client, title: str) -> bool:
        """One tab may have MAX_PENDING_PER_TAB actions waiting for (or holding) the studio at once; a press
        beyond that is dropped and the tab told (at most once a second). 300 presses of *Add part(s)* on a
        folder in 0.3 s once kept every other tab waiting for two minutes."""
        desk = self.desk
        with desk.pending_lock:
            n, everyone = desk.pending.get(cid, 0), sum(desk.pending.values())
            if n < MAX_PENDING_PER_TAB and everyone < MAX_PENDING_ALL:  # many tabs of one flooder count too
                desk.pending[cid] = n + 1
                return True
            now, told = time.monotonic(), desk.dropped_told.get(cid, 0.0)
            if now - told < 1.0:
                return False
            desk.dropped_told[cid] = now
        log.info("tab %s: %s dropped, %d actions of it still waiting", cid, title, n)
        waiting = f"{n} of your earlier actions are" if n >= MAX_PENDING_PER_TAB else f"{everyone} actions of all tabs are"
        self.notify(client, title, f"not done: {waiting} still waiting; press again once they have finished", error=True)
        return False

    def on_connect(self, client) -> None:
        try:
            client.camera.up_direction = (0.0, 0.0, 1.0)
        except Exception as e:  # one tab's camera never stops the others' (nor this tab's clicks)
            log.info("tab %s: camera not turned upright (%s)", client.client_id, e)
        self.mates.listen(client)

    def build_gui(self, inspect_first: bool = False) -> None:
        gui = self.ui.gui
        gui.configure_theme(control_layout="fixed", control_width="large", show_share_button=False,
                            brand_color=(40, 90, 230))
        self.ui.scene.set_up_direction("+z")
        # plain lights: no shadows and no environment map. Drawn without a GPU (software WebGL, as in VMs and remote
        # desktops) a frame of the inspect view took ~1 s with viser's defaults, ~0.7 s without the environment map,
        # ~0.25 s without shadows too; and while the browser draws, the page answers no click (benchmarks/
        # studio_browser.py). A sky/ground light stands in for the map, so that the sides of a part are not black.
        self.ui.scene.configure_default_lights(True, cast_shadow=False)
        self.ui.scene.configure_environment_map(hdri=None)
        self.ui.scene.add_light_hemisphere("/lights/sky", sky_color=(255, 255, 255), ground_color=(110, 110, 120),
                                               intensity=1.2, position=(0.0, 0.0, 1.0))
        self.view = gui.add_button_group("3D view", VIEWS)
        self.view.on_click(lambda e: self.guarded("3D view")(lambda c: self.on_view_button(e.target.value))(e))
        b = gui.add_button("Download image (PNG)", hint="the 3D view as this tab shows it, as a PNG file (for reports)")
        b.on_click(self.guarded("Download image")(self.on_download_image))
        tabs = self.tabs = gui.add_tab_group()

        def assembly_tab() -> None:
            with tabs.add_tab("Assembly"):
                self.edit_row = gui.add_button_group("Edit", ("Undo", "Redo"))
                self.edit_row.on_click(lambda e: self.guarded(e.target.value)(lambda c: self.undo_redo(e.target.value, c))(e))
                for label, modifier in (("Undo", "cmd/ctrl"), ("Redo", "cmd/ctrl+shift")):
                    cmd = gui.add_command(label, description=f"{label} the last authoring edit", hotkey="Z", modifier=modifier)
                    cmd.on_trigger(lambda e, label=label: self.guarded(label)(lambda c: self.undo_redo(label, c))(e))
                self.files.build()
                self.steps.build()
                self.mates.build()
                self.grasps.build()

        def inspect_tab() -> None:
            with tabs.add_tab("Inspect"):
                self.inspect.build()
                self.sequence.build()
                self.prompt.build()
                self.views.build()
                self.results.build()
                self.robot.build()

        # a page opens on the first tab (viser 1.1.1 cannot select one from the server): started with data to
        # inspect (`--dataset`), the Inspect tab comes first, beside the Inspect view it opens on
        for build in ((inspect_tab, assembly_tab) if inspect_first else (assembly_tab, inspect_tab)):
            build()
        self.ui.scene.add_grid("/grid", width=1.0, height=1.0, cell_size=0.01, section_size=0.1,
                                   plane="xy", position=(0.0, 0.0, -0.0005))
        self.show_view("Assembly")

    def on_view_button(self, label: str) -> None:
        which = label.removeprefix(ACTIVE)
        self.show_view(which)
        if which == "Inspect":
            self.inspect.frame_camera_on_frame()
        else:
            self.frame_camera_on_assembly()

    def show_view(self, which: str) -> None:
        self.current_view = which
        self.view.options = tuple(ACTIVE + v if v == which else v for v in VIEWS)
        for name, handle in list(self.nodes.items()):
            if name.startswith("/assembly") or name.startswith("/inspect"):
                want = name.startswith("/assembly") == (which == "Assembly")
                handle.visible = want and getattr(handle, "_apose_visible", True)
        for pid, h in self.state.meshes.items():
            h.visible = which == "Assembly" and getattr(h, "_apose_visible", True)

    def on_download_image(self, client) -> None:
        """The 3D view as `client`'s tab draws it (viser's render API: the page renders a frame at its own view
        size and sends it back), as a PNG download. The studio lock is let go while the page renders: other
        tabs go on meanwhile."""
        import cv2

        if client is None:
            raise AposeError("no browser to send the image to")
        w, h = int(client.camera.image_width), int(client.camera.image_height)
        if not (16 <= w <= 8192 and 16 <= h <= 8192):
            raise AposeError(f"this tab reports a {w}x{h} view; resize the window and try again")
        self.lock.release()
        try:  # a JPEG (viser's quality 80): a PNG of a busy view is over the 1 MiB a page may send (webguard.py)
            rgb = client.get_render(h, w, transport_format="jpeg", timeout=RENDER_TIMEOUT_S)
        except TimeoutError:
            raise AposeError(f"the page did not send its image within {RENDER_TIMEOUT_S:.0f} s; try again") from None
        finally:
            self.lock.acquire()
        ok, png = cv2.imencode(".png", cv2.cvtColor(np.asarray(rgb, np.uint8)[..., :3], cv2.COLOR_RGB2BGR))
        if not ok:
            raise AposeError("the image could not be encoded as PNG")
        send_download(client, f"apose_{self.current_view.lower()}_view.png", png.tobytes())

    def node(self, name: str, handle, visible: bool = True):
        handle._apose_visible = visible
        handle.visible = visible and name.startswith("/" + self.current_view.lower())
        self.nodes[name] = handle
        return handle

    def look_at(self, centre: np.ndarray, radius: float, direction: np.ndarray) -> None:
        """Every tab's camera (and a new tab's) looking at a sphere from `direction`, the sphere filling
        most of the view."""
        direction = np.asarray(direction, float) / max(np.linalg.norm(direction), 1e-9)
        for cam in self._cameras():
            try:
                fov = float(cam.fov)
            except Exception:
                fov = 0.0
            if not 0.05 < fov < 3.0:  # none yet, or a tab's report beyond belief: never trusted for arithmetic
                fov = np.radians(50.0)
            eye = centre + direction * (radius / np.sin(fov / 2.0)) * 1.1
            self._place(cam, (0.0, 0.0, 1.0), eye, centre)  # the world's up (a sensor's view may have turned it)

    def view_from(self, T_world_camera: np.ndarray, centre: np.ndarray, fov: float | None = None) -> None:
        """Every tab's camera (and a new tab's) at a sensor's pose looking at `centre`, the image's up as
        the view's up and its vertical field of view `fov` (radians): the scene as that camera saw it, each
        point about a pixel on screen."""
        for cam in self._cameras():
            self._place(cam, -np.asarray(T_world_camera)[:3, 1], T_world_camera[:3, 3], centre, fov)  # OpenCV's y: down

    def _cameras(self) -> list:
        """Every tab's camera, and the one a new tab starts with."""
        if self.tab is not None:
            return [self.tab.camera]
        return [c.camera for c in self.server.get_clients().values()] + [self.server.initial_camera]

    def _place(self, cam, up, position, look_at, fov: float | None = None) -> None:
        """Move one camera. One that cannot be moved keeps its view: a tab's camera, whatever it reported,
        never breaks another tab's action."""
        try:
            up = tuple(float(v) for v in up)
            if cam is self.server.initial_camera:
                cam.up = up
            else:
                cam.up_direction = up
            cam.position, cam.look_at = tuple(float(v) for v in position), tuple(float(v) for v in look_at)
            if fov is not None:
                cam.fov = float(fov)
        except Exception as e:
            log.info("a camera was not moved (%s: %s)", type(e).__name__, e)

    def frame_camera_on_assembly(self) -> None:
        """Frame what the selected step is about: its part and the sub-assembly it goes on (the parts sharing
        its base's root, as placed up to that step), not the parts waiting aside; every part shown when no
        step is selected (or none of those is drawn)."""
        preview = dict(self.state.preview)
        i, asm = self.state.step_index, self.valid_asm
        if i is not None and i < len(asm.steps) and asm is self.asm:
            s = asm.steps[i]
            root = asm.root_of(s.base[0])
            wanted = {root, s.part} | {t.part for t in asm.steps[:i + 1] if asm.root_of(t.part) == root}
            preview = {p: T for p, T in preview.items() if p in wanted} or preview
        spheres = []
        for pid, T_world_part in preview.items():
            try:
                m = self.model(pid, self.valid_asm)
            except (AposeError, KeyError):
                continue
            spheres.append((se3.transform_points(T_world_part, m.box_corners()).mean(axis=0), m.diameter / 2.0))
        if not spheres:
            return
        centres = np.array([c for c, _ in spheres])
        centre = (centres.min(axis=0) + centres.max(axis=0)) / 2.0
        radius = max(float(np.linalg.norm(c - centre)) + r for c, r in spheres)
        self.look_at(centre, radius, np.array([1.0, -1.0, 0.75]))

    def next_pointer(self, client, title: str, kind: str, handle, ask: str) -> None:
        """The next click (kind "click") or dragged rectangle ("rect") in the 3D view of this tab goes to
        handle(event, client), guarded like every callback; `ask` tells the user what to do. Pointing
        is at the inspected frame, so there must be one."""
        if self.state.inspect.frame is None:
            raise AposeError("open a dataset or capture first")
        if client is None:
            raise AposeError("no browser to point in")
        scene = client.scene
        register, remove = ((scene.on_click, scene.remove_click_callback) if kind == "click"
                            else (scene.on_rect_select, scene.remove_rect_select_callback))

        def once(event) -> None:
            remove(once)
            self.guarded(title)(lambda c: handle(event, c))(event)

        register()(once)
        self.notify(client, title, ask)

    def estimate_job(self, step: int, ids: list[int]) -> EstimateJob:
        """An estimate of frames `ids` of `step` with the Inspect panel's settings of this moment (its
        Estimate folder owns them); for panels that estimate in their own way (Views)."""
        return self.inspect.job(step, ids)

    def start_thread(self, target, *args, name: str) -> threading.Thread:
        """A daemon thread for a panel's background work (a player, a warm-up), started under the read
        confinement every page action has (safeio.reads_within the workspace): a file read in the background
        obeys the workspace as one read by a click does. Panels start their threads only here."""
        readable = self.workspace.readable

        def run():
            with reads_within(readable):
                target(*args)

        thread = threading.Thread(target=run, daemon=True, name=name)
        thread.start()
        return thread

    def show_draft(self) -> None:
        """A new tab's studio shows the shared draft as it is now: its first step selected (none without
        steps), assembled, the Assembly file field on its file, the camera framing it."""
        asm = self.asm
        self.state.step_index = 0 if asm.steps else None
        self.refresh_assembly_widgets()
        if self.state.saved_path is not None:
            self.events.emit(Event.DRAFT_OPENED)
        self.frame_camera_on_assembly()
        self.seen_asm = asm

    def catch_up(self, journal: list) -> None:
        """Another tab's action changed the draft (Desk.spread, under the lock): replay the draft events it
        emitted here, with this tab's own selection kept on its step (the same step wherever it moved; in its
        place when edited; the last one when it is gone; the first for another file), and draw the draft anew
        if no event did. Faces picked here are dropped once the selected step places another part."""
        self.clear_errors(self.tab)  # errors kept here are about a draft no longer on show
        if self.steps.drop_drag() | self.files.drop_region_drag():
            self.notify(self.tab, "Drag stopped", "another tab changed the assembly during this drag; what it had "
                        "moved stays. Let go, check the step, and drag again", error=True)
        before, i = self.seen_asm, self.state.step_index
        was = before.steps[i] if i is not None and i < len(before.steps) else None
        n = len(self.asm.steps)
        opened = before is not self.asm and any(e is Event.DRAFT_OPENED for e, _ in journal)  # another file
        if opened:
            i = 0 if n else None
        elif was is not None:
            same = [j for j, s in enumerate(self.asm.steps) if s is was]  # (steps are never changed in place)
            i = same[0] if same else (min(i, n - 1) if n else None)
        elif i is None and n and not before.steps:
            i = 0  # the first step of a draft that had none
        moved = i != self.state.step_index
        self.state.step_index = i
        now = self.asm.steps[i] if i is not None else None
        if self.state.picks and (now is None or was is None or now.part != was.part or tuple(now.base) != tuple(was.base)):
            self.mates.clear_picks()  # faces picked for the step this tab had selected
        drawn = False
        for event, payload in journal:
            if event is Event.MESHES_CHANGED:
                self.mates.clear_picks()  # a picked face may belong to a part gone or changed
            self.events.emit(event, **payload)
            drawn |= event is Event.DRAFT_CHANGED
        if not drawn and (before is not self.asm or moved):
            self.refresh_assembly_widgets()  # the fields always show the step selected here
        if moved and not opened:  # (another file is shown assembled, as Open shows it)
            self.steps.preview_up_to_selected()
        self.seen_asm = self.asm

    def shutdown(self) -> None:
        """Before the server stops (Ctrl-C): the player stopped, a live camera closed, the background
        preparation finished (a process that exits inside Open3D is aborted by the C++ runtime)."""
        self.steps.stop_play()
        self.sequence.stop()
        frames = self.state.inspect.frames
        if hasattr(frames, "close"):  # a live camera
            frames.close()
        self.inspect.settle()

    def estimate_frame(self, job: EstimateJob, im_id: int):
        """(result, score) of frame `im_id` of `job`, estimated with its settings and cached (the Inspect panel's
        estimate, for panels that run estimates of their own: the Sequence player)."""
        return self.inspect.estimate(job, im_id)

    def step_context(self, step: int):
        """The inspected assembly's prepared context for `step` (cached by the Inspect panel)."""
        return self.inspect.context(step)

    def model(self, pid: str, asm: Assembly | None = None) -> PartModel:
        """A part's loaded mesh and derived geometry, cached by file, unit, colour and index."""
        return self.desk.model(pid, asm if asm is not None else self.asm)

    def close_errors_of(self, client, title: str, shown: list) -> None:
        """Close the errors among `shown` (on screen before the action ran) that an earlier try of the action
        `title` raised on `client`'s tab: it has now gone through, and a refusal left beside a success that says
        nothing (a prompt typed anew and sent with Enter) reads as if the new try had been refused too."""
        if client is None or not shown:
            return
        mine = [h for h in shown if title is None or self._error_titles.get(id(h)) == title]  # (None: every one shown)
        if not mine:
            return
        left = [h for h in self._errors_shown.get(client.client_id, []) if not any(h is m for m in mine)]
        self._errors_shown[client.client_id] = left
        for old in mine:
            self._error_titles.pop(id(old), None)
            try:
                old.remove()
            except Exception:  # a tab that just closed
                pass

    def close_refusals(self, client) -> None:
        """Close the errors (red) kept open on `client`'s tab, leaving kept results (a step's summary): another frame or
        step on show, which they were about ("frame 1: not confident" stayed up over frame 0's result)."""
        if client is None:
            return
        shown = self._errors_shown.get(client.client_id, [])
        self.close_errors_of(client, None, [h for h in shown if id(h) in self._error_titles])

    def clear_errors(self, client) -> None:
        """Close the errors kept open on `client`'s tab: an action that takes back what they were about (Undo)."""
        if client is None:
            return
        for old in self._errors_shown.pop(client.client_id, []):
            self._error_titles.pop(id(old), None)
            try:
                old.remove()
            except Exception:  # a tab that just closed
                pass

    def undo_redo(self, which: str, client) -> None:
        asm = self.history.undo(self.asm) if which == "Undo" else self.history.redo(self.asm)
        self.clear_errors(client)  # a refusal shown before is about a draft no longer on show
        self.events.emit(Event.MESHES_CHANGED, pid=None)  # a part may come back with another mesh
        self.mates.clear_picks()
        self.set_assembly(asm, client, record=False)  # the typed pose fields follow the draft

    def set_assembly(self, asm: Assembly, client=None, quiet: bool = False, record: bool = True) -> None:
        """Adopt a new draft: validate, remember the last valid one, keep the selected step inside it,
        and tell every view of it (DRAFT_CHANGED). With `record`, the draft it replaces goes on the
        undo history."""
        if record and asm is not self.asm:
            self.history.record(self.asm)
        self.asm = asm
        self.problems = authoring.problems(asm)
        hard = [p for p in self.problems if p.key != "steps"]  # "no steps yet" is not an error
        if not hard:
            self.valid_asm = asm
        elif not quiet:
            self.notice_problems_later(client)
        if self.state.step_index is not None and self.state.step_index >= len(asm.steps):
            self.state.step_index = len(asm.steps) - 1 if asm.steps else None
        elif self.state.step_index is None and asm.steps and not self.seen_asm.steps:
            self.state.step_index = 0  # steps again (an Undo of deleting them all): the first one selected
        self.refresh_assembly_widgets()

    def notice_problems_later(self, client, delay: float = 0.8) -> None:
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

    def require_valid(self) -> None:
        if self.problems:
            raise AssemblyError(self.problems)

    def refresh_assembly_widgets(self) -> None:
        """Every widget and the preview show the draft and the selected step as they are now."""
        self.events.emit(Event.DRAFT_CHANGED)


MAX_PENDING_PER_TAB = 4  # page actions one tab may have waiting for the studio at once
MAX_PENDING_ALL = 16  # ... and all tabs together (the 16 connections a studio takes, flooding at once)


def default_workspace(assembly=None, dataset=None, root=None) -> Workspace:
    """The folders the page may name: `root` if given, else the current directory, or the assembly
    file's folder when the file lies outside it; a dataset given at start is always readable."""
    if root is None:
        cwd = Path.cwd().resolve()
        folder = Path(assembly).expanduser().resolve().parent if assembly is not None else cwd
        root = cwd if folder.is_relative_to(cwd) else folder
    return Workspace.of(root, dataset)


def serve(assembly=None, dataset=None, host: str = "127.0.0.1", port: int = 8080, cache=None, root=None,
          token: str | None = None, obj_map: list[str] | None = None, tabs: bool = True):
    """Start the studio in the background; returns (server, studio). `server.stop()` ends it.

    `tabs` (the default): each browser tab gets a studio of its own (its selection, fields and 3D view)
    over the one shared draft, and `studio` is the `Desk` (its `views` are the tabs' studios). `tabs=False`:
    one `Studio` on the server's GUI, shared by every tab, driven without a page (tests, export-html).

    Only the studio's own page may connect (Origin check), and the page and its websocket need
    `token` (a new random one when None, on loopback too); `studio.url` is the address to open. `obj_map`:
    PART=OBJ_ID items for a BOP scene `dataset` (its ground truth)."""
    if not 0 < int(port) < 65536:
        raise AposeError(f"--port {port}: expected a port number from 1 to 65535")
    token = new_token() if token is None else check_token(token)
    ready = threading.Event()  # pages may connect once the studio (and its screen of their messages) is built
    server = start_viser(host, port, token, ready=ready)
    try:
        workspace = default_workspace(assembly, dataset, root)
        studio = open_desk(server, assembly, dataset, cache, workspace, obj_map) if tabs else \
            Studio(server, assembly, dataset, cache, workspace, obj_map)
    except BaseException:
        server.stop()
        raise
    studio.url = studio_url(host, server.get_port(), token)
    ready.set()
    return server, studio


def open_desk(server, assembly, dataset, cache, workspace: Workspace, obj_map) -> Desk:
    """The shared half of a studio whose tabs each get their own (`serve(tabs=True)`): the server guarded,
    the start-up assembly read (its errors end the start, as a bad file named on the command line should),
    and a tab's studio built when it connects."""
    desk = Desk(server, workspace, cache)

    def notify(client, *a, **k):  # a refusal for a tab: through its studio (none yet: straight to the tab)
        view = desk.views.get(getattr(client, "client_id", None))
        if view is not None:
            view.notify(client, *a, **k)
        elif client is not None:
            client.add_notification(a[0], a[1], color="red", auto_close_seconds=None)

    screen_messages(server, notify)  # before any page's message is handled
    limit_uploads(server.gui, desk.upload_states, MAX_UPLOAD_BYTES,
                  lambda cid, *a, **k: notify(server.get_clients().get(cid), *a, **k))
    if assembly is not None:  # named on the command line: the user's own files, not the page's
        asm = desk.open(Path(assembly), confine=False)
        desk.workspace = desk.workspace.trusting(*(p.mesh.parent for p in asm.parts.values()))
    desk.make_view = lambda client: Studio(server, None, dataset, desk=desk, tab=client, obj_map=obj_map)
    server.on_client_connect(desk.on_connect)
    server.on_client_disconnect(desk.on_disconnect)
    return desk
