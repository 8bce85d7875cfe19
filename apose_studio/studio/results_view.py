"""The Inspect tab's Registration replay, Result and Layers folders, and the frame in the 3D view: clouds,
boxes (estimate, truth, alternatives) in their legend colours with labels, the ghost part, the RGB
overlay cropped around the object, the pose as numbers and JSON.

It draws what the studio's shared state holds (`state.inspect`: frame, estimate, score, prompt) on
FRAME_CHANGED and RESULT_READY, and redraws the overlay on OVERLAY_CHANGED."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from apose_studio.assembly.mesh import base_mesh
from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.robot.grasping import gripper_mesh
from apose_studio.studio import inspection
from apose_studio.studio.prompt_panel import overlay_mask, typed_prompt, uses_prompt
from apose_studio.studio.state import Event
from apose_studio.studio.viser_adapter import scene_serializer
from apose_studio.studio.widgets import LAYERS, SHARP_EDGE_DEG, esc, legend_html, pos, send_download, shaded, wxyz

log = logging.getLogger(__name__)

REPLAY_SECONDS_PER_STAGE = 0.4  # in an exported replay page
REPLAY_HOLD_S = 2.0  # ... and how long it holds the final pose before it loops
SCENE_UNDER_ESTIMATE = 0.4  # the scene cloud's discs shrink to this share of a pixel's footprint under an estimate


def inject_caption(page: str, caption_html: str) -> str:
    """`page` (an HTML document) with `caption_html` in a box over its top-right corner (the playback controls
    are at the bottom)."""
    box = ("<div id='apose-caption' style='position:fixed;right:12px;top:12px;z-index:1000;max-width:460px;"
           "background:rgba(255,255,255,0.92);color:#222;padding:8px 10px;border-radius:6px;"
           f"font:13px/1.4 sans-serif;box-shadow:0 1px 4px rgba(0,0,0,0.3)'>{caption_html}</div>")
    end = page.rindex("</body>")
    return page[:end] + box + page[end:]


class ResultsView:
    def __init__(self, app):
        self.app = app
        self._syncing = False
        self.stages: list = []
        self._seen_from_sensor = None  # the capture whose camera layer was turned off (its view is the sensor's)
        self._base_mesh: tuple = (None, None)  # ((assembly identity, step), its base mesh)
        self._ghost: tuple = (None, None)  # (the part's mesh, widgets.shaded of it): the ghost drawn at the estimate
        self._gripper: tuple = (None, None)  # ((grasp width, gripper), (vertices, faces)): the gripper drawn at the grasp
        self._drawn_frame: tuple | None = None  # what identifies the frame whose camera and scene cloud are drawn
        self._scene_footprint = 0.001  # a pixel's footprint at the drawn frame's depth (metres; draw_scene)
        self._meshes_drawn: dict = {}  # node name -> the mesh it shows (posed_mesh)
        self._source_of: list | None = None  # the replay whose source cloud the "/inspect/source" node holds
        self._label_layers: dict[str, str | None] = {}  # label node -> the layer of what it names (label_layer)
        app.events.on(Event.FRAME_CHANGED, self.draw_frame)
        app.events.on(Event.RESULT_READY, self.draw_frame)
        app.events.on(Event.OVERLAY_CHANGED, self.draw_overlay)

    def build(self) -> None:
        gui = self.app.ui.gui
        with gui.add_folder("Result"):  # first: what the user looks for after Estimate
            self.i_legend = gui.add_html(legend_html())
            self.i_metrics = gui.add_markdown("")
            self.i_pose = gui.add_markdown("")
            b = gui.add_button("Download pose (JSON)", hint="T_world_part, T_camera_part and T_world_base of the estimate")
            b.on_click(self.app.guarded("Download pose")(self.on_download_pose))
            b = gui.add_button("Export replay (HTML)", hint="this view and the registration replay as one page that any "
                               "browser opens without the studio or a network")
            b.on_click(self.app.guarded("Export replay")(self.on_export_replay))
            self.i_image = gui.add_image(np.zeros((48, 64, 3), np.uint8), label="RGB")
            self.i_full = gui.add_checkbox("Full image", False, hint="show the whole RGB image instead of the part around the object")
            self.i_full.on_update(self.app.guarded("Full image")(lambda c: self.draw_overlay()))
        with gui.add_folder("Registration replay"):
            self.i_stage = gui.add_slider("Stage", 1, 2, 1, 1, disabled=True)  # 1..n, as the stage text counts
            self.i_stage.on_update(self.app.guarded("Stage")(lambda c: self.show_stage()))
            b = gui.add_button("Play registration")
            b.on_click(self.app.guarded("Play registration")(self.on_play_registration))
            self.i_stage_md = gui.add_markdown("")
        with gui.add_folder("Layers", expand_by_default=False):
            self.layers = {k: gui.add_checkbox(k, True) for k in LAYERS}
            for w in self.layers.values():
                w.on_update(self.app.guarded("Layers")(lambda c: self.apply_layers()))

    def draw_frame(self) -> None:
        """The frame and its estimate in the 3D view (each thing in its legend colour, labelled) and the
        RGB overlay in the panel."""
        fr = self.app.state.inspect.frame
        self.app.state.inspect.mask_asked = False  # a new frame, prompt or estimate: the RGB shows the estimate's mask
        scene = self.app.ui.scene
        part_model = self.app.state.part_model()
        Tc = fr.T_world_camera
        drawn = (fr.source, int(fr.im_id), Tc.tobytes(), fr.depth.shape, float(np.sum(fr.depth[::7, ::7], dtype=np.float64)))
        if drawn != self._drawn_frame or not {"/inspect/camera", "/inspect/scene"} <= set(self.app.nodes):
            # the frame itself (its camera and scene cloud) is sent only when it changed, not with every estimate of
            # it: the browser re-decodes and re-draws every node it is sent (benchmarks/studio_browser.py)
            self._drawn_frame = drawn
            self.draw_scene(fr)
        for name in [n for n in self.app.nodes if n.startswith(("/inspect/box_", "/inspect/label_"))] + [
                "/inspect/target", "/inspect/source"]:
            if name in self.app.nodes:
                self.app.nodes.pop(name).remove()
        r = self.app.state.inspect.result
        corners = part_model.box_corners()
        d = part_model.diameter
        labels = []
        if fr.T_world_part is not None:  # truth: amber, dashed, a little outside so it never z-fights the estimate
            seg = inspection.dashed(inspection.box_segments(inspection.inflate(corners, 0.03), fr.T_world_part))
            self.app.node("/inspect/box_gt", scene.add_line_segments("/inspect/box_gt", seg.astype(np.float32), inspection.AMBER,
                                                                  thickness=4.0, thickness_units="screen"))
            labels.append(("truth", se3.transform_points(fr.T_world_part, corners).min(axis=0), "top-right"))
        if r is not None and r.ok:
            seg = inspection.box_segments(corners, np.eye(4))  # in the part's frame: the replay moves it with its stage
            self.app.node("/inspect/box_est", scene.add_line_segments("/inspect/box_est", seg.astype(np.float32), inspection.GREEN,
                                                                   thickness=3.0, thickness_units="screen",
                                                                   wxyz=wxyz(r.T_world_part), position=pos(r.T_world_part)))
            labels.append(("estimate", se3.transform_points(r.T_world_part, corners).max(axis=0), "bottom-left"))
            alts = [c.T_world_part for c in r.alternatives]
            if alts:
                seg = np.concatenate([inspection.box_segments(corners, T) for T in alts])
                self.app.node("/inspect/box_alt", scene.add_line_segments("/inspect/box_alt", seg.astype(np.float32),
                                                                       inspection.MAGENTA, thickness=2.0, thickness_units="screen"))
                labels.append(("alternative", se3.transform_points(alts[0], corners).max(axis=0), "bottom-left"))
            base = self.base_mesh()  # the base object's model where the estimate puts it: does it fit the cloud?
            if self._ghost[0] is not part_model.mesh:  # shaded once per part, not on every frame drawn
                self._ghost = (part_model.mesh, shaded(part_model.mesh))
            self.posed_mesh("/inspect/base_est", base, r.T_world_base, lambda: self.app.ui.scene.add_line_segments(
                "/inspect/base_est", inspection.feature_edges(base, SHARP_EDGE_DEG).astype(np.float32), inspection.GREEN, thickness=1.5,
                thickness_units="screen"))
            self.posed_mesh("/inspect/ghost", self._ghost[1], r.T_world_part, lambda: self.app.ui.scene.add_mesh_simple(
                "/inspect/ghost", *self._ghost[1], color=inspection.GREEN, opacity=0.45))
            grasp = self.draw_gripper(r.T_world_part)
            if grasp is not None:
                labels.append(("place", (r.T_world_part @ grasp.T_part_gripper)[:3, 3], "top-left"))
        else:
            for name in ("/inspect/base_est", "/inspect/ghost", "/inspect/gripper"):
                if name in self.app.nodes:
                    self.app.nodes.pop(name).remove()
        labels += self.draw_robot(fr)
        scene_node, size = self.app.nodes.get("/inspect/scene"), self.scene_point_size()
        if scene_node is not None and scene_node.point_size != size:  # (a small message, not the cloud again)
            scene_node.point_size = size
        if r is not None and len(r.target_cloud):
            tgt = inspection.thin(r.target_cloud, 20000).astype(np.float32)
            self.app.node("/inspect/target", scene.add_point_cloud("/inspect/target", tgt, inspection.RED, point_size=d / 120,
                                                                point_shape="circle", precision="float32"))  # float16
            # (viser's default) rounds positions to 0.25-0.5 mm at half a metre: as much as the fits it shows
            # at the cloud's foot, hanging below it: at its top it sat on the estimate's label (the box's top corner)
            labels.append(("target cloud", tgt[np.argmin(tgt[:, 2])], "top-right"))
        labels = on_truth(labels, self.app.state.inspect.score, d)
        # the legend names what is drawn: the labels' things and the layers with a node (their names are the legend's)
        self.i_legend.content = legend_html({text for text, _, _ in labels} |
                                            {layer for node, layer in NODE_LAYERS.items() if node in self.app.nodes} |
                                            ({"source cloud"} if r is not None and r.ok else set()))  # (drawn below)
        self._label_layers = {}
        for k, (text, where, anchor) in enumerate(labels):
            name = f"/inspect/label_{k}"
            self._label_layers[name] = label_layer(text)
            self.app.node(name, scene.add_label(name, text, position=tuple(float(v) for v in where), anchor=anchor,
                                             font_screen_scale=1.2))
        self.stages = inspection.replay(r) if (r is not None and r.ok) else []
        self._syncing = True
        try:
            self.i_stage.max = max(len(self.stages), 2)
            self.i_stage.value = max(len(self.stages), 1)
            self.i_stage.disabled = len(self.stages) < 2
            if self.i_stage.visible != (len(self.stages) >= 2):  # no estimate, no stages: no slider (it read 1..2)
                self.i_stage.visible = len(self.stages) >= 2
        finally:
            self._syncing = False
        self.show_stage()
        self.i_metrics.content = inspection.metrics_markdown(self.app.state.inspect.score, r, self.app.state.inspect.refusal)
        self.i_pose.content = inspection.pose_markdown(inspection.pose_report(r, Tc)) if (r is not None and r.ok) else ""
        self.draw_overlay()
        self.apply_layers()

    def draw_scene(self, fr) -> None:
        """The frame's camera (its frustum, with the RGB image) and its scene cloud, coloured by the image."""
        scene, cam, Tc = self.app.ui.scene, fr.camera, fr.T_world_camera
        small = fr.rgb[::2, ::2] if fr.rgb.shape[1] > 400 else fr.rgb
        fov = 2.0 * np.arctan2(cam.height / 2.0, cam.fy)
        self.app.node("/inspect/camera", scene.add_camera_frustum("/inspect/camera", fov=float(fov), aspect=cam.width / cam.height,
                                                               scale=0.03, image=small, format="jpeg", jpeg_quality=80,
                                                               wxyz=wxyz(Tc), position=pos(Tc), color=(60, 60, 60),
                                                               thickness=1.5, thickness_units="screen"))  # viser's
        # default is 2 cm thick in the world: on a 3 cm frustum, a black slab
        if not fr.masks and self._seen_from_sensor != fr.source:  # a capture is seen from its sensor: its own
            self._seen_from_sensor = fr.source  # frustum would sit at the eye and hide the scene (tick it back in Layers)
            self.layers["camera"].value = False
        pts, cols = inspection.scene_cloud(fr.depth, fr.rgb, cam, Tc)
        stride = max(1, int(np.ceil(np.sqrt(fr.depth.size / 60000))))
        # about one pixel's footprint at the scene's depth: dense, but never blobs that hide the boxes
        footprint = 0.5 * float(np.median(se3.transform_points(se3.inv(Tc), pts)[:, 2])) / cam.fx * stride if len(pts) else 0.001
        self._scene_footprint = footprint
        self.app.node("/inspect/scene", scene.add_point_cloud("/inspect/scene", pts, cols, point_size=self.scene_point_size(),
                                                           point_shape="circle", point_shading="flat"))  # flat
        # discs read as a surface; the default shading draws every point as a ball

    def scene_point_size(self) -> float:
        """The scene cloud's disc size: a pixel's footprint, or SCENE_UNDER_ESTIMATE of it while an estimate is drawn,
        whose outline and box lie on the very surface the discs show: the view closes in on the estimate and the full
        discs hid the base's outline and box (a newcomer saw the fit only after unticking the scene cloud)."""
        r = self.app.state.inspect.result
        return self._scene_footprint * (SCENE_UNDER_ESTIMATE if r is not None and r.ok else 1.0)

    def draw_gripper(self, T_world_part: np.ndarray):
        """The gripper holding the inspected step's part at T_world_part by its first grasp (the assembly file's
        `grasps`): where the robot's gripper goes to place it. Returns that grasp, or None (none drawn)."""
        asm = self.app.state.inspect_assembly()
        part = asm.parts.get(asm.steps[self.app.state.inspect.step - 1].part)
        if part is None or not part.grasps:
            if "/inspect/gripper" in self.app.nodes:
                self.app.nodes.pop("/inspect/gripper").remove()
            return None
        g = part.grasps[0]
        self.posed_gripper("/inspect/gripper", g, T_world_part @ g.T_part_gripper)
        return g

    def posed_gripper(self, name: str, grasp, T_world_gripper: np.ndarray, opacity: float = 1.0) -> None:
        """Node `name`: the assembly's gripper opened to `grasp`'s width at T_world_gripper (its mesh made once
        per width and gripper)."""
        gripper = self.app.state.inspect_assembly().gripper
        if self._gripper[0] != (grasp.width, gripper):
            m = gripper_mesh(grasp.width, gripper)
            self._gripper = ((grasp.width, gripper), (np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)))
        mesh = self._gripper[1]
        self.posed_mesh(name, mesh, T_world_gripper, lambda: self.app.ui.scene.add_mesh_simple(
            name, *mesh, color=inspection.GRIPPER, flat_shading=True, opacity=opacity))

    def draw_robot(self, fr) -> list[tuple]:
        """What the robot does about the step's part, in the world: the gripper (by the part's first grasp) at the
        pre-place where the step has an approach, and at the pick where the Robot folder found the loose part;
        the robot base's axes where it has a hand-eye calibration. Returns their labels."""
        ins, scene = self.app.state.inspect, self.app.ui.scene
        asm = self.app.state.inspect_assembly()
        step = asm.steps[ins.step - 1]
        part = asm.parts.get(step.part)
        grasp = part.grasps[0] if part is not None and part.grasps else None
        r, pick = ins.result, ins.pick()[1]
        poses = {}
        if grasp is not None and r is not None and r.ok and step.approach is not None:
            poses["/inspect/gripper_preplace"] = step.approach.start(r.T_world_part, r.T_world_base) @ grasp.T_part_gripper
        if grasp is not None and pick is not None and pick.ok:  # the loose part's estimate: its base is the part
            poses["/inspect/gripper_pick"] = pick.T_world_base @ grasp.T_part_gripper
        labels = []
        for name in ("/inspect/gripper_preplace", "/inspect/gripper_pick"):
            if name not in poses:
                if name in self.app.nodes:
                    self.app.nodes.pop(name).remove()
                continue
            # the approach's start: fainter, as in the Assembly tab
            self.posed_gripper(name, grasp, poses[name], 0.35 if name.endswith("preplace") else 1.0)
            labels.append(("pre-place" if name.endswith("preplace") else "pick", poses[name][:3, 3], "top-left"))
        T_world_robot = inspection.T_world_robot(ins)
        if T_world_robot is None:
            if "/inspect/robot" in self.app.nodes:
                self.app.nodes.pop("/inspect/robot").remove()
        else:
            length = max(0.1, 1.5 * self.app.state.part_model().diameter)
            self.app.node("/inspect/robot", scene.add_frame("/inspect/robot", axes_length=length, axes_radius=length / 40,
                                                         wxyz=wxyz(T_world_robot), position=pos(T_world_robot)))
            labels.append((f"robot base ({ins.hand_eye.robot_frame})", T_world_robot[:3, 3], "top-left"))
        return labels

    def posed_mesh(self, name: str, mesh, T_world_mesh: np.ndarray, make) -> None:
        """Node `name` showing `mesh` at T_world_mesh: the node already showing that mesh is moved (a pose is a
        few bytes; the mesh, sent again, is decoded and uploaded again), else `make()` draws it anew."""
        h = self.app.nodes.get(name)
        if h is None or self._meshes_drawn.get(name) is not mesh:
            if h is not None:
                self.app.nodes.pop(name).remove()
            h = self.app.node(name, make())
            self._meshes_drawn[name] = mesh
        h.wxyz, h.position = wxyz(T_world_mesh), pos(T_world_mesh)

    def base_mesh(self):
        """The inspected step's base object as one mesh (frame of base[0]), kept per assembly and step."""
        asm, step = self.app.state.inspect_assembly(), self.app.state.inspect.step
        key = (id(asm), step)
        if self._base_mesh[0] != key:
            self._base_mesh = (key, base_mesh(self.app.state.inspect_models(), asm.step_view(step)))
        return self._base_mesh[1]

    def draw_overlay(self) -> None:
        """The RGB image cropped around the object (unless 'Full image' is ticked) and enlarged to be read at
        pixel level: the mask as a cyan outline, the base's model outline where the estimate puts it (green)
        and where the truth does (amber), and the placed part's boxes."""
        fr, r = self.app.state.inspect.frame, self.app.state.inspect.result
        if fr is None:
            return
        corners = self.app.state.part_model().box_corners()
        boxes = []  # earlier boxes are drawn thicker: truth under estimate
        if fr.T_world_part is not None:
            boxes.append((fr.T_world_part, inspection.AMBER))
        if r is not None and r.ok:
            boxes.append((r.T_world_part, inspection.GREEN))
            boxes += [(c.T_world_part, inspection.MAGENTA) for c in r.alternatives]
        image = inspection.draw_boxes(fr.rgb, fr.camera, fr.T_world_camera, corners, boxes)
        ins = self.app.state.inspect
        if ins.mask_asked and uses_prompt(ins):  # Show mask: the prompt's own mask, even beside an estimate
            prompted, what = overlay_mask(ins, fr, self.app.state.inspect_assembly().base_is_region(ins.step)), "prompted mask (Show mask)"
        elif r is not None and r.ok and r.model_mask is not None and r.tracked:  # a played frame: no prompt of its own
            prompted, what = r.model_mask, "the tracked model's mask: where the depth agrees with it"
        elif r is not None and r.ok and r.model_mask is not None and uses_prompt(ins):  # (the prompt not segmented again)
            prompted, what = r.model_mask, "the estimate's mask: what the model shows at the pose"
        else:
            prompted, what = overlay_mask(ins, fr, self.app.state.inspect_assembly().base_is_region(ins.step)), "prompted mask"
        outlines = []  # the base's model: truth under estimate
        if fr.T_world_base is not None:
            outlines.append((fr.T_world_base, inspection.AMBER))
        if r is not None and r.ok and r.T_world_base is not None:
            outlines.append((r.T_world_base, inspection.GREEN))
        if prompted is not None:  # the prompt's mask (or the estimate's) as its outline, under the model's
            inspection.draw_outline(image, prompted, inspection.CYAN, inset=1 if outlines else 0)
        typed = typed_prompt(ins)
        if typed is not None:  # the box (or point) typed: what the mask was asked for
            inspection.draw_prompt(image, *typed)
        shapes = []  # the base's silhouettes: the crop shows all of them
        for T, colour in outlines:
            shapes.append(inspection.silhouette(self.base_mesh(), T, fr.T_world_camera, fr.camera))
            inspection.draw_outline(image, shapes[-1], colour)
        if not self.i_full.value:
            uv = np.concatenate([inspection.project_points(se3.transform_points(T, corners), fr.T_world_camera, fr.camera)[0]
                                 for T, _ in boxes]) if boxes else np.zeros((0, 2))
            if not boxes:  # no boxes: around the base object, if its mask is known
                vs, us = np.nonzero(prompted if prompted is not None else fr.base_mask())
                uv = np.stack([us, vs], axis=1)[:: max(1, len(us) // 500)]
            if typed is not None and typed[0] is not None:  # the typed box is in the crop
                x0, y0, x1, y1 = typed[0]
                uv = np.concatenate([uv, np.array([[x0, y0], [x1, y1]], float)])
            for shape in shapes:
                vs, us = np.nonzero(shape)
                uv = np.concatenate([uv, np.stack([us, vs], axis=1)[:: max(1, len(us) // 500)]])
            x0, y0, x1, y1 = inspection.crop_window(fr.rgb.shape[:2], uv)
            image = image[y0:y1, x0:x1]
        self.i_image.image = inspection.enlarge(image)
        drawn = (["estimate (green: the base's outline, the part's box)"] if r is not None and r.ok else []) + (
            ["truth (amber)"] if fr.T_world_part is not None else [])  # (no estimate named where none is drawn)
        self.i_image.label = ("RGB: " + ", ".join(drawn) if drawn else "RGB") + (
            f"; {what} (cyan outline), {int(prompted.sum())} pixels" if prompted is not None else "") + (
            "; the typed prompt (white)" if typed is not None else "")

    def on_download_pose(self, client) -> None:
        ins = self.app.state.inspect
        r = ins.result
        if r is None or not r.ok or ins.frame is None:
            raise AposeError("no estimate on this frame yet: press Estimate frame first")
        report = inspection.pose_report(r, ins.frame.T_world_camera)
        report.update({"source": ins.frames_path, "step": ins.step, "frame": int(ins.frame.im_id),
                       "units": "metres (matrices), mm (translation_mm)"})
        send_download(client, f"pose_step{ins.step}_frame{ins.frame.im_id}.json", json.dumps(report, indent=1).encode("utf-8"))

    def on_export_replay(self, client) -> None:
        if client is None:
            raise AposeError("no browser to send the download to")
        ins = self.app.state.inspect
        page = self.replay_html()
        send_download(client, f"replay_step{ins.step}_frame{ins.frame.im_id}.html", page.encode("utf-8"))

    def replay_html(self) -> str:
        """The Inspect view of this frame and its estimate as one standalone HTML page: viser's scene
        serializer writes its own client and the scene into one file, which opens from disk with no server and
        no network request (the studio draws with no environment map, which the client would fetch). The page
        shows the scene as drawn now, then replays the registration, REPLAY_SECONDS_PER_STAGE per stage,
        ending on the final pose (viser's playback controls pause and scrub it), with the legend, the step
        and frame and the result's numbers over the view."""
        ins = self.app.state.inspect
        r = ins.result
        if r is None or not r.ok or not self.stages:
            raise AposeError("estimate this frame first (Estimate frame); then its replay can be exported")
        if self.app.current_view != "Inspect":
            self.app.show_view("Inspect")
        self.set_stage(0)  # the page starts where the registration did
        label = self.app.ui.scene.add_label("/inspect/stage_label", self.stage_text(0), position=self.label_at(),
                                               anchor="bottom-left", font_screen_scale=1.2)
        serializer = scene_serializer(self.app.ui)  # from the scene as drawn now (this tab's)
        try:
            self.app.events.emit(Event.FRAMING_ASKED)  # the page opens looking at the object
            for k in range(1, len(self.stages)):
                serializer.insert_sleep(REPLAY_SECONDS_PER_STAGE)
                self.set_stage(k)
                label.text = self.stage_text(k)
            serializer.insert_sleep(REPLAY_HOLD_S)  # the final pose stays a while before the page loops
        finally:
            page = serializer.as_html()  # (also stops the recording when the replay failed)
            label.remove()
        return inject_caption(page, self.caption())

    def stage_text(self, k: int, bold: bool = False) -> str:
        """Replay stage `k` in words, its name in markdown bold for the panel (`bold`), plain for a 3D label."""
        s = self.stages[k]
        name = f"**{s.name}**" if bold else s.name
        return f"{name} ({k + 1}/{len(self.stages)}): fitness {s.fitness:.3f}, inlier RMSE {s.inlier_rmse * 1000:.2f} mm"

    def label_at(self) -> tuple:
        """Where the exported replay's stage label goes: above the target cloud."""
        r = self.app.state.inspect.result
        pts = r.target_cloud if len(r.target_cloud) else r.T_world_part[None, :3, 3]
        top = pts[np.argmax(pts[:, 2])]
        return tuple(float(v) for v in top + [0.0, 0.0, 0.25 * self.app.state.part_model().diameter])

    def set_stage(self, k: int) -> None:
        """Show replay stage `k`, the slider moved to it without its callback."""
        self._syncing = True
        try:
            self.i_stage.value = k + 1
        finally:
            self._syncing = False
        self.show_stage()

    def caption(self) -> str:
        """What the exported page says over the view: source, step, frame, the legend and the numbers."""
        ins = self.app.state.inspect
        r, score = ins.result, ins.score
        asm = self.app.state.inspect_assembly()
        verdict = "ok and confident" if r.confident else "not confident"
        numbers = [f"fitness {r.fitness:.3f}", f"inlier RMSE {r.inlier_rmse * 1000:.2f} mm"]
        if inspection.placement_mssd(score) is not None:
            numbers.insert(0, f"MSSD {inspection.mssd_text(score)} against the truth")
        shown = {"target cloud", "source cloud", "estimate"} | ({"truth"} if ins.frame.T_world_part is not None else set())
        part, base = asm.steps[ins.step - 1].part, ", ".join(asm.steps[ins.step - 1].base)
        return (f"<b>apose studio</b> &middot; {esc(asm.name)} &middot; step {ins.step}: {esc(part)} on {esc(base)}<br>"
                f"{esc(Path(str(ins.frames_path)).name)} &middot; frame {int(ins.frame.im_id)} &middot; {esc(verdict)}: "
                f"{esc(', '.join(numbers))}{legend_html(shown)}")

    def show_stage(self) -> None:
        if self._syncing:
            return
        if not self.stages:
            self.i_stage_md.content = "" if self.app.state.inspect.result is None else "_no registration trace (estimation failed)_"
            return
        k = int(np.clip(self.i_stage.value - 1, 0, len(self.stages) - 1))  # the slider counts from 1
        s = self.stages[k]
        h = self.app.nodes.get("/inspect/source")
        if h is None or self._source_of is not self.stages:  # the cloud is sent once per estimate; a stage moves it
            if h is not None:
                self.app.nodes.pop("/inspect/source").remove()
            d = self.app.state.part_model().diameter
            h = self.app.node("/inspect/source", self.app.ui.scene.add_point_cloud(
                "/inspect/source", s.source_base, inspection.BLUE, point_size=d / 120, point_shape="circle",
                precision="float32"),
                visible=bool(self.layers["source cloud"].value))
            self._source_of = self.stages
        h.wxyz, h.position = wxyz(s.T_world_base), pos(s.T_world_base)
        r = self.app.state.inspect.result
        T_base_part = se3.inv(r.T_world_base) @ r.T_world_part
        # the estimate's base, ghost and box follow the stage shown
        for name, T in (("/inspect/base_est", s.T_world_base), ("/inspect/ghost", s.T_world_base @ T_base_part),
                        ("/inspect/box_est", s.T_world_base @ T_base_part)):
            if name in self.app.nodes:
                self.app.nodes[name].wxyz, self.app.nodes[name].position = wxyz(T), pos(T)
        self.i_stage_md.content = self.stage_text(k, bold=True)

    def on_play_registration(self, client) -> None:
        if len(self.stages) < 2:
            raise AposeError("estimate this frame first; then the registration can be replayed")
        n = len(self.stages)

        def play():  # 0.2-0.4 s a stage (at most ~6 s in all): slow enough to follow the fit
            for k in range(n):
                self.i_stage.value = k + 1
                time.sleep(max(0.2, min(0.4, 6.0 / n)))

        self.app.start_thread(play, name="registration replay")

    def apply_layers(self) -> None:
        which = dict(NODE_LAYERS)
        which.update({n: "labels" for n in self.app.nodes if n.startswith("/inspect/label_")})
        present = {layer for name, layer in which.items() if name in self.app.nodes}
        for layer, box in self.layers.items():  # a checkbox only for what this frame draws (no robot base: none)
            if box.visible != (layer in present):
                box.visible = layer in present
        for name, layer in which.items():
            if name in self.app.nodes:
                h = self.app.nodes[name]
                own = self._label_layers.get(name) if layer == "labels" else None  # a label goes with what it names
                h._apose_visible = bool(self.layers[layer].value) and (own is None or bool(self.layers[own].value))
                h.visible = h._apose_visible and self.app.current_view == "Inspect"


NODE_LAYERS = {"/inspect/scene": "scene cloud", "/inspect/target": "target cloud", "/inspect/source": "source cloud",
               "/inspect/box_gt": "boxes", "/inspect/box_est": "boxes", "/inspect/box_alt": "boxes",
               "/inspect/ghost": "part at estimate", "/inspect/base_est": "base at estimate", "/inspect/camera": "camera",
               "/inspect/gripper": "gripper", "/inspect/gripper_preplace": "gripper", "/inspect/gripper_pick": "gripper",
               "/inspect/robot": "robot base"}  # node -> its Layers checkbox (and legend entry, where it has one)


def on_truth(labels: list, score, diameter: float) -> list:
    """`labels` (text, where, anchor) with "truth" and "estimate" made one "estimate on truth" label at the
    estimate's place when the estimate lies within ON_TRUTH of the part's diameter of the truth (placement MSSD):
    its green box is then drawn on the dashed amber one, and two labels for what reads as one box left the user
    asking where the other was."""
    m = inspection.placement_mssd(score)
    texts = [t for t, _, _ in labels]
    if m is None or m > inspection.ON_TRUTH * diameter or not {"truth", "estimate"} <= set(texts):
        return labels
    return [("estimate on truth", w, a) if t == "estimate" else (t, w, a) for t, w, a in labels if t != "truth"]


LABEL_LAYERS = {"truth": "boxes", "estimate": "boxes", "estimate on truth": "boxes", "alternative": "boxes", "place": "gripper",
                "pre-place": "gripper", "pick": "gripper", "target cloud": "target cloud"}


def label_layer(text: str) -> str | None:
    """The Layers checkbox of what a 3D label names (LABEL_LAYERS; "robot base (FRAME)" -> robot base): the label
    is hidden with it. None for a label of no layer of its own."""
    return "robot base" if text.startswith("robot base") else LABEL_LAYERS.get(text)
