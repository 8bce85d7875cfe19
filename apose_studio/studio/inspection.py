"""What the studio's Inspect tab shows, as pure functions: boxes, their 2D projection, clouds per stage.

Colours, one per thing (the legend): target cloud red, source cloud blue, estimated box green, ground
truth amber (dashed, drawn a little outside the estimate so coincident boxes do not z-fight),
alternatives magenta. Everything is metres and world frame unless a name says otherwise.
"""

from __future__ import annotations

import html
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from apose_studio.api import pose_estimate, robot_targets
from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.raycast import raycast_depth
from apose_studio.registration import RegistrationResult, doubts
from apose_studio.robot.targets import Targets

RED = (220, 40, 40)
BLUE = (40, 90, 230)
GREEN = (30, 190, 60)
AMBER = (255, 160, 0)  # ground truth
CYAN = (0, 200, 255)  # the mask on the RGB overlay
MAGENTA = (220, 60, 220)  # other placements that fit as well as the estimate (an ambiguous result)
GRIPPER = (150, 156, 170)  # light steel: the gripper at a grasp (robot/grasping.py), in no part palette
LEGEND = (("target cloud", RED), ("source cloud", BLUE), ("estimate (the part's box)", GREEN), ("truth (dashed)", AMBER),
          ("part at estimate (see-through)", (160, 225, 170)),
          ("base at estimate (outline)", GREEN), ("alternatives", MAGENTA), ("gripper", GRIPPER),
          ("scene cloud (the image's colours)", (150, 150, 150)))
ON_TRUTH = 0.02  # an estimate this close to the truth (placement MSSD, share of the part's diameter) draws its box on
# the truth's: one label, "estimate on truth", says so instead of two labels for what looks like one box

# the 12 edges of a box whose corners are ordered as mesh.PartModel.box_corners() (x major, z minor)
BOX_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]])


def box_segments(corners_part: np.ndarray, T_world_part: np.ndarray) -> np.ndarray:
    """(12, 2, 3) world line segments of a part's box (corners in the part frame) at a pose."""
    c = se3.transform_points(T_world_part, corners_part)
    return c[BOX_EDGES]


def feature_edges(mesh, angle_deg: float, max_segments: int = 6000) -> np.ndarray:
    """(M, 2, 3) line segments of a mesh's outline, in the mesh's frame: the edges where its surface folds by
    more than `angle_deg` (the studio passes widgets.SHARP_EDGE_DEG, the creases its meshes are drawn with) and
    its open borders; at most `max_segments` (the sharpest folds first, borders always). The base at the
    estimate is drawn so: a full wireframe of an 8,000-triangle base took ~115 ms of each frame drawn in
    software WebGL (benchmarks/studio_browser.py), and its mesh of lines hid the cloud."""
    v = np.asarray(mesh.vertices, float)
    if len(mesh.faces) == 0:
        return np.zeros((0, 2, 3))
    angles = np.asarray(mesh.face_adjacency_angles, float)
    sharp = angles > np.radians(angle_deg)
    folds = np.asarray(mesh.face_adjacency_edges)[sharp][np.argsort(-angles[sharp], kind="stable")]
    edges = np.sort(np.asarray(mesh.edges_unique), axis=1)
    counts = np.bincount(np.asarray(mesh.edges_unique_inverse), minlength=len(edges))
    border = edges[counts == 1]  # an edge of one face only: where the surface ends
    seg = np.concatenate([border, folds])[:max(max_segments, len(border))].astype(np.intp)
    return v[seg]


def inflate(corners_part: np.ndarray, fraction: float) -> np.ndarray:
    """Box corners moved out from the box centre by `fraction` of its size (a ground-truth box drawn just
    outside an estimate on the same spot stays visible instead of z-fighting)."""
    c = corners_part.mean(axis=0)
    return c + (corners_part - c) * (1.0 + fraction)


def dashed(segments: np.ndarray, dashes: int = 6) -> np.ndarray:
    """(N, 2, 3) segments cut into `dashes` pieces each, every other piece kept: (N * dashes // 2... , 2, 3)."""
    t = np.linspace(0.0, 1.0, 2 * dashes)
    a, b = segments[:, :1, :], segments[:, 1:, :]
    pts = a + (b - a) * t[None, :, None]  # (N, 2*dashes, 3)
    return pts.reshape(len(segments), dashes, 2, 3).reshape(-1, 2, 3)


