"""Rendered frames on their way to disk (`render.render_dataset`): images encoded in threads, frames
listed in the scene's JSON files in order once their images are on disk."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from apose_studio.assembly.model import StepView
from apose_studio.data.dataset import AnnotatedObject
from apose_studio.data.outdir import write_manifest
from apose_studio.synth.frame import RenderedFrame, RenderSettings, misregistration, noisy_depth


class FrameQueue:
    """Rendered frames on their way to disk: PNG encoding in two threads (it releases the GIL, so it
    overlaps the next frame's casting), frames recorded in the scene's JSON in order, once their images
    are on disk. An interrupt keeps every frame whose images made it."""

    def __init__(self, out, info: dict, settings: RenderSettings):
        self.out, self.info, self.settings = out, info, settings
        self.pool = ThreadPoolExecutor(2)
        self.pending: list = []  # (writer, future of the images, what to record once they are on disk)
        self.writer = None

    def submit(self, writer, im_id: int, fr: RenderedFrame, view: StepView, obj_ids: dict[str, int],
               placement: int) -> None:
        self.writer = writer
        annotated = [i for i, o in enumerate(fr.scene.objects) if o.part is not None]
        objects = [AnnotatedObject(obj_ids[fr.scene.objects[i].part], fr.scene.objects[i].T_world_obj,
                                   *fr.hits.object_stats(i)) for i in annotated]
        extra = {"T_world_base": fr.scene.T_world_base, "T_world_part": fr.scene.T_world_base @ view.T_base_part,
                 "T_world_camera": fr.T_world_camera, "placement": placement}
        if self.settings.misregistration_px:  # how far the depth image lies from the colour image (du, dv pixels)
            extra["depth_shift_px"] = misregistration(fr.noise_seed, self.settings.misregistration_px)
        fut = self.pool.submit(lambda: writer.write_images(im_id, fr.rgb, noisy_depth(fr, self.settings), objects))
        self.pending.append((writer, fut, (im_id, self.settings.camera, fr.T_world_camera, objects, extra)))
        self._settle(keep=4)

    def _settle(self, keep: int) -> None:
        """Record finished frames in order, keeping at most `keep` in flight."""
        while len(self.pending) > keep:
            w, fut, args = self.pending.pop(0)
            w.record(args[0], args[1], args[2], fut.result(), *args[3:])

    def checkpoint(self, writer) -> None:
        """Every frame so far on disk and listed (scene JSON files and the manifest)."""
        self._settle(keep=0)
        writer.flush()
        write_manifest(self.out, self.info)

    def close(self) -> None:
        try:
            for w, fut, args in self.pending:  # an interrupt: keep every frame whose images made it to disk
                try:
                    w.record(args[0], args[1], args[2], fut.result(), *args[3:])
                except Exception:
                    pass
            if self.writer is not None:
                self.writer.flush()
            write_manifest(self.out, self.info)
        finally:
            self.pool.shutdown(wait=True)
