"""What the studio's panels share, and how they tell each other that it changed.

`StudioState` holds the data more than one panel reads: the draft assembly (a `Draft`, shared by every
browser tab), and the tab's own selected step, preview poses and part meshes in the 3D view, the faces
picked for a mate, and (in `InspectState`) the inspected data, frame, estimate, mask source and prompt.
The app owns it; each field names the panel that writes it, the others only read it.

`Events` is a small synchronous hub: `on(event, fn)` subscribes, `emit(event, **payload)` calls the
subscribers in the order they subscribed, in the emitting thread (and first its `tap`, through which the
desk keeps the draft's events for the other tabs: desk.py). Every studio callback already
runs under the studio lock (`Studio.guarded`), so subscribers do too. The events are the fixed set
in `Event`, each with the payload keys in `PAYLOAD`; a panel that must react to another panel's
action subscribes to its event instead of being called by it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path
from typing import Callable

import numpy as np

from apose_studio.assembly.mesh import PartModel, load_parts
from apose_studio.assembly.model import Assembly
from apose_studio.data.bop import BopScene
from apose_studio.data.dataset import Dataset, Frame
from apose_studio.data.realsense import LiveCamera
from apose_studio.data.recording import Recording, RecordingPlayer
from apose_studio.errors import AposeError
from apose_studio.studio import authoring


class Event(str, Enum):
    """What happened, for the panels that show it. Payload keys: `PAYLOAD`."""

    DRAFT_CHANGED = "draft changed"  # the draft (and with it maybe the selected step) was adopted: widgets and preview refresh
    STEP_SELECTED = "step selected"  # the user selected step `index` (0-based) in the Steps folder; the draft is the same
    MESHES_CHANGED = "meshes changed"  # part `pid`'s mesh (every part's when None) must be drawn anew: colour, units, file
    DRAFT_OPENED = "draft opened"  # an assembly file was opened and adopted: the preview shows it assembled
    DRAFT_SAVED = "draft saved"  # the draft was written to `state.saved_path`
    PICKS_CHANGED = "picks changed"  # `state.picks` changed (a face picked, a pick dropped, picks cleared)
    REGION_HANDLES = "region handles"  # Drag region's handles came or went (`state.region_handles`)
    FRAME_CHANGED = "frame changed"  # `state.inspect.frame` (and its cached result and score) changed
    RESULT_READY = "result ready"  # a new estimate is in `state.inspect.result` / `score` for `state.inspect.frame`
    MASK_SOURCE_CHOSEN = "mask source chosen"  # the user chose mask source `source` outside the Mask dropdown
    OVERLAY_CHANGED = "overlay changed"  # what the RGB overlay shows changed (a prompt's mask): redraw it
    PROMPT_CHANGED = "prompt changed"  # the typed prompt changed (usable or not): a result made with another is not shown
    FRAMING_ASKED = "framing asked"  # the cameras should look at the object under inspection (an export records them)
    PLAYED = "played"  # Play sequence put part `pid` at `T_world_part` (pid None: the play ended)
    FRAME_PLAYED = "frame played"  # the Sequence folder's player put frame `im_id` (and its result) on show


PAYLOAD: dict[Event, tuple[str, ...]] = {
    Event.DRAFT_CHANGED: (),
    Event.STEP_SELECTED: ("index",),
    Event.MESHES_CHANGED: ("pid",),
    Event.DRAFT_OPENED: (),
    Event.DRAFT_SAVED: (),
    Event.PICKS_CHANGED: (),
    Event.REGION_HANDLES: (),
    Event.FRAME_CHANGED: (),
    Event.RESULT_READY: (),
    Event.MASK_SOURCE_CHOSEN: ("source",),
    Event.OVERLAY_CHANGED: (),
    Event.PROMPT_CHANGED: (),
    Event.FRAMING_ASKED: (),
    Event.PLAYED: ("pid", "T_world_part"),
    Event.FRAME_PLAYED: ("im_id",),
}


class Events:
    """Subscribers by event; `emit` calls them in subscription order, synchronously. An event outside
    `Event`, or a payload without exactly the keys `PAYLOAD` lists, is a programming error (TypeError)."""

    def __init__(self, tap: Callable[[Event, dict], None] | None = None) -> None:
        self._subscribers: dict[Event, list[Callable[..., None]]] = {e: [] for e in Event}
        self._tap = tap  # told of every event before its subscribers (the desk keeps the draft's for other tabs)

    def on(self, event: Event, fn: Callable[..., None]) -> None:
        if not isinstance(event, Event):
            raise TypeError(f"{event!r} is not a studio Event")
        self._subscribers[event].append(fn)

    def subscribers(self, event: Event) -> tuple[Callable[..., None], ...]:
        return tuple(self._subscribers[event])

    def emit(self, event: Event, **payload) -> None:
        if not isinstance(event, Event):
            raise TypeError(f"{event!r} is not a studio Event")
        if set(payload) != set(PAYLOAD[event]):
            raise TypeError(f"{event.name} carries {PAYLOAD[event]}, not {tuple(payload)}")
        if self._tap is not None:
            self._tap(event, payload)
        for fn in list(self._subscribers[event]):
            fn(**payload)


@dataclass
class InspectState:
    """The Inspect tab's data. Written by the Inspect panel (data, step, frame, estimate, mask source),
    the Views panel (a fused estimate), the Prompt panel (prompt text) and the Robot panel (hand-eye, pick
    estimates); read by the others."""

    frames: Dataset | Frame | Recording | LiveCamera | None = None  # a dataset, a capture (one Frame), a recording, a camera
    frames_path: str | None = None  # where it was opened from (results are cached under it)
    step: int | None = None  # the inspected step, 1-based
    frame: Frame | None = None  # the frame on show
    result: object | None = None  # the registration result for `frame` (None: not estimated)
    score: object | None = None  # its score against the truth (None: no truth or no result)
    refusal: str | None = None  # why the last Estimate of `frame` with these settings was refused (no result), or None
    refusals: dict = field(default_factory=dict)  # cache key -> that refusal, per frame and settings
    advice: object | None = None  # where to look from to settle `result` (registration.next_view.NextView), or None
    mask_source: str = ""  # the Mask dropdown's choice (gt, depth, box, prompt, or a model path)
    prompt_text: str = ""  # the Prompt field: a box x0,y0,x1,y1 or a point u,v, in pixels, on the image on show
    prompt_image: object | None = None  # the image `prompt_text` marks the base in (InspectPanel.image_key)
    prompts: dict = field(default_factory=dict)  # image key -> (the prompt typed there, whether Mask was 'prompt' when
    # the image was left): each image keeps its own
    prompt_masks: dict = field(default_factory=dict)  # (frame source, im_id, step, prompt, align) -> mask
    mask_asked: bool = False  # Show mask was pressed: the RGB shows the prompt's mask (not the estimate's) until the
    # frame is drawn anew (another frame, prompt or estimate)
    align_depth: bool = False  # the Prompt folder's "Align depth to colour": around the prompt, the depth moved
    # back onto the colour image (estimation.colour_registered), for the mask and the estimate
    part_models: dict = field(default_factory=dict)  # id(assembly) -> its PartModels (one assembly's)
    hand_eye: object | None = None  # the cell's calibration (robot.handeye.HandEye) from the Robot folder, or None
    T_robot_flange: np.ndarray | None = None  # eye-in-hand: the arm at the capture (its camera.json, else the file's)
    pick_estimates: dict = field(default_factory=dict)  # (frame source, im_id, step) -> (the Pick prompt (px) text,
    # the loose part's estimate there with it): the Robot panel's


    def pick_key(self) -> tuple | None:
        """The key of `pick_estimates` for the frame and step on show (None: no frame)."""
        return None if self.frame is None else (self.frame.source, self.frame.im_id, self.step)

    def pick(self) -> tuple:
        """(prompt text, estimate) of the loose part on the frame on show, or (None, None)."""
        return self.pick_estimates.get(self.pick_key(), (None, None))

@dataclass
class Draft:
    """The assembly being authored, shared by every tab of a studio: the draft, the last valid one, its
    problems, and the file it was opened from or saved to. Written by the app (`Studio.set_assembly`),
    the Steps panel (a gizmo drag) and the Assembly panel (open, new, save)."""

    asm: Assembly  # the draft
    valid_asm: Assembly  # the last draft without problems: what the preview shows
    problems: list  # the draft's problems (an empty draft has one: no steps)
    saved_path: Path | None = None  # the file the draft was opened from or last saved to
    saved_how: str = "saved"  # "opened" or "saved": what last made saved_path hold the draft (the status says it)
    saved_draft: Assembly | None = None  # the draft as it was opened or last saved (drafts are never changed in
    # place: `asm is saved_draft` means nothing is unsaved, Undo back to it included)

    @classmethod
    def empty(cls) -> "Draft":
        asm = authoring.new_assembly()
        return cls(asm=asm, valid_asm=asm, problems=authoring.problems(asm))


def _in_draft(name: str) -> property:
    return property(lambda st: getattr(st.draft, name), lambda st, v: setattr(st.draft, name, v),
                    doc=f"`draft.{name}` (shared by every tab)")


@dataclass
class StudioState:
    """One tab's data beside the draft it shares with the others (see the module docstring). `draft` is
    the studio's one `Draft` (its fields read as this state's own: `asm`, `valid_asm`, `problems`,
    `saved_path`, `saved_how`, `saved_draft`); the rest is this tab's: `step_index` written by the Steps
    panel and the app, `preview` and `meshes` by the Steps panel, `picks` by the Mates panel,
    `region_handles` by the Parts folder's Drag region, `inspect` by the Inspect tab's panels."""

    draft: Draft
    step_index: int | None = None  # the selected step, 0-based
    preview: dict[str, np.ndarray] = field(default_factory=dict)  # part id -> T_world_part in the preview
    meshes: dict[str, object] = field(default_factory=dict)  # part id -> its mesh handle in the 3D view
    picks: dict[str, tuple] = field(default_factory=dict)  # "part" / "base" -> (part id, Feature in its frame)
    region_handles: bool = False  # Drag region's handles are on a part: the step's gizmo steps aside meanwhile
    inspect: InspectState = field(default_factory=InspectState)

    asm = _in_draft("asm")
    valid_asm = _in_draft("valid_asm")
    problems = _in_draft("problems")
    saved_path = _in_draft("saved_path")
    saved_how = _in_draft("saved_how")
    saved_draft = _in_draft("saved_draft")

    @classmethod
    def empty(cls, draft: Draft | None = None) -> "StudioState":
        return cls(draft=draft if draft is not None else Draft.empty())

    def T_world_shown(self, pid: str) -> np.ndarray | None:
        """Where a part is drawn now: the selected step's part at the draft's pose, the others at the preview's."""
        i, asm = self.step_index, self.asm
        if i is not None and i < len(asm.steps) and asm.steps[i].part == pid and asm.steps[i].base[0] in self.preview:
            return self.preview[asm.steps[i].base[0]] @ asm.steps[i].T_base_part
        return self.preview.get(pid)

    def inspect_assembly(self) -> Assembly:
        """The assembly under inspection: a dataset's own, else (a capture) the last valid draft."""
        frames = self.inspect.frames
        return frames.assembly if isinstance(frames, Dataset) else self.valid_asm

    def inspect_models(self) -> dict[str, PartModel]:
        """The PartModels of the inspected assembly (kept for one assembly at a time, not every draft's)."""
        asm = self.inspect_assembly()
        if id(asm) not in self.inspect.part_models:
            self.inspect.part_models = {id(asm): load_parts(asm)}
        return self.inspect.part_models[id(asm)]

    def part_model(self) -> PartModel:
        """The PartModel of the part the inspected step places."""
        return self.inspect_models()[self.inspect_assembly().steps[self.inspect.step - 1].part]

    def load_frame(self, step: int, im_id: int, frames=None, asm: Assembly | None = None) -> Frame:
        """Frame `im_id` of `step` from `frames` (default: the opened data); a capture is the one frame and a
        BOP scene's frames are its images, their base parts set from `asm` (default: the last valid draft)."""
        frames = self.inspect.frames if frames is None else frames
        if isinstance(frames, Dataset):
            return frames.frame(step, im_id)
        steps = (asm or self.valid_asm).steps
        if not 1 <= step <= len(steps):
            raise AposeError(f"step {step} is not in the assembly any more (it has {len(steps)}); choose a step")
        view = steps[step - 1]
        if isinstance(frames, BopScene):  # read from its files, with the truth of the typed obj_ids
            return frames.frame(im_id, view)
        if isinstance(frames, LiveCamera):  # a live camera keeps only its newest frame
            if frames.last is None or frames.last.im_id != im_id:
                raise AposeError(f"{frames.name}: frame {im_id} is gone (a live camera keeps only its newest frame; "
                                 "Capture saves the one on show)")
            return replace(frames.last, base=tuple(view.base), part=view.part, step=step)
        if isinstance(frames, (Recording, RecordingPlayer)):  # a recorded camera: its im_id-th frame, no truth
            return replace(frames.frame(im_id), base=tuple(view.base), part=view.part, step=step)
        # a copy: the opened capture is shared by every tab and job
        return replace(frames, base=tuple(view.base), part=view.part, step=step)


def shared(name: str, doc: str = "") -> property:
    """A panel attribute kept in the studio's shared state: `name` is its path in `app.state` ("step_index",
    "inspect.frame"). The panel that writes it keeps its old name for it; the others read the state. On
    the Studio itself (no `.app`) it reads its own `state`."""
    *parents, leaf = name.split(".")

    def owner(panel):
        obj = getattr(panel, "app", panel).state
        for p in parents:
            obj = getattr(obj, p)
        return obj

    return property(lambda panel: getattr(owner(panel), leaf), lambda panel, v: setattr(owner(panel), leaf, v),
                    doc=doc or f"`state.{name}`")
