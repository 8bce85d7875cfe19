"""The Inspect tab's Data and Estimate folders: datasets and captures, step and frame, the estimator's
settings, the crop box, and estimates (fixed to the settings of the moment they are asked for, run
without the studio lock, cached).

The opened data, the inspected step and frame, its estimate and the Mask choice live in the studio's
shared state (`state.inspect`), which this panel writes; a new frame is FRAME_CHANGED. The prompt
comes from the shared state too (the Prompt panel writes it), and a mask source chosen elsewhere
(MASK_SOURCE_CHOSEN) is shown in the Mask dropdown."""

from __future__ import annotations

import copy
import itertools
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from apose_studio.assembly.model import Assembly
from apose_studio.data import realsense
from apose_studio.data.bop import BopScene, parse_obj_map
from apose_studio.data.dataset import Dataset, DatasetError, Frame
from apose_studio.data.realsense import LiveCamera, live_serial
from apose_studio.data.recording import Recording, is_recording, open_recording
from apose_studio.data.sources import open_frames
from apose_studio.errors import AposeError
from apose_studio.estimation import MASK_SOURCES, StepContext, check_mask_source, mask_sources_for
from apose_studio.evaluate import estimate_and_score
from apose_studio.geometry import se3
from apose_studio.masks.segment import depth_mask
from apose_studio.params import PRESETS, resolve_params
from apose_studio.registration import doubts, project_to_cloud
from apose_studio.registration.next_view import next_view
from apose_studio.studio import inspection
from apose_studio.studio.prompt_panel import PROMPT_SOURCE, colour_aligned, prompt_of, prompted_mask, typed_prompt
from apose_studio.studio.state import Event, shared
from apose_studio.studio.widgets import VECTOR_MM, scene_point_at_ray


def step_labels(asm: Assembly, steps: list[int] | None = None) -> list[str]:
    """The Inspect step choices: each step's number, the part it places and the base it registers ("2. label_can on
    watering_can"): the base is what must be in view and what a prompt marks (a newcomer looked for the object to
    box among the parts' names). `steps`: those numbers only (1-based; a dataset's), else all."""
    steps = steps if steps is not None else range(1, len(asm.steps) + 1)
    return [f"{k}. {asm.steps[k - 1].part} on {', '.join(asm.steps[k - 1].base)}" for k in steps]


log = logging.getLogger(__name__)
OPENED = itertools.count(1)  # live cameras opened: their results are cached apart (frame numbers restart)


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
    prompt: tuple | None = None  # (box, point) for mask "prompt"
    align: bool = False  # with a prompt: the depth moved onto the colour image around it first (Align depth to colour)

    def params(self):
        """The estimator's parameters for this job (Upright applies to the default preset)."""
        return resolve_params(self.preset, self.assembly.registration,
                              **({"upright": self.upright} if self.preset == "default" else {}))

    def key(self, cache: inspection.ResultCache, im_id: int) -> tuple:
        mask = self.mask
        if self.crop is not None:
            mask = (mask, tuple(np.round(self.crop[0], 4).ravel()), tuple(np.round(self.crop[1], 4)))
        if self.prompt is not None:
            mask = (mask, self.prompt, "depth onto colour") if self.align else (mask, self.prompt)
        preset = self.preset + (" free" if not self.upright and self.preset == "default" else "")
        return cache.key(self.frames_path, self.step, im_id, preset, mask, self.prior)