def crop_window(shape: tuple[int, int], uv: np.ndarray, margin: float = 0.35, min_size: int = 96) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the image window around pixels `uv` (N, 2) with a margin of their extent, at least
    `min_size` across, clipped to the image; the whole image when nothing is given."""
    h, w = shape
    uv = uv[np.isfinite(uv).all(axis=1)] if len(uv) else uv
    if not len(uv):
        return 0, 0, w, h
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    size = max(float((hi - lo).max()) * (1.0 + 2.0 * margin), min_size)
    c = (lo + hi) / 2.0
    x0, y0 = int(np.clip(c[0] - size / 2, 0, w - 1)), int(np.clip(c[1] - size / 2, 0, h - 1))
    x1, y1 = int(np.clip(c[0] + size / 2, x0 + 1, w)), int(np.clip(c[1] + size / 2, y0 + 1, h))
    return x0, y0, x1, y1


def pose_report(result: RegistrationResult, T_world_camera: np.ndarray) -> dict:
    """The estimate as a robot needs it: T_world_part and T_camera_part (4x4, metres) and each as
    translation (mm) + quaternion wxyz. JSON-ready."""
    T_camera_part = se3.inv(T_world_camera) @ result.T_world_part

    def entry(T):
        return {"matrix": T.tolist(), "translation_mm": (T[:3, 3] * 1000.0).tolist(),
                "quat_wxyz": [float(v) for v in se3.matrix_to_quat_wxyz(T[:3, :3])]}

    return {"T_world_part": entry(result.T_world_part), "T_camera_part": entry(T_camera_part),
            "T_world_base": entry(result.T_world_base), "fitness": float(result.fitness),
            "inlier_rmse_mm": float(result.inlier_rmse * 1000.0), "coverage": float(result.coverage),
            "confident": bool(result.confident), "ambiguous": bool(result.ambiguous)}


def pose_markdown(report: dict) -> str:
    """The two poses of `pose_report` as a small table (mm, wxyz)."""
    rows = []
    for name in ("T_world_part", "T_camera_part"):
        t, q = report[name]["translation_mm"], report[name]["quat_wxyz"]
        rows.append(f"| `{name}` | {t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f} | {q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f} |")
    return "| pose | t (mm) | q (wxyz) |\n|---|---|---|\n" + "\n".join(rows)


def project_points(points_world: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) and a mask of the points in front of the camera."""
    pc = se3.transform_points(se3.inv(T_world_camera), points_world)
    front = pc[:, 2] > 1e-6
    u, v = cam.project(np.where(front[:, None], pc, [0.0, 0.0, 1.0]))
    return np.stack([u, v], axis=1), front


def draw_boxes(rgb: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray, corners_part: np.ndarray,
               boxes: list[tuple[np.ndarray, tuple[int, int, int]]], thickness: int = 2) -> np.ndarray:
    """A copy of the RGB image with each (T_world_part, colour) box projected and drawn (OpenCV lines).
    Earlier boxes are drawn thicker, so a later box on top of one (a good estimate on the truth) leaves
    both visible."""
    out = np.ascontiguousarray(rgb.copy())
    for i, (T, colour) in enumerate(boxes):
        width = thickness + 2 * (len(boxes) - 1 - i)
        seg = box_segments(corners_part, T).reshape(-1, 3)
        uv, front = project_points(seg, T_world_camera, cam)
        for k in range(0, len(uv), 2):
            if front[k] and front[k + 1]:
                a = tuple(int(round(v)) for v in uv[k])
                b = tuple(int(round(v)) for v in uv[k + 1])
                cv2.line(out, a, b, colour, width, cv2.LINE_AA)
    return out


