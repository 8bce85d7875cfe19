"""The Inspect tab's prompt: a 2D box or a click on the base object, the mask it gives drawn over the
RGB image, then the estimate with that mask (mask source "prompt").

The prompt text and the masks made from prompts live in the studio's shared state (`state.inspect`):
the estimate and the RGB overlay use them through `prompt_of`, `prompted_mask` and `overlay_mask`.
Showing a mask chooses mask source "prompt" (MASK_SOURCE_CHOSEN) and redraws the overlay
(OVERLAY_CHANGED)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from apose_studio.errors import AposeError
from apose_studio.estimation import colour_registered
from apose_studio.masks.prompt import check_box, parse_box, parse_point
from apose_studio.masks.prompt import prompted_mask as segment
from apose_studio.studio import inspection
from apose_studio.studio.state import Event, InspectState
from apose_studio.studio.widgets import pixel_at_ray

PROMPT_SOURCE = "prompt"


def parse_prompt(text: str) -> tuple[tuple | None, tuple | None]:
    """'x0,y0,x1,y1' -> (box, None); 'u,v' -> (None, point); AposeError otherwise."""
    n = len([t for t in text.split(",") if t.strip()])
    if n == 4:
        return parse_box(text, "Prompt (px)"), None
    if n == 2:
        return None, parse_point(text, "Prompt (px)")
    raise AposeError(f"prompt {text[:60]!r}: type a box x0,y0,x1,y1 or a point u,v (pixels), or press 'Prompt at click'")


def prompt_of(text: str) -> tuple[tuple | None, tuple | None]:
    """The prompt typed into 'Prompt (px)' as (box, point); AposeError when there is none or it is malformed."""
    text = text.strip()
    if not text:
        raise AposeError("Mask is 'prompt': type a box x0,y0,x1,y1 or a point u,v into 'Prompt (px)', or press "
                         "'Prompt at click'")
    return parse_prompt(text)


def colour_aligned(masks: dict, frame, prompt: tuple):
    """(frame, (du, dv)): `frame` with its depth moved back onto the colour image around `prompt` when it lies
    shifted against it there (estimation.colour_registered), kept in `masks` beside the prompt's masks."""
    key = (frame.source, frame.im_id, frame.step, prompt, "depth onto colour")
    if key not in masks:
        if len(masks) > 32:
            masks.clear()
        box, point = prompt
        masks[key] = colour_registered(frame.rgb, frame.depth, box, point)
    depth, shift = masks[key]
    return (replace(frame, depth=depth) if shift != (0, 0) else frame), shift


def prompted_mask(masks: dict, frame, prompt: tuple, align: bool = False, region: bool = False) -> np.ndarray:
    """The mask `prompt` gives on `frame` (with `align`, on its depth moved onto the colour image first:
    colour_aligned; `region`: the step's base is a region of a larger part, masks.prompt.prompted_mask), kept in
    `masks` (by frame source, im_id, step, prompt, align and region) so that redrawing the overlay is instant
    and an estimate uses the mask on show."""
    key = (frame.source, frame.im_id, frame.step, prompt, align, region)
    if key not in masks:
        seen = colour_aligned(masks, frame, prompt)[0] if align else frame
        if len(masks) > 32:
            masks.clear()
        box, point = prompt
        masks[key] = segment(seen.rgb, seen.depth, seen.camera, box=box, point=point, region=region).mask
    return masks[key]


def uses_prompt(ins: InspectState) -> bool:
    """Whether the Mask is 'prompt' and a prompt is typed (usable or not)."""
    return ins.mask_source == PROMPT_SOURCE and bool(ins.prompt_text.strip())


def typed_prompt(ins: InspectState) -> tuple | None:
    """(box, point) typed into 'Prompt (px)' while Mask is 'prompt', None when there is none or it is malformed."""
    if not uses_prompt(ins):
        return None
    try:
        return prompt_of(ins.prompt_text)
    except AposeError:
        return None


def overlay_mask(ins: InspectState, frame, region: bool = False) -> np.ndarray | None:
    """The prompted mask to draw over the RGB image: with Mask 'prompt' and a usable prompt, else None."""
    prompt = typed_prompt(ins) if frame is not None else None
    if prompt is None:
        return None
    try:
        return prompted_mask(ins.prompt_masks, frame, prompt, ins.align_depth, region)
    except AposeError:
        return None