class InspectPanel:
    frames = shared("inspect.frames", "the opened data: a Dataset or a capture Frame (`state.inspect.frames`)")
    frames_path = shared("inspect.frames_path")
    frame = shared("inspect.frame", "the frame on show (`state.inspect.frame`)")
    result = shared("inspect.result", "its estimate, or None (`state.inspect.result`)")
    score = shared("inspect.score", "the estimate's score, or None (`state.inspect.score`)")

    def __init__(self, app):
        self.app = app
        self._syncing = False
        self.contexts: dict = {}  # (assembly, models identity, step) -> (assembly, models, StepContext)
        self._last_framing: tuple | None = None  # the last framing made (frame_camera_on_frame)
        self._warming: tuple | None = None  # (assembly identity, step) last prepared in the background
        self._warm_thread: threading.Thread | None = None
        self._told_step: int | None = None  # a BOP scene's step whose missing truth was last told
        app.events.on(Event.MASK_SOURCE_CHOSEN, self.on_mask_source_chosen)
        app.events.on(Event.DRAFT_CHANGED, self.follow_draft_steps)
        app.events.on(Event.FRAMING_ASKED, self.frame_camera_on_frame)
        app.events.on(Event.FRAME_PLAYED, self.on_frame_played)
        app.events.on(Event.PROMPT_CHANGED, self.on_prompt_changed)

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Data"):
            self.i_path = gui.add_text("Dataset or capture", "", hint="a folder from `apose render`, rgb.png + depth.png + "
                                       "camera.json, a BOP scene (scene_camera.json, rgb/, depth/), or a ROS 2 "
                                       "recording (.mcap: colour, aligned depth, camera_info)")
            b = gui.add_button("Open data")
            b.on_click(self.app.guarded("Open data")(lambda c: self.on_open_data(c)))
            self.i_obj_map = gui.add_text("BOP object ids", "", hint="a BOP scene's ground truth: which obj_id of its "
                                          "scene_gt.json each part is, PART=OBJ_ID separated by commas (e.g. housing=5)")
            self.i_obj_map.on_update(self.app.guarded("BOP object ids")(lambda c: self.on_obj_map(c)))
            self.i_step = gui.add_dropdown("Inspect step", ("—",))
            self.i_step.on_update(self.app.guarded("Step")(lambda c: self.on_other_frame(c)))
            self.i_frame = gui.add_slider("Frame", 0, 1, 1, 0)
            self.i_frame.on_update(self.app.guarded("Frame")(lambda c: self.on_other_frame(c)))
        with gui.add_folder("Estimate") as self.estimate_folder:
            self.i_preset = gui.add_dropdown("Preset", tuple(PRESETS), initial_value="default")
            sources = tuple(MASK_SOURCES)
            self.i_mask = gui.add_dropdown("Mask", sources + (PROMPT_SOURCE,), initial_value=sources[0],
                                           hint="gt: the dataset's masks; depth: table removal + 3D clustering; box: "
                                           "prompted by the truth's box; prompt: your box or click (Prompt folder); "
                                           "or a trained model")
            self.app.state.inspect.mask_source = self.i_mask.value  # shared: the Prompt panel and the overlay read it
            self.i_mask.on_update(self.app.guarded("Mask")(
                lambda c: setattr(self.app.state.inspect, "mask_source", self.i_mask.value)))
            # the less used settings folded away, so that the Result folder is nearer the Run buttons
            with gui.add_folder("Mask model", expand_by_default=False):
                self.i_model = gui.add_text("Mask model (.pt)", "", hint="a model from `apose train-seg` for this assembly")
                b = gui.add_button("Use model")
                b.on_click(self.app.guarded("Mask model")(self.on_use_model))
            with gui.add_folder("Crop box (depth masks)", expand_by_default=False):
                self.i_crop = gui.add_checkbox("Crop box", False, hint="limit depth masks to a box you drag around the base object")
                self.i_crop_size = gui.add_vector3("Crop size (mm)", (150.0, 150.0, 100.0), min=(1.0, 1.0, 1.0),
                                                   max=(1e5,) * 3, step=5.0)
                self.i_crop_centre = gui.add_vector3("Crop centre (mm)", (0.0, 0.0, 0.0), step=1.0, **VECTOR_MM,
                                                     hint="world frame; typed, dragged with the box's gizmo, or clicked")
                b = gui.add_button("Crop around click", hint="then click the base object in the 3D view")
                b.on_click(self.app.guarded("Crop around click")(self.on_crop_around_click))
            self.i_crop.on_update(self.app.guarded("Crop box")(lambda c: self.show_crop()))
            self.i_crop_size.on_update(self.app.guarded("Crop box")(lambda c: self.show_crop()))
            self.i_crop_centre.on_update(self.app.guarded("Crop box")(lambda c: self.on_crop_centre()))
            self.i_upright = gui.add_checkbox("Upright", True,
                                              hint="where a table is seen, search first the yaw of the base standing on it as "
                                              "modelled, then freely if that fits poorly (preset default)")
            self.i_prior = gui.add_checkbox("Orientation prior", False, hint="take the CAD orientation as the base's (the paper's assumption)")
            for w in (self.i_preset, self.i_mask, self.i_prior, self.i_upright):
                w.on_update(self.app.guarded("Estimator")(lambda c: self.on_frame_changed()))
            row = gui.add_button_group("Run", ("Estimate frame", "Estimate step"))
            row.on_click(self.on_estimate)
            self.i_progress = gui.add_progress_bar(0.0, visible=False)

    def on_open_data(self, client) -> None:
        try:
            text = self.i_path.value.strip()
            if not text:
                raise AposeError("type a dataset folder (from `apose render`) or a capture folder into 'Dataset or capture'")
            live, serial = live_serial(text)
            if live:
                self.open_live(serial)
            else:
                self.open_frames(str(self.app.workspace.resolve(text, "dataset or capture")), client)
        except AposeError as e:
            if self.frames_path is not None:  # say what stays on screen
                raise AposeError(f"{e}\n(still showing the data opened before: {self.frames_path})") from None
            raise
        if isinstance(self.frames, Dataset):
            what = f"a dataset of {len(self.frames.steps)} step(s)"
        elif isinstance(self.frames, Recording):
            rec = self.frames
            what = (f"a recording of {len(rec)} frames ({rec.seconds:.1f} s; {rec.topics['color']}, {rec.topics['depth']}"
                    f"{', camera poses' if rec.topics.get('pose') else ''}): Play it in the Sequence folder")
        elif isinstance(self.frames, LiveCamera):
            cam = self.frames
            what = (f"live, {cam.camera.width}x{cam.camera.height}, depth aligned to colour: Play in the Sequence folder "
                    "streams it with the base tracked; Estimate frame estimates the frame on show; Capture saves it"
                    + "".join(f"; {n}" for n in cam.notes))
        elif isinstance(self.frames, BopScene):
            mapped = ", ".join(f"{k}={v}" for k, v in self.frames.obj_of_part.items())
            present = ", ".join(map(str, self.frames.obj_ids())) or "none"
            what = (f"a BOP scene of {len(self.frames.image_ids())} image(s), obj_ids {present} in its ground truth; " +
                    (f"mapped: {mapped}" if mapped else "type 'BOP object ids' (PART=OBJ_ID) to compare with it"))
        else:
            what = "a capture"
        self.app.notify(client, "Data opened", f"{self.frames_path}: {what}")  # and an older error on screen closes

    def open_frames(self, text: str, client=None, confine: bool = True) -> None:
        path = Path(text).expanduser()
        frames = open_recording(path) if is_recording(path) else open_frames(path)
        if isinstance(frames, Recording):
            if not self.app.valid_asm.steps:
                raise AposeError("a recording needs an assembly: open one in the Assembly tab first")
            frames.frame(0)  # read now: a refusal leaves what is shown as it was
            steps = step_labels(self.app.valid_asm)
        elif isinstance(frames, BopScene):
            if not self.app.valid_asm.steps:
                raise AposeError("a BOP scene needs an assembly: open one in the Assembly tab first")
            ids = frames.image_ids()
            if not ids:
                raise AposeError(f"{text}: its scene_camera.json lists no images")
            frames.obj_of_part = self.obj_map(self.app.valid_asm, frames)  # the typed ids, checked against these parts
            frames.frame(ids[0], self.app.valid_asm.steps[0])  # read now: a refusal leaves what is shown as it was
            steps = step_labels(self.app.valid_asm)
        elif isinstance(frames, Dataset):
            if confine:  # a dataset named on the command line at start is the user's choice
                self.app.workspace.check_assembly(frames.assembly)
            steps = step_labels(frames.assembly, frames.steps)
            first = frames.steps[0] if frames.steps else None
            ids = frames.image_ids(first) if first is not None else []
            if ids:  # its first frame read now (scene files, images): a refusal leaves what is shown as it was
                frames.frame(first, ids[0])
        else:
            if not self.app.valid_asm.steps:
                raise AposeError("a capture needs an assembly: open one in the Assembly tab first")
            steps = step_labels(self.app.valid_asm)
        self.show_frames(frames, str(Path(text).expanduser().resolve()), steps)

    def open_live(self, serial: str | None) -> None:
        """A RealSense (the one with `serial`, else the first found) as the opened data: its newest frame on show.
        Its results are cached under the camera's name and the moment it was opened (frame numbers restart)."""
        if not self.app.valid_asm.steps:
            raise AposeError("a live camera needs an assembly: open one in the Assembly tab first")
        cam = realsense.open_realsense(serial)
        try:
            cam.next_frame()  # a camera that sends nothing is refused now, and what is shown stays
        except BaseException:
            cam.close()
            raise
        steps = step_labels(self.app.valid_asm)
        self.show_frames(cam, f"{cam.name} (opened {time.strftime('%Y-%m-%d %H:%M:%S')}, #{next(OPENED)})", steps,
                         "realsense" + (f":{serial}" if serial else ""))

    def follow_draft_steps(self) -> None:
        """Data inspected against the draft (a capture, a BOP scene, a camera, a recording: not a dataset, which
        has its own assembly): its Step list follows the draft's steps, edited here or in another tab; a step
        that is gone leaves the one now in its place (the last) on show."""
        if self.frames is None or isinstance(self.frames, Dataset) or not self.app.valid_asm.steps:
            return
        steps = step_labels(self.app.valid_asm)
        if list(self.i_step.options) == steps:
            return
        before = self.i_step.value
        k = min(self.current_step(), len(steps)) - 1
        self._syncing = True
        try:
            self.i_step.options = steps
            self.i_step.value = before if before in steps else steps[k]
        finally:
            self._syncing = False
        if self.i_step.value != before:
            self.result = self.score = None
            self.on_frame_changed()

    def show_frames(self, frames, frames_path: str, steps: list[str], typed: str | None = None) -> None:
        """`frames` become the opened data (a live camera shown before is closed); its first step on show."""
        self.offer_mask_sources(self.bop_truth(frames, 1) if isinstance(frames, BopScene) else
                                isinstance(frames, Dataset) or (isinstance(frames, Frame) and bool(frames.masks)))
        old = self.frames
        self.frames, self.frames_path = frames, frames_path
        if isinstance(old, LiveCamera) and old is not frames:
            old.close()
        self.result = self.score = None
        self.i_path.value = typed or self.frames_path
        before = self.i_step.value
        self._syncing = True
        try:
            self.i_step.options = steps
            self.i_step.value = before if before in steps else steps[0]  # reopened or a step's recording: its step stays
        finally:
            self._syncing = False
        self.app.show_view("Inspect")
        self.on_frame_changed()
        self.frame_camera_on_frame()

    def obj_map(self, asm: Assembly, scene: BopScene | None = None) -> dict[str, int]:
        """'BOP object ids' read against the assembly's parts (PART=OBJ_ID, commas or spaces between), and
        against the obj_ids `scene` shows. The refusal names the item typed (the notice's title names the field)."""
        items = [t for t in str(self.i_obj_map.value).replace(",", " ").split() if t]
        try:
            mapped = parse_obj_map(items, asm.parts)
            if scene is not None:  # none of the typed ids in this scene: refused (a map naming every object of a
                # dataset is fine; the step on show is told whether its base has a truth: tell_truth)
                scene.check_obj_map(mapped, flag="")
            return mapped
        except DatasetError as e:
            raise AposeError(str(e).replace("--obj-map ", "").strip()) from None

    def bop_truth(self, frames: BopScene, step: int) -> bool:
        """Whether a BOP scene has ground truth for the step's base (its obj_id typed, scene_gt.json there)."""
        steps = self.app.valid_asm.steps
        base = steps[step - 1].base[0] if 0 < step <= len(steps) else None
        return bool(frames.gt) and base in frames.obj_of_part and frames.images_with(frames.obj_of_part[base]) > 0

    def on_obj_map(self, client=None) -> None:
        """New 'BOP object ids': the opened BOP scene's ground truth follows them (masks, poses, scores), and
        the tab is told in how many of the scene's images each typed object is."""
        if not isinstance(self.frames, BopScene):
            if str(self.i_obj_map.value).strip():
                self.obj_map(self.app.valid_asm)  # checked now all the same: a typo is said where it was typed
            return
        mapped = self.obj_map(self.app.valid_asm, self.frames)
        # a new scene object: an estimate running now keeps the map (and the cache key) it started with
        self.frames = copy.copy(self.frames)
        self.frames.obj_of_part = mapped
        self._told_step = self.current_step()  # told below, not again by the frame change
        self.on_frame_changed()  # offers the masks the truth allows
        self.tell_truth(client)

    def tell_truth(self, client=None) -> None:
        """Say which of the typed obj_ids the scene shows, and whether the step on show has its base's truth."""
        scene, n = self.frames, len(self.frames.image_ids())
        seen = [f"{part} (obj_id {oid}) in {scene.images_with(oid)} of {n} images"
                for part, oid in scene.obj_of_part.items()]
        steps, k = self.app.valid_asm.steps, self.current_step()
        base = steps[k - 1].base[0] if 0 < k <= len(steps) else None
        present = ", ".join(map(str, scene.obj_ids())) or "none"
        if not seen:
            self.app.notify(client, "Ground truth", "none: no BOP object ids typed")
        elif base is not None and base not in scene.obj_of_part:
            self.app.notify(client, "No ground truth for this step",
                            f"{'; '.join(seen)}; but the step's base {base!r} has no obj_id: type {base}=ID "
                            f"(this scene shows obj_ids {present})", error=True)
        elif base is not None and not scene.images_with(scene.obj_of_part[base]):
            self.app.notify(client, "No ground truth for this step",
                            f"{'; '.join(seen)}: the step's base {base!r} (obj_id {scene.obj_of_part[base]}) is in "
                            f"none of this scene's images (it shows obj_ids {present})", error=True)
        else:
            self.app.notify(client, "Ground truth", "; ".join(seen))

    def offer_mask_sources(self, truth: bool) -> None:
        """The Mask choices that work on the data opened: without ground truth (a capture) neither `gt` nor
        `box` (both read the truth's masks); a capture starts on the typed prompt when there is one, else
        on depth, and moves from that default to `gt` when a truth comes. Models added with 'Use model' stay."""
        models = [o for o in self.i_mask.options if o not in MASK_SOURCES and o != PROMPT_SOURCE]
        options = list(mask_sources_for(truth)) + [PROMPT_SOURCE] + models
        had_truth = "gt" in self.i_mask.options
        if list(self.i_mask.options) != options:
            self.i_mask.options = options
        if self.i_mask.value not in options or (not truth and self.i_mask.value == "depth"):
            typed = self.app.state.inspect.prompt_text.strip()
            self.i_mask.value = PROMPT_SOURCE if typed else ("gt" if truth else "depth")
        elif truth and not had_truth and self.i_mask.value == "depth":  # a truth just came (a BOP scene's typed
            self.i_mask.value = "gt"  # ids): its masks, as a dataset opens on them
        self.app.state.inspect.mask_source = self.i_mask.value

    FILL = 2.0  # an estimated object framed from its sensor: its radius times this fills half the view's height

    def frame_camera_on_frame(self, again: bool = True) -> None:
        """Frame the object under inspection (its mask, else the estimate's points, else the middle of the
        depth image). A capture is seen from its sensor's pose, as the camera saw it (a real scene seen from
        elsewhere is a wall of points in front of the object); a rendered frame from beside and above its
        camera, so that the frustum does not block the view. `again=False` (after an estimate): only when
        that framing differs from the last one made, so that an estimate neither moves a view the user
        has turned nor costs the browser the redraws of a camera move."""
        fr = self.frame
        if fr is None:
            return
        framing = self.framing(fr)
        if framing is None:
            return
        if not again and self._last_framing is not None and self._last_framing[0] == framing[0] \
                and np.allclose(self._last_framing[1], framing[1], atol=1e-9):
            return
        self._last_framing = framing
        kind, args = framing
        if kind == "sensor":
            fov = 2.0 * np.arctan2(fr.camera.height / 2.0, fr.camera.fy)
            T = fr.T_world_camera
            radius = float(args[15])
            if radius > 0:  # an estimate's target: nearer along the sensor's ray to it, until it fills the view
                centre, eye = args[:3], T[:3, 3]
                far = float(np.linalg.norm(eye - centre))
                near = min(far, self.FILL * radius / np.tan(fov / 2.0))
                T = T.copy()
                T[:3, 3] = centre + (eye - centre) * (near / max(far, 1e-9))
            self.app.view_from(T, args[:3], fov)
        else:
            self.app.look_at(args[:3], args[3], args[4:])

    def framing(self, fr) -> tuple[str, np.ndarray] | None:
        """How frame_camera_on_frame frames `fr`: ("sensor", centre + the camera's 3x4 pose + the estimated
        target's radius, 0 before an estimate) or ("beside", centre + radius + direction); None when nothing in
        the frame has depth."""
        mask = fr.base_mask()
        estimated = not mask.any() and self.result is not None and len(self.result.target_cloud)
        if not mask.any() and not estimated:
            mask = self.prompt_region(fr)
        if estimated:
            pts = self.result.target_cloud
        else:
            if not mask.any():
                h, w = fr.depth.shape
                mask = np.zeros_like(mask)
                mask[h // 3: 2 * h // 3, w // 3: 2 * w // 3] = True
            pts = project_to_cloud(fr.depth, mask & np.isfinite(fr.depth) & (fr.depth > 0), fr.camera, fr.T_world_camera)
        if not len(pts):
            return None
        centre = np.median(pts, axis=0)
        if not fr.masks or not isinstance(self.frames, Dataset):  # a real frame: as its sensor saw it (once estimated,
            # nearer along the sensor's ray: the object small amid the whole bench was hard to judge)
            radius = float(np.percentile(np.linalg.norm(pts - centre, axis=1), 95)) if estimated else 0.0
            return "sensor", np.concatenate([centre, fr.T_world_camera[:3, :].ravel(), [radius]])
        radius = max(float(np.percentile(np.linalg.norm(pts - centre, axis=1), 95)), 0.02, self.base_radius())
        to_camera = fr.T_world_camera[:3, 3] - centre
        direction = se3.axis_angle_matrix([0.0, 0.0, 1.0], np.radians(35.0)) @ to_camera
        direction[2] = max(direction[2], 0.6 * np.linalg.norm(direction[:2]))  # from above the table
        return "beside", np.concatenate([centre, [1.3 * radius], direction])

    def base_radius(self) -> float:
        """Half the largest diameter among the inspected step's base parts (0 where unknown): a base mostly hidden
        shows a small patch, and framed on that patch alone the view closed in until the scene's points were discs
        the size of the objects (a newcomer could not tell the watering can among them)."""
        try:
            models, asm = self.inspect_models(), self.inspect_assembly()
            return 0.5 * max(models[b].diameter for b in asm.steps[self.app.state.inspect.step - 1].base)
        except (AposeError, KeyError, IndexError, TypeError, ValueError):
            return 0.0

    PROMPT_POINT_PX = 40  # a point prompt is framed with the pixels this far round it

    def prompt_region(self, fr) -> np.ndarray:
        """The pixels the typed prompt marks on `fr` (its box, or the square round its point), none without a usable
        one: before an estimate, a capture is framed on what the user pointed at, not on the image's middle."""
        out = np.zeros(fr.depth.shape, bool)
        prompt = typed_prompt(self.app.state.inspect)
        if prompt is None:
            return out
        box, point = prompt
        if box is None:
            r = self.PROMPT_POINT_PX
            box = (point[0] - r, point[1] - r, point[0] + r + 1, point[1] + r + 1)
        x0, y0, x1, y1 = (int(v) for v in box)
        out[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = True
        return out

    def on_prompt_changed(self) -> None:
        """A new prompt typed while Mask is 'prompt': the frame shows the result made with this prompt (the cache's),
        or none, never one made with the prompt before (a newcomer typed a malformed box and still saw the last
        box's pose, 'ok and confident', beside the refusal)."""
        if self.frame is None or self.app.state.inspect.mask_source != PROMPT_SOURCE:
            return
        key = self.cache_key(self.app.state.inspect.step, int(self.frame.im_id))
        cached = self.app.cache.get(key)
        result, score = cached if cached is not None else (None, None)
        refusal = self.app.state.inspect.refusals.get(key) if cached is None else None
        if result is not self.result or refusal != self.app.state.inspect.refusal:
            self.app.state.inspect.refusal = refusal
            self.result, self.score = result, score
            self.app.events.emit(Event.FRAME_CHANGED)

    def on_mask_source_chosen(self, source: str) -> None:
        if self.i_mask.value != source:
            self.i_mask.value = source  # its callback redraws the frame, with the new mask

    def inspect_assembly(self) -> Assembly:
        """The assembly under inspection (`state.inspect_assembly`)."""
        return self.app.state.inspect_assembly()

    def part_model(self):
        """The PartModel of the part the inspected step places (`state.part_model`)."""
        return self.app.state.part_model()

    def current_step(self) -> int:
        return int(str(self.i_step.value).split(".")[0])

    def job(self, step: int, ids: list[int]) -> "EstimateJob":
        """Everything an estimate depends on, read from the widgets now: a later click in any tab (another
        dataset, another preset) cannot change what a running estimate is computed with or cached under."""
        crop = None
        # the box is part of the mask
        if self.i_mask.value == "depth" and self.i_crop.value and "/inspect/crop" in self.app.nodes:
            g = self.app.nodes["/inspect/crop"]
            crop = (se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(g.wxyz)), np.asarray(g.position)),
                    np.asarray(self.i_crop_size.value, dtype=float) / 1000.0)
        asm = self.inspect_assembly()
        prompt = prompt_of(self.app.state.inspect.prompt_text) if self.i_mask.value == PROMPT_SOURCE else None
        path = self.frames_path
        if isinstance(self.frames, BopScene):  # its ground truth (masks, scores) follows the typed ids
            path += "#" + ",".join(f"{k}={v}" for k, v in sorted(self.frames.obj_of_part.items()))
        return EstimateJob(self.frames, path, asm, self.inspect_models(), step, tuple(ids),
                           self.i_preset.value, bool(self.i_upright.value), self.confined_mask(self.i_mask.value),
                           bool(self.i_prior.value), crop, prompt,
                           prompt is not None and self.app.state.inspect.align_depth)

    def confined_mask(self, source: str) -> str:
        """The Mask choice as the estimator is given it: a built-in source by name, a model file (any other
        choice) through the workspace again, here where it is used. The page can only choose among the
        options (the studio's screen of page input), and 'Use model' adds only confined files; this holds
        even if either ever changes."""
        if source in MASK_SOURCES or source == PROMPT_SOURCE:
            return source
        return str(self.app.workspace.resolve(source, "mask model"))

    def cache_key(self, step: int, im_id: int) -> tuple | None:
        try:
            return self.job(step, [im_id]).key(self.app.cache, im_id)
        except AposeError:  # e.g. mask "prompt" before a prompt is typed: nothing cached under it yet
            return None

    def load_frame(self, step: int, im_id: int, frames=None, asm: Assembly | None = None):
        """A frame of the opened data, or of `frames` (`state.load_frame`)."""
        return self.app.state.load_frame(step, im_id, frames, asm)

    def on_frame_changed(self) -> None:
        if self._syncing or self.frames is None:
            return
        step = self.current_step()
        if isinstance(self.frames, BopScene):
            truth = self.bop_truth(self.frames, step)
            self.offer_mask_sources(truth)
            if self.frames.obj_of_part and self._told_step != step and not truth:  # a step without its truth says so
                self._told_step = step
                self.tell_truth()
        if isinstance(self.frames, (Dataset, BopScene, Recording)):
            ids = self.frame_ids(step)
            self._syncing = True
            try:
                self.i_frame.max = max(len(ids) - 1, 1)
                self.i_frame.disabled = len(ids) <= 1
                self.i_frame.visible = True
                if self.i_frame.value > len(ids) - 1:
                    self.i_frame.value = 0
            finally:
                self._syncing = False
            im_id = ids[int(self.i_frame.value)]
        else:  # a capture is one frame, a live camera its newest: nothing to slide through
            self._syncing = True
            try:
                self.i_frame.value, self.i_frame.disabled = 0, True
                self.i_frame.visible = False  # (a slider from 0 to 1 over one image read as two frames)
            finally:
                self._syncing = False
            im_id = self.frames.last.im_id if isinstance(self.frames, LiveCamera) else 0
        self.app.state.inspect.step = step
        self.frame = self.load_frame(step, im_id)
        self.follow_prompt()
        key = self.cache_key(step, im_id)
        cached = self.app.cache.get(key)
        self.result, self.score = cached if cached is not None else (None, None)
        self.app.state.inspect.refusal = self.app.state.inspect.refusals.get(key) if cached is None else None
        self.app.events.emit(Event.FRAME_CHANGED)
        self.warm_in_background(step)

    def on_other_frame(self, client) -> None:
        """Another step or frame chosen: the refusals on screen were about the one shown before, and go."""
        if not self._syncing:
            self.app.close_refusals(client)
        self.on_frame_changed()
        if not self._syncing:  # each frame its own camera, its object elsewhere in view: framed on it
            self.frame_camera_on_frame(again=False)

    def image_key(self) -> tuple:
        """The image a prompt marks the base in: the frame on show (its data, file and number), or for a live
        camera or a recording the stream as a whole (the player and the live view prompt their newest frame)."""
        if isinstance(self.frames, (LiveCamera, Recording)):
            return ("stream", self.frames_path)
        return (self.frames_path, self.frame.source, int(self.frame.im_id))

    def follow_prompt(self) -> None:
        """A prompt marks the base in the image it was typed on: another image on show (other data opened, another
        frame or scene) shows the prompt typed there, or none, and Mask leaves 'prompt' for the truth's masks (or
        depth) where that image has none. Coming back brings the image's prompt back, and with it its cached
        estimate. (A newcomer's box typed on a capture was estimated on the next dataset's image, and the failure
        read as a wrong step.)"""
        ins = self.app.state.inspect
        key = self.image_key()
        if key == ins.prompt_image:
            return
        if ins.prompt_image is not None:
            if ins.prompt_text.strip():  # (with the Mask choice it was left with: estimated with it or not)
                ins.prompts[ins.prompt_image] = (ins.prompt_text, self.i_mask.value == PROMPT_SOURCE)
            else:
                ins.prompts.pop(ins.prompt_image, None)
        ins.prompt_image = key
        ins.prompt_text, prompting = ins.prompts.get(key, ("", False))
        if prompting != (self.i_mask.value == PROMPT_SOURCE) and (prompting or not ins.prompt_text.strip()):
            # back on an image prompted: Mask 'prompt' again, its estimate found in the cache and used by Estimate
            # frame (an outsider saw the box back beside Mask 'gt'); an image without one: its truth, or depth
            syncing, self._syncing = self._syncing, True
            try:
                self.i_mask.value = PROMPT_SOURCE if prompting else ("gt" if "gt" in self.i_mask.options else "depth")
            finally:
                self._syncing = syncing
            ins.mask_source = self.i_mask.value

    def frame_ids(self, step: int) -> list[int]:
        """The im_ids the Frame slider runs through: a dataset's step's frames, a BOP scene's or a recording's."""
        frames = self.frames
        if isinstance(frames, Dataset):
            return frames.image_ids(step)
        if isinstance(frames, BopScene):
            return frames.image_ids()
        if isinstance(frames, Recording):
            return list(range(len(frames)))
        return [0]

    def on_frame_played(self, im_id: int) -> None:
        """The Sequence folder's player showed frame `im_id`: the Frame slider follows (the frame, its result and
        the view are the player's), and so does the Prompt field: a frame of a dataset or BOP scene shows its own
        prompt, so that Estimate frame on the frame paused at never uses the box drawn on the first one."""
        self.follow_prompt()
        ids = self.frame_ids(self.current_step())
        if im_id in ids and self.i_frame.value != ids.index(im_id):
            self._syncing = True
            try:
                self.i_frame.value = ids.index(im_id)
            finally:
                self._syncing = False

    def warm_in_background(self, step: int) -> None:
        """Prepare the step's base for the estimator (its StepContext and the model's features: seconds, once
        per step) in a background thread as soon as the step is on show, so that the first Estimate costs only
        its own work. An estimate that starts meanwhile prepares what is not ready yet itself; the pieces are
        deterministic, so whichever thread fills a cache fills it with the same values."""
        if self._warming == (id(self.inspect_assembly()), step):
            return
        job = self.job(step, [])
        self._warming = (id(job.assembly), step)

        def warm():
            try:
                self.context(step, job.assembly, job.models).base.warm_up(job.params())
            except Exception as e:  # a part that does not load says so when estimated
                log.info("warming step %s up failed: %s", step, e)

        self._warm_thread = self.app.start_thread(warm, name=f"warm step {step}")

    def settle(self, timeout: float = 60.0) -> None:
        """Wait for the background preparation to finish: a process that exits while it runs inside Open3D
        is aborted by the C++ runtime ('terminate called without an active exception')."""
        if self._warm_thread is not None:
            self._warm_thread.join(timeout)

    def inspect_models(self) -> dict:
        """The inspected assembly's PartModels (`state.inspect_models`)."""
        return self.app.state.inspect_models()

    def context(self, step: int, asm: Assembly | None = None, models: dict | None = None) -> StepContext:
        """A step's prepared base (default: of the inspected assembly), kept while the assembly and its models
        are the same objects: the second estimate of a step costs only its own work (preparing a base takes
        seconds). Estimates running on a job's snapshot read the same cache."""
        asm = self.inspect_assembly() if asm is None else asm
        models = self.inspect_models() if models is None else models
        key = (id(asm), id(models), step)
        hit = self.contexts.get(key)
        if hit is None or hit[0] is not asm or hit[1] is not models:
            if len(self.contexts) >= 8:
                self.contexts.clear()
            hit = (asm, models, StepContext(asm, models, step))
            self.contexts[key] = hit
        return hit[2]

    def estimate(self, job: "EstimateJob", im_id: int):
        """Estimate one frame of `job` and cache it under the job's key (runs without the studio lock)."""
        ctx = self.context(job.step, job.assembly, job.models)
        frame = self.load_frame(job.step, im_id, job.frames, job.assembly)
        params = job.params()
        mask = None
        if job.crop is not None:
            keep = inspection.pixels_in_box(frame.depth, frame.camera, frame.T_world_camera, *job.crop)
            mask = depth_mask(frame.depth, frame.camera, keep=keep)
        if job.prompt is not None:
            masks = self.app.state.inspect.prompt_masks
            mask = prompted_mask(masks, frame, job.prompt, job.align, job.assembly.base_is_region(job.step))
            if job.align:  # the estimate on the depth the mask was found on
                frame = colour_aligned(masks, frame, job.prompt)[0]
        box = job.prompt[0] if job.prompt is not None else None
        result, score = estimate_and_score(frame, ctx, params, job.mask, job.prior, trace_iterations=True, mask=mask,
                                           box=box)
        self.app.cache.put(job.key(self.app.cache, im_id), (result, score))
        return result, score

    def show_crop(self) -> None:
        """The crop box: a gizmo with a wireframe box as its child, first placed on the base object's
        likely spot (the depth point at the image centre)."""
        for name in ("/inspect/crop/box",):
            if name in self.app.nodes:
                self.app.nodes.pop(name).remove()
        if not self.i_crop.value or self.frame is None:
            if "/inspect/crop" in self.app.nodes:
                self.app.nodes.pop("/inspect/crop").remove()
            return
        size = np.asarray(self.i_crop_size.value, dtype=float) / 1000.0
        g = self.app.nodes.get("/inspect/crop")
        if g is None:
            fr = self.frame
            h, w = fr.depth.shape
            win = fr.depth[h // 2 - 20:h // 2 + 20, w // 2 - 20:w // 2 + 20]
            z = float(np.median(win[np.isfinite(win) & (win > 0)])) if (np.isfinite(win) & (win > 0)).any() else 0.5
            centre = se3.transform_points(fr.T_world_camera, np.array([[0.0, 0.0, z]]))[0]
            g = self.app.node("/inspect/crop", self.app.ui.scene.add_transform_controls(
                "/inspect/crop", scale=float(size.max()), position=tuple(centre)))
            g.on_update(lambda e: self.app.guarded("Crop box")(lambda c: self.on_crop_drag(e))(e))
            self.show_crop_centre()

        box = trimesh.creation.box(size)
        self.app.node("/inspect/crop/box", self.app.ui.scene.add_mesh_simple(
            "/inspect/crop/box", box.vertices.astype(np.float32), box.faces.astype(np.uint32), color=(255, 170, 0),
            wireframe=True))

    def show_crop_centre(self) -> None:
        """The typed centre follows the box (a fresh input: see make_pose_fields on why not a written value)."""
        g = self.app.nodes.get("/inspect/crop")
        if g is None:
            return
        value = tuple(round(float(v) * 1000.0, 1) for v in g.position)
        if tuple(self.i_crop_centre.value) == value:
            return
        order = self.i_crop_centre.order
        self.i_crop_centre.remove()
        with self.estimate_folder:
            self.i_crop_centre = self.app.ui.gui.add_vector3(
                "Crop centre (mm)", value, step=1.0, order=order, **VECTOR_MM, hint="world frame; typed, dragged with the box's gizmo, or clicked")
        self.i_crop_centre.on_update(self.app.guarded("Crop box")(lambda c: self.on_crop_centre()))

    def on_crop_centre(self) -> None:
        """A typed centre moves the box there (and turns the box on)."""
        centre = np.asarray(self.i_crop_centre.value, dtype=float) / 1000.0
        if not np.isfinite(centre).all():
            raise AposeError("the crop centre needs three finite numbers (mm, world frame)")
        self.place_crop(centre)

    def place_crop(self, centre: np.ndarray) -> None:
        if self.frame is None:
            raise AposeError("open a dataset or capture first")
        if not self.i_crop.value:
            self.i_crop.value = True  # creates the box (show_crop)
        self.app.nodes["/inspect/crop"].position = tuple(float(v) for v in centre)
        self.show_crop_centre()

    def on_crop_drag(self, event) -> None:
        if event.phase == "end":
            self.show_crop_centre()

    def on_crop_around_click(self, client) -> None:
        """The next click in the 3D view (by this tab) centres the crop box on the scene point it hits."""
        self.app.next_pointer(client, "Crop around click", "click",
                          lambda e, c: self.crop_at_ray(e.ray_origin, e.ray_direction, c),
                          "click the base object in the 3D view")

    def crop_at_ray(self, origin, direction, client) -> None:
        hit = scene_point_at_ray(self.frame, origin, direction)
        self.place_crop(hit)
        self.app.notify(client, "Crop box", "centred at ({:.0f}, {:.0f}, {:.0f}) mm".format(*(hit * 1000)))

    def on_use_model(self, client) -> None:
        text = self.i_model.value.strip()
        if not text:
            raise AposeError("type the path of a model file (.pt) from `apose train-seg` into 'Mask model (.pt)'")
        path = check_mask_source(str(self.app.workspace.resolve(text, "mask model")), self.inspect_assembly())
        options = list(self.i_mask.options)
        if path not in options:
            self.i_mask.options = options + [path]
        self.i_mask.value = path
        self.app.notify(client, "Mask model", f"using {Path(path).name} for masks")

    def on_estimate(self, event) -> None:
        which = event.target.value
        self.app.guarded(which)(lambda c: self.run_estimation(which == "Estimate step", c))(event)

    def run_estimation(self, whole_step: bool, client) -> None:
        if self.frames is None:
            raise AposeError("open a dataset or capture first")
        if not self.app.busy.acquire(blocking=False):
            raise AposeError("an estimation is already running (or the Sequence player plays: press Pause); wait for it to finish")
        try:
            step = self.current_step()
            if whole_step and isinstance(self.frames, Recording):
                raise AposeError("a recording's frames are played, not estimated one by one: press Play in the Sequence "
                                 "folder (it tracks the base from frame to frame); Estimate frame estimates the frame on show")
            if whole_step and isinstance(self.frames, Dataset):
                ids = self.frames.image_ids(step)
            elif whole_step and isinstance(self.frames, BopScene):
                ids = self.frames.image_ids()
            else:
                ids = [self.frame.im_id]
            job = self.job(step, ids)  # the settings of this moment, whatever other tabs do meanwhile
            if len(ids) > 1 and job.mask == PROMPT_SOURCE:
                raise AposeError("a prompt marks the base in one frame, and it moves from frame to frame: use "
                                 "Estimate frame on each, or choose a Mask for the whole step (gt, box, depth or a model)")
        except BaseException:
            self.app.busy.release()
            raise
        self.app.lock.release()  # estimation is long: let other tabs edit meanwhile
        try:
            self.i_progress.visible = True
            self.i_progress.value = 0.0
            failed, unsure, t0 = [], [], time.perf_counter()
            for k, im_id in enumerate(ids):
                cached = self.app.cache.get(job.key(self.app.cache, im_id))
                result = cached[0] if cached is not None else self.estimate(job, im_id)[0]
                if not result.ok:
                    failed.append(f"frame {im_id}: {result.reason}")
                elif not result.confident:
                    unsure.append(f"frame {im_id}: {doubts(result)}")
                self.i_progress.value = 100.0 * (k + 1) / len(ids)
            dt = time.perf_counter() - t0
        except BaseException as e:
            self.app.lock.acquire()
            self.app.busy.release()
            self.i_progress.visible = False
            if isinstance(e, AposeError) and len(ids) == 1:  # the Result folder says why, beside the frame, not only
                # a notice that fades (a newcomer read "No estimate for this frame yet" after a refused box)
                if len(self.app.state.inspect.refusals) > 256:
                    self.app.state.inspect.refusals.clear()
                self.app.state.inspect.refusals[job.key(self.app.cache, ids[0])] = str(e)
            # what stays on screen is what is cached for these settings: never an older estimate that looks
            # like the answer to the prompt that just failed
            self.on_frame_changed()
            raise
        self.app.lock.acquire()
        self.app.busy.release()
        self.i_progress.visible = False
        self.on_frame_changed()
        self.frame_camera_on_frame(again=False)
        if len(ids) == 1 and unsure and self.advise(job):
            a = self.app.state.inspect.advice
            unsure[-1] += (f"; look again from where the orange frustum in the 3D view shows: from there about {a.pixels} "
                           f"pixels tell the placements apart (from here {a.pixels_now})")
        hint = []
        if (failed or unsure) and self.app.state.inspect.mask_source == PROMPT_SOURCE:
            # a prompt marks whatever the user chose: the base model fitted to another object says only 'ambiguous'
            # or 'poor fit' (a newcomer on the wrong step went to take another view instead of changing the step)
            step = self.app.state.inspect.step
            base = ", ".join(self.inspect_assembly().steps[step - 1].base)
            hint = [f"(step {step} registers {base}: if the prompt marks another object, choose that object's step in "
                    "Inspect step)"]
        if failed:
            self.app.notify(client, "Estimation failed", "\n".join(failed[:5] + hint), error=True)
        elif unsure:
            self.app.notify(client, "Estimated, not confident", "\n".join(unsure[:5] + hint), error=True)
        else:
            # a step's summary is a result to read: it stays (until the tab's next message), a frame's fades
            if len(ids) == 1:  # the verdict where the button was pressed: the Result folder is a screen further down
                self.app.notify(client, "Estimated", f"frame {ids[0]}: ok and confident ({dt:.1f} s)"
                                f"{self.truth_summary(job, ids)}")
            else:
                self.app.notify(client, "Estimated", f"{len(ids)} frame(s) in {dt:.1f} s{self.truth_summary(job, ids)}",
                                keep=True)

    def advise(self, job: "EstimateJob") -> bool:
        """For an ambiguous result on show: the camera from which its rival placements look most different
        (registration.next_view), into `state.inspect.advice` and drawn (RESULT_READY). True when advised."""
        ins = self.app.state.inspect
        r = ins.result
        if r is None or not r.ok or not r.ambiguous or ins.frame is None:
            return False
        ins.advice = next_view(r, self.context(job.step).base, [ins.frame.T_world_camera], ins.frame.camera)
        if ins.advice is None:
            return False
        self.app.events.emit(Event.RESULT_READY)
        return True

    def truth_summary(self, job: "EstimateJob", ids: list[int]) -> str:
        """Against the ground truth of a step's frames, where it has one: how many are right (MSSD under 10 %
        of the part's diameter, the paper's recall, modulo the base's exact symmetries as `apose eval` counts
        it) and their median MSSD; one frame's MSSD; '' without truth."""
        scores = [c[1] for c in (self.app.cache.get(job.key(self.app.cache, i)) for i in ids) if c is not None]
        mssd = [m for m in map(inspection.placement_mssd, scores) if m is not None]  # modulo exact symmetries
        if len(ids) == 1 and mssd:
            return f"; MSSD to the truth {mssd[0] * 1000:.2f} mm"
        if len(ids) < 2 or not mssd:
            return ""
        d = self.app.state.part_model().diameter
        right = sum(m < 0.1 * d for m in mssd)
        return (f"; against the truth: {right}/{len(ids)} right (MSSD < 10 % of the part's diameter), "
                f"median MSSD {float(np.median(mssd)) * 1000:.2f} mm")
