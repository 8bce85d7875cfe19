"""What every browser tab of one studio shares: the draft and its undo history, the loaded part models, the
estimate cache, the workspace, the lock, and the count of actions waiting for it.

Each tab has a studio of its own (`app.Studio` on the tab's own GUI and 3D scene: viser's per-client
API), so that what a tab selects and shows is its own: tab B choosing step 2 leaves tab A's Step fields
on the step A's user picked, and a pose typed in A moves A's part. The draft is one (`state.Draft`, held
here), so an edit made in any tab reaches all of them: after each action, still under the lock, the
desk hands the other tabs the draft events the action emitted (`spread`), and each draws the draft anew.

A studio made without a desk of its own (`Studio(server)`, tests and `export-html`) makes one and draws on
the server's GUI, which every tab then shares.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from apose_studio.assembly.mesh import PartModel, load_part
from apose_studio.assembly.model import Assembly, load_assembly
from apose_studio.studio import authoring, inspection
from apose_studio.studio.state import Draft, Event
from apose_studio.studio.webguard import Workspace

log = logging.getLogger(__name__)

SHARED_EVENTS = (Event.MESHES_CHANGED, Event.DRAFT_CHANGED, Event.DRAFT_OPENED, Event.DRAFT_SAVED)  # about the draft


class Desk:
    """The shared half of a studio (module doc). `views`: client id -> that tab's studio (tabs of their own)."""

    def __init__(self, server, workspace: Workspace, cache: inspection.ResultCache | None = None):
        self.server = server
        self.workspace = workspace
        self.lock = threading.RLock()  # one edit at a time, whichever tab it comes from
        self.busy = threading.Lock()  # one estimation at a time
        self.draft = Draft.empty()  # the empty draft is not saveable either (it has no steps)
        self.history = authoring.History()
        self.models: dict[tuple, PartModel] = {}  # (mesh path, units, colour, index, roi) -> PartModel
        self.cache = cache if cache is not None else inspection.ResultCache()
        self.views: dict[int, object] = {}
        self.pending: dict[int, int] = {}  # client id -> its page actions waiting for or holding the lock
        self.pending_lock = threading.Lock()
        self.dropped_told: dict[int, float] = {}  # client id -> when it was last told of dropped presses
        self.url = ""
        self._journal: list[tuple[Event, dict]] = []  # the draft events of the action under way
        self._spreading = False
        self.make_view = None  # client -> its studio (set by serve(); None: one studio on the server's GUI)

    def model(self, pid: str, asm: Assembly) -> PartModel:
        """A part's loaded mesh and derived geometry, cached by file, unit, colour, index and region."""
        part = asm.parts[pid]
        key = (str(part.mesh), part.solid, asm.units, part.color, list(asm.parts).index(pid), part.roi)
        if key not in self.models:
            self.models[key] = load_part(part, asm.units, key[4])
        return self.models[key]

    def open(self, path: Path, confine: bool = True) -> Assembly:
        """Read an assembly file and make it the draft, its meshes loaded (a bad one is reported before
        anything changes) and the undo history cleared. `confine`: its meshes must lie in the workspace."""
        asm = load_assembly(path)
        if confine:
            self.workspace.check_assembly(asm)  # the meshes a file names obey the workspace as typed paths do
        for pid in asm.parts:
            self.model(pid, asm)
        d = self.draft
        d.saved_path, d.saved_how, d.saved_draft = asm.path, "opened", asm
        d.asm, d.problems = asm, authoring.problems(asm)
        if not [p for p in d.problems if p.key != "steps"]:
            d.valid_asm = asm
        self.history.clear()  # another file: Undo never brings the previous file's draft back over this one
        return asm

    # ----------------------------------------------------------------------------- tabs of their own

    def on_connect(self, client) -> None:
        """A new tab: its own studio, built on its GUI and scene, showing the draft as it is now."""
        with self.lock:
            view = self.make_view(client)
            gone = client.client_id not in self.server.get_clients()  # it closed while its studio was built
            if not gone:
                self.views[client.client_id] = view
        if gone:
            view.shutdown()
        else:
            view.on_connect(client)

    def on_disconnect(self, client) -> None:
        with self.lock:
            view = self.views.pop(client.client_id, None)
            with self.pending_lock:
                self.pending.pop(client.client_id, None)
                self.dropped_told.pop(client.client_id, None)
        if view is not None:  # (viser drops the tab's unfinished uploads itself)
            view.shutdown()

    def record(self, view, event: Event, payload: dict) -> None:
        """An event `view` emitted: a draft event is kept for the other tabs (`spread`)."""
        if event in SHARED_EVENTS and not self._spreading and self._is_tab(view) and len(self.views) > 1:
            self._journal.append((event, payload))

    def _is_tab(self, view) -> bool:
        """`view` is a connected tab's studio (not one still being built, whose first drawing of the draft is
        no change to it)."""
        return any(v is view for v in self.views.values())

    def spread(self, view) -> None:
        """After an action of `view` (under the lock): the other tabs draw the draft as it is now, through
        the draft events the action emitted, and DRAFT_CHANGED when the draft changed without one (a
        gizmo drag writes the draft directly)."""
        journal, self._journal = self._journal, []
        view.seen_asm = self.draft.asm
        if self._spreading or not self._is_tab(view):
            return
        self._spreading = True
        try:
            for other in list(self.views.values()):
                if other is not view:
                    try:
                        other.catch_up(journal)
                    except Exception:  # one tab that cannot draw never stops the others (nor the action's own tab)
                        log.exception("a tab did not follow the draft")
        finally:
            self._spreading = False

    def upload_states(self) -> list[dict]:
        """The upload buffers of every GUI (the server's and each tab's): limits count them together."""
        guis = [self.server.gui] + [v.ui.gui for v in list(self.views.values()) if v.ui is not self.server]
        return [g._current_file_upload_states for g in guis]

    def shutdown(self) -> None:
        """Before the server stops: each tab's player stopped, live camera closed, background work finished."""
        with self.lock:
            views = list(self.views.values())
        for v in views:
            v.shutdown()
