"""The Inspect tab's prompt: a 2D box or a click on the base object, the mask it gives drawn over the
RGB image, then the estimate with that mask (mask source "prompt")."""

from __future__ import annotations

import numpy as np

from .. import inspection, se3
from ..errors import AposeError

PROMPT_SOURCE = "prompt"


def parse_prompt(text: str) -> tuple[tuple | None, tuple | None]:
    """'x0,y0,x1,y1' -> (box, None); 'u,v' -> (None, point); AposeError otherwise."""
    from ..prompt import parse_box, parse_point

    n = len([t for t in text.split(",") if t.strip()])
    if n == 4:
        return parse_box(text), None
    if n == 2:
        return None, parse_point(text)
    raise AposeError(f"prompt {text!r}: type a box x0,y0,x1,y1 or a point u,v (pixels), or press 'Prompt at click'")


class PromptPanel:
    def __init__(self, app):
        self.app = app

    def build(self) -> None:
        gui = self.app.server.gui
        with gui.add_folder("Prompt (cluttered scenes)"):
            self.i_prompt = gui.add_text("Prompt (px)", "", hint="a box x0,y0,x1,y1 or a point u,v on the base object, in "
                                         "image pixels; then Mask: prompt")
            b = gui.add_button("Prompt at click", hint="then click the base object in the 3D view")
            b.on_click(self.app.guarded("Prompt at click")(self.on_prompt_at_click))
            b = gui.add_button("Show mask", hint="the mask the prompt gives, drawn over the RGB image")
            b.on_click(self.app.guarded("Show mask")(lambda c: self.show_mask(c)))

    def prompt(self) -> tuple[tuple | None, tuple | None]:
        text = self.i_prompt.value.strip()
        if not text:
            raise AposeError("Mask is 'prompt': type a box x0,y0,x1,y1 or a point u,v into 'Prompt (px)', or press "
                             "'Prompt at click'")
        return parse_prompt(text)

    def mask(self, frame, prompt=None) -> np.ndarray:
        from ..prompt import prompted_mask

        box, point = prompt if prompt is not None else self.prompt()
        return prompted_mask(frame.rgb, frame.depth, frame.camera, box=box, point=point).mask

    def show_mask(self, client) -> None:
        fr = self.app.inspect.frame
        if fr is None:
            raise AposeError("open a dataset or capture first")
        m = self.mask(fr)
        image = fr.rgb.copy()
        image[m] = (0.45 * image[m] + 0.55 * np.array([40, 220, 60])).astype(np.uint8)
        vs, us = np.nonzero(m)
        x0, y0, x1, y1 = inspection.crop_window(fr.rgb.shape[:2], np.stack([us, vs], axis=1)[:: max(1, len(us) // 500)])
        self.app.results.i_image.image = image if self.app.results.i_full.value else image[y0:y1, x0:x1]
        self.app.results.i_image.label = f"RGB: prompted mask (green), {int(m.sum())} pixels"
        self.app.notify(client, "Mask", f"{int(m.sum())} pixels; set Mask to 'prompt' and estimate")

    def on_prompt_at_click(self, client) -> None:
        if self.app.inspect.frame is None:
            raise AposeError("open a dataset or capture first")
        if client is None:
            raise AposeError("no browser to click in")

        def clicked(event) -> None:
            client.scene.remove_click_callback(clicked)
            self.app.guarded("Prompt at click")(lambda c: self.prompt_at_ray(event.ray_origin, event.ray_direction, c))(event)

        client.scene.on_click()(clicked)
        self.app.notify(client, "Prompt at click", "click the base object in the 3D view")

    def prompt_at_ray(self, origin, direction, client) -> None:
        """The scene point the click's ray hits, as a pixel of the frame: the point prompt."""
        fr = self.app.inspect.frame
        pts, _ = inspection.scene_cloud(fr.depth, fr.rgb, fr.camera, fr.T_world_camera)
        hit = inspection.point_on_ray(pts, np.asarray(origin, float), np.asarray(direction, float),
                                      max_offset=0.01 * float(np.median(fr.depth[fr.depth > 0])))
        if hit is None:
            raise AposeError("the click hit no depth point; click on the object itself")
        u, v = fr.camera.project(se3.transform_points(se3.inv(fr.T_world_camera), hit[None]))
        self.i_prompt.value = f"{int(round(float(u[0])))},{int(round(float(v[0])))}"
        self.app.inspect.i_mask.value = PROMPT_SOURCE
        self.show_mask(client)