def draw_outline(image: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int], thickness: int = 1,
                 inset: int = 0) -> np.ndarray:
    """`mask`'s outer and inner outlines drawn onto `image` (in place, returned): a mask shown as its edge
    keeps the pixels under it visible, so the fit can be judged by eye. `inset` (pixels): the outlines of the mask
    eroded by that much, so that they run inside another outline drawn on the mask's own edge (the estimate's mask
    is the model's silhouette less what hides it: drawn on the edge, the model's outline covered it but for dots)."""
    if inset > 0:
        mask = cv2.erode(np.ascontiguousarray(mask, dtype=np.uint8), np.ones((2 * inset + 1, 2 * inset + 1), np.uint8))
    contours, _ = cv2.findContours(np.ascontiguousarray(mask, dtype=np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(image, contours, -1, colour, thickness, cv2.LINE_8)
    return image


WHITE = (255, 255, 255)


def draw_prompt(image: np.ndarray, box: tuple | None, point: tuple | None) -> np.ndarray:
    """The prompt typed (a box x0,y0,x1,y1, its right and bottom edges exclusive; or a point u,v) drawn onto
    `image` in white (in place, returned): the user sees what the mask was asked for."""
    if box is not None:
        x0, y0, x1, y1 = (int(v) for v in box)
        cv2.rectangle(image, (x0, y0), (x1 - 1, y1 - 1), WHITE, 1, cv2.LINE_8)
    if point is not None:
        cv2.drawMarker(image, (int(point[0]), int(point[1])), WHITE, cv2.MARKER_CROSS, 9, 1)
    return image


def silhouette(mesh, T_world_mesh: np.ndarray, T_world_camera: np.ndarray, cam: CameraIntrinsics) -> np.ndarray:
    """(H, W) bool: the pixels the mesh at T_world_mesh covers in the camera (one ray per pixel centre)."""
    return np.isfinite(raycast_depth(mesh, T_world_mesh, T_world_camera, cam))


def enlarge(image: np.ndarray, min_width: int = 360) -> np.ndarray:
    """An image narrower than `min_width` scaled up by a whole factor (nearest pixel: each sensor pixel
    stays a visible square), so a crop around a small object is still read at pixel level."""
    k = int(np.ceil(min_width / max(image.shape[1], 1)))
    return image if k <= 1 else cv2.resize(image, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)


def scene_cloud(depth: np.ndarray, rgb: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray,
                max_points: int = 60000) -> tuple[np.ndarray, np.ndarray]:
    """The whole depth image back-projected to world points with their RGB colours, thinned on a pixel
    grid to at most ~max_points (so a browser draws it smoothly)."""
    h, w = depth.shape
    stride = max(1, int(np.ceil(np.sqrt(h * w / max_points))))
    d = depth[::stride, ::stride]
    vs, us = np.nonzero(np.isfinite(d) & (d > 0))
    u, v = us * stride, vs * stride
    pc = cam.backproject(u, v, d[vs, us])
    return se3.transform_points(T_world_camera, pc).astype(np.float32), rgb[v, u]


def pixels_in_box(depth: np.ndarray, cam: CameraIntrinsics, T_world_camera: np.ndarray, T_world_box: np.ndarray,
                  size: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose depth point lies inside a box (pose of its centre, full side lengths)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    z = np.where(np.isfinite(depth), depth, 0.0)
    pc = cam.backproject(u, v, z).reshape(-1, 3)
    local = se3.transform_points(se3.inv(T_world_box) @ T_world_camera, pc)
    inside = (np.abs(local) <= np.asarray(size) / 2.0).all(axis=1).reshape(h, w)
    return inside & (z > 0)


def point_on_ray(points: np.ndarray, origin: np.ndarray, direction: np.ndarray, max_offset: float) -> np.ndarray | None:
    """The point a click's ray hits first: among points within `max_offset` of the ray (in front of its
    origin), the one nearest the origin; None when the ray passes no point."""
    d = direction / np.linalg.norm(direction)
    rel = points - origin
    along = rel @ d
    off = np.linalg.norm(rel - along[:, None] * d, axis=1)
    near = (along > 0) & (off < max_offset)
    if not near.any():
        return None
    return points[near][np.argmin(along[near])].astype(float)


def thin(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    if len(points) <= max_points:
        return points
    idx = np.random.default_rng(seed).choice(len(points), max_points, replace=False)
    return points[np.sort(idx)]


@dataclass(frozen=True)
class StageView:
    """One frame of the registration replay: the source cloud (base frame, shared by every stage) at
    this stage's pose."""

    name: str
    source_base: np.ndarray  # (N, 3) float32, the source cloud in the base's frame
    T_world_base: np.ndarray
    fitness: float
    inlier_rmse: float

    @property
    def source_world(self) -> np.ndarray:
        return se3.transform_points(self.T_world_base, self.source_base)


def replay(result: RegistrationResult, max_points: int = 20000) -> list[StageView]:
    """Each stage of the registration (initial -> global -> ICP iterations -> final) as the pose that moves
    the (thinned) source cloud: a replay sends the cloud once and then only poses."""
    src = thin(result.source_cloud, max_points).astype(np.float32)
    return [StageView(s.name, src, s.T_world_base, float(s.fitness), float(s.inlier_rmse)) for s in result.stages]


def placement_mssd(score) -> float | None:
    """The MSSD that says whether the placement is right: to the nearest of the truth and its twins under the
    base's exact symmetries (the same assembly, as `apose eval`'s recall counts it); None without a truth."""
    if score is None or getattr(score, "mssd", None) is None:
        return None
    sym = getattr(score, "mssd_mod_base_sym", None)
    return score.mssd if sym is None else min(score.mssd, sym)


def mssd_text(score) -> str:
    """'0.05 mm', or '0.05 mm (48.08 mm to the truth's own orientation: the base's symmetry makes them the same
    assembly)' when the base's exact symmetry forgives the difference."""
    m = placement_mssd(score)
    if m is None:
        return ""
    if score.mssd - m > 1e-6:
        return (f"{m * 1000:.2f} mm ({score.mssd * 1000:.2f} mm to the truth's own orientation: the base's "
                "symmetry makes them the same assembly)")
    return f"{m * 1000:.2f} mm"


def metrics_markdown(score, result: RegistrationResult | None, refusal: str | None = None) -> str:
    """The metrics panel: errors against ground truth (when known) and the estimator's own numbers; without a
    result, why the last Estimate of this frame with these settings was refused (`refusal`), else how to get one."""
    if result is None and refusal:
        return f"**Not estimated:** {html.escape(refusal)}"
    if result is None:
        return "_No estimate for this frame yet: press **Estimate frame**._"
    if not result.ok:
        return f"**Estimation failed:** {html.escape(str(result.reason))}"
    rows = [("fitness", f"{result.fitness:.3f}"), ("inlier RMSE", f"{result.inlier_rmse * 1000:.2f} mm"),
            ("time", f"{result.seconds * 1000:.0f} ms"), ("coverage", f"{result.coverage:.0%}")]
    if score is not None and score.adi is not None:
        rows = [("ADI", f"{score.adi * 1000:.2f} mm"), ("MSSD", mssd_text(score)),
                ("te (translation error)", f"{score.te * 1000:.2f} mm"), ("re (rotation error)", f"{score.re_deg:.2f}°")] + rows
    if score is not None and score.mask_iou is not None:
        rows.append(("mask IoU", f"{score.mask_iou:.3f}"))
    if result.reading:  # the pose came from another reading of the mask (registration/hypotheses.py)
        rows.append(("mask read as", html.escape(result.reading).replace("|", "&#124;")))
    if result.ok and result.depth_moved_px != (0, 0):  # estimation.estimate_view moved the depth onto the colour image
        du, dv = result.depth_moved_px
        rows.append(("depth vs colour", f"the depth's edges lay {du:+d}, {dv:+d} px (right, down) off the colour image's: "
                     "moved back, and the pose estimated on it"))
    if result.ok and result.colour_offset > 0:  # estimation.colour_checked found the depth's edges off the colour's
        du, dv = result.colour_offset_px
        bleed = (", or the depth's outlines bleed past the colour's by as much (the edges cannot tell which: the depth "
                 "was not moved)") if result.colour_offset_bleed else ""
        rows.append(("depth vs colour", f"edges {du:+d}, {dv:+d} px apart (right, down){bleed}: up to "
                     f"{result.colour_offset * 1000:.1f} mm off; tick Align depth to colour if the depth is registered off"))
    flags = []
    if result.ambiguous:
        flags.append(f"ambiguous: {len(result.alternatives) + 1} placements fit the data equally (a (nearly) symmetric "
                     "base, and what tells them apart is not in view); the others are the magenta boxes")
    if not result.confident:
        flags.append(f"not confident: {doubts(result)}")
    elif result.base_alternatives:
        flags.append(f"the base's own turn is not sure: turned {len(result.base_alternatives)} other way(s) it fits as "
                     "well and places the part alike (the view hides what tells them apart); the part's pose stands")
    table = "| metric | value |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)
    verdict = ("**✔ ok and confident**: one placement that the data supports" if result.confident else
               "**⚠ ok, not confident**: do not act on this pose without a second look")
    return verdict + "\n\n" + table + ("\n\n" + "\n\n".join(f"⚠ {f}" for f in flags) if flags else "")


@dataclass
class ResultCache:
    """Estimates per (dataset, step, frame, preset, mask, prior), so revisiting a frame is instant. The
    newest `max_entries` are kept (a live camera or a long recording estimated frame after frame would
    otherwise grow the studio's memory without end)."""

    entries: OrderedDict = field(default_factory=OrderedDict)
    max_entries: int = 512

    @staticmethod
    def key(dataset: str, step: int | None, im_id: int, preset: str, mask, prior: bool) -> tuple:
        return (str(dataset), step, int(im_id), preset, mask, bool(prior))

    def get(self, key):
        return self.entries.get(key)

    def put(self, key, value) -> None:
        self.entries[key] = value
        self.entries.move_to_end(key)
        while len(self.entries) > self.max_entries:
            self.entries.popitem(last=False)

    def __len__(self) -> int:
        return len(self.entries)


def box_from_view_rect(points_world: np.ndarray, T_world_view: np.ndarray, fov: float, aspect: float,
                       rect_min, rect_max, T_world_camera: np.ndarray, cam: CameraIntrinsics) -> tuple[int, int, int, int] | None:
    """A box prompt (x0, y0, x1, y1 in the frame's pixels) from a rectangle dragged in the 3D view: the
    scene points the rectangle covers (the view's camera: OpenCV axes, vertical field of view `fov` in
    radians, width/height `aspect`, the rectangle in 0..1 screen coordinates), projected into the frame.
    None when it covers no scene point."""
    pc = se3.transform_points(se3.inv(T_world_view), points_world)
    front = pc[:, 2] > 1e-6
    t = np.tan(fov / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = 0.5 + pc[:, 0] / np.where(front, pc[:, 2], 1.0) / (2.0 * t * aspect)
        sy = 0.5 + pc[:, 1] / np.where(front, pc[:, 2], 1.0) / (2.0 * t)
    (x0, y0), (x1, y1) = rect_min, rect_max
    inside = front & (sx >= min(x0, x1)) & (sx <= max(x0, x1)) & (sy >= min(y0, y1)) & (sy <= max(y0, y1))
    if inside.sum() < 3:
        return None
    uv, ok = project_points(points_world[inside], T_world_camera, cam)
    uv = uv[ok]
    if not len(uv):
        return None
    lo, hi = np.floor(uv.min(axis=0)), np.ceil(uv.max(axis=0)) + 1
    return (int(max(lo[0], 0)), int(max(lo[1], 0)), int(min(hi[0], cam.width)), int(min(hi[1], cam.height)))


def frame_box_from_drag(frame, event, what: str) -> tuple[int, int, int, int]:
    """The box prompt (frame pixels) of a rectangle dragged in a tab's 3D view (viser's rect pointer event: the
    tab's camera and the rectangle): box_from_view_rect on the frame's scene points. AposeError naming `what`
    (the object to drag around) when it covers none."""
    cam = event.client.camera
    T_world_view = se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(cam.wxyz)), np.asarray(cam.position))
    pts, _ = scene_cloud(frame.depth, frame.rgb, frame.camera, frame.T_world_camera)
    box = box_from_view_rect(pts, T_world_view, cam.fov, cam.aspect, event.screen_min, event.screen_max,
                             frame.T_world_camera, frame.camera)
    if box is None:
        raise AposeError(f"the rectangle covers no depth point; drag it around {what} itself")
    return box


def robot_targets_shown(ins, asm, ctx):
    """The pick-and-place targets of what the Inspect tab shows, in the robot's frame (api.robot_targets): the
    estimate on show (`ins.result`) placed, the loose part's estimate in this frame (`ins.pick()`) picked, by the
    part's first grasp, with the Robot folder's calibration (`ins.hand_eye`, `ins.T_robot_flange`). None
    without a calibration or a frame; without an estimate, only T_robot_camera (the robot base's axes)."""
    he, fr = ins.hand_eye, ins.frame
    if he is None or fr is None:
        return None
    pick = ins.pick()[1]
    r = ins.result
    if r is None:
        t = Targets(he.robot_frame, he.camera_frame, he.T_robot_camera(ins.T_robot_flange),
                    notes=["not estimated yet: Estimate frame gives the place targets"])
        if pick is None:
            return t
        r = RegistrationResult(ok=False, reason="not estimated yet")
    est = pose_estimate(r, fr.T_world_camera, ctx.view, None, "", {})
    return robot_targets(est, asm, ctx, he, None, pick, ins.T_robot_flange)


def T_world_robot(ins) -> np.ndarray | None:
    """The robot base in the world of the frame on show, by the Robot folder's calibration; None without a
    calibration or a frame, or for an eye-in-hand calibration without the arm's pose (the Robot folder says so)."""
    if ins.hand_eye is None or ins.frame is None:
        return None
    try:
        return ins.frame.T_world_camera @ se3.inv(ins.hand_eye.T_robot_camera(ins.T_robot_flange))
    except AposeError:
        return None