class PromptPanel:
    def __init__(self, app):
        self.app = app
        self._quiet = False
        app.events.on(Event.FRAME_CHANGED, self.show_prompt_of_image)
        app.events.on(Event.FRAME_PLAYED, lambda im_id: self.show_prompt_of_image())

    def show_prompt_of_image(self) -> None:
        """The Prompt field shows the prompt of the image on show (`state.inspect.prompt_text`, which the Inspect
        panel keeps per image), without acting on it as a prompt typed."""
        text = self.app.state.inspect.prompt_text
        if getattr(self, "i_prompt", None) is not None and self.i_prompt.value != text:
            self._quiet = True
            try:
                self.i_prompt.value = text
            finally:
                self._quiet = False

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Prompt (cluttered scenes)"):
            self.i_prompt = gui.add_text("Prompt (px)", "", hint="a box x0,y0,x1,y1 or a point u,v on the base object, in "
                                         "image pixels; then Mask: prompt")
            self.i_prompt.on_update(self.app.guarded("Prompt")(lambda c: self.on_prompt_typed()))
            b = gui.add_button("Prompt at click", hint="then click the base object in the 3D view")
            b.on_click(self.app.guarded("Prompt at click")(self.on_prompt_at_click))
            b = gui.add_button("Drag a box", hint="then drag a rectangle around the base object in the 3D view")
            b.on_click(self.app.guarded("Drag a box")(self.on_drag_box))
            b = gui.add_button("Show mask", hint="the mask the prompt gives, drawn over the RGB image")
            b.on_click(self.app.guarded("Show mask")(lambda c: self.show_mask(c)))
            self.i_align = gui.add_checkbox("Align depth to colour", False, hint="a Kinect v1's depth is often "
                                            "registered a few pixels off its colour image: find the shift around the "
                                            "prompt and move the depth back before the mask and the estimate")
            self.i_align.on_update(self.app.guarded("Align depth to colour")(lambda c: self.on_align(c)))

    def on_prompt_typed(self) -> None:
        """A prompt typed (and sent with Enter) is the one to estimate with: Mask switches to prompt. A
        malformed one says what is wrong and leaves the Mask choice alone."""
        if self._quiet:  # (the field following the image on show: not typed)
            return
        changed = self.app.state.inspect.prompt_text != self.i_prompt.value
        self.app.state.inspect.prompt_text = self.i_prompt.value
        if changed:
            self.app.events.emit(Event.PROMPT_CHANGED)  # before any refusal below: the old prompt's result goes too
        if not self.i_prompt.value.strip():
            return
        box, _ = prompt_of(self.i_prompt.value)  # raises with the expected form
        fr = self.app.state.inspect.frame
        if box is not None and fr is not None:
            check_box(box, fr.depth.shape)  # an inverted box (x,y,w,h typed) or one off the image: said now, not at Estimate
        if self.app.state.inspect.mask_source != PROMPT_SOURCE:
            self.app.events.emit(Event.MASK_SOURCE_CHOSEN, source=PROMPT_SOURCE)
        self.app.events.emit(Event.FRAMING_ASKED)  # the view turns to what the prompt marks (a newcomer's stayed put)

    def prompt(self) -> tuple[tuple | None, tuple | None]:
        """The typed prompt as (box, point)."""
        return prompt_of(self.i_prompt.value)

    def mask(self, frame, prompt=None) -> np.ndarray:
        """The mask of `prompt` (default: the typed one) on `frame`."""
        ins = self.app.state.inspect
        return prompted_mask(ins.prompt_masks, frame, prompt if prompt is not None else self.prompt(), ins.align_depth,
                             self.app.state.inspect_assembly().base_is_region(ins.step))

    def on_align(self, client) -> None:
        """Align depth to colour ticked or unticked: the mask on show and the next estimate follow it."""
        self.app.state.inspect.align_depth = bool(self.i_align.value)
        if self.app.state.inspect.frame is not None and uses_prompt(self.app.state.inspect):
            self.show_mask(client)

    def show_mask(self, client) -> None:
        """Compute the prompt's mask (errors say what is wrong with the prompt) and draw it over the RGB."""
        fr = self.app.state.inspect.frame
        if fr is None:
            raise AposeError("open a dataset or capture first")
        m = self.mask(fr)
        if self.app.state.inspect.mask_source != PROMPT_SOURCE:
            self.app.events.emit(Event.MASK_SOURCE_CHOSEN, source=PROMPT_SOURCE)  # the frame is redrawn, with the mask
        self.app.state.inspect.mask_asked = True  # (after any redraw above: it shows the prompt's mask, not the estimate's)
        self.app.events.emit(Event.OVERLAY_CHANGED)
        moved = ""
        if self.app.state.inspect.align_depth:
            du, dv = colour_aligned(self.app.state.inspect.prompt_masks, fr, self.prompt())[1]
            moved = (f"; the depth lay {du:+d}, {dv:+d} px (right, down) off the colour image here, moved back"
                     if (du, dv) != (0, 0) else "; the depth lies on the colour image here (no shift found)")
        self.app.notify(client, "Mask", f"{int(m.sum())} pixels from the prompt{moved}; estimate with it (Mask: prompt)")

    def on_prompt_at_click(self, client) -> None:
        """The next click in the 3D view (by this tab) becomes the point prompt."""
        self.app.next_pointer(client, "Prompt at click", "click",
                              lambda e, c: self.prompt_at_ray(e.ray_origin, e.ray_direction, c),
                              "click the base object in the 3D view")

    def on_drag_box(self, client) -> None:
        """The next rectangle dragged in the 3D view (by this tab) becomes the box prompt."""
        def dragged(event, c) -> None:
            box = inspection.frame_box_from_drag(self.app.state.inspect.frame, event, "the object")
            self.i_prompt.value = ",".join(map(str, box))
            self.show_mask(c)

        self.app.next_pointer(client, "Drag a box", "rect", dragged,
                              "drag a rectangle around the base object in the 3D view")

    def prompt_at_ray(self, origin, direction, client) -> None:
        """The scene point the click's ray hits, as a pixel of the frame: the point prompt."""
        self.i_prompt.value = pixel_at_ray(self.app.state.inspect.frame, origin, direction)
        self.show_mask(client)
