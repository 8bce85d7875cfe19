"""One synthetic RGB-D frame of an assembly step by ray casting (Open3D's RaycastingScene): no GUI, no GPU.

A frame shows the base object of a step resting on a table (at a fixed or random pose), the part
to place lying loose beside it, and optional distractor shapes; the camera sits on a hemisphere
around the base (yaw, pitch, distance) and looks at it. Everything is in metres and OpenCV camera
convention (x right, y down, z forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from apose_studio.assembly.mesh import PartModel, base_body_mesh
from apose_studio.assembly.model import StepView
from apose_studio.errors import RenderError
from apose_studio.geometry import se3
from apose_studio.geometry.camera import CameraIntrinsics
from apose_studio.geometry.noise import NOISE_MODELS, add_depth_noise, bleed, noise_texture
from apose_studio.geometry.raycast import RayGrid, body, pixel_window
from apose_studio.geometry.sensor import shift_image
from apose_studio.synth.clutter import Pattern, clutter_around, hide_base, stack_on

BASE_POSES = ("yaw", "fixed")
CLUTTER_KINDS = ("bench", "stacked", "hidden", "textured")  # what `--clutter` may combine (synth/clutter.py)
TRAJECTORIES = ("approach", "orbit")  # the camera paths of `--trajectory` (synth/placement.trajectory_cameras)


@dataclass(frozen=True)
class RenderSettings:
    """What `apose render` varies. Angles in degrees, lengths in metres."""

    frames: int = 10
    seed: int = 0
    noise: str = "none"
    noise_sigma_at_05m: float = 0.001  # axial depth noise at 0.5 m; grows with z^2 (RealSense-like)
    yaw_range_deg: tuple[float, float] = (0.0, 360.0)
    pitch_range_deg: tuple[float, float] = (25.0, 75.0)  # camera elevation above the table
    distance_range_m: tuple[float, float] | None = None  # None: chosen so the base fills 25-50 % of the image
    base_pose: str = "yaw"
    distractors: int = 2
    # what a real bench and sensor add (any of CLUTTER_KINDS; True means ("bench",)): bench: objects of the base's
    # height touching it and around it, the base off-centre; stacked: a flat object lying on top of the base;
    # hidden: an object in front that hides 65-80 % of the base; textured: patterned table, clutter and base
    clutter: tuple[str, ...] = ()
    views_per_scene: int = 1  # camera poses per placement of the base (an eye-in-hand camera's looks), >= 30 deg apart
    trajectory: str = ""  # "" (each frame its own camera), or a camera path over one placement per step, a frame per
    # point (synth/placement.TRAJECTORIES: approach, orbit): what a camera sees moving, for tracking
    camera: CameraIntrinsics = field(default_factory=CameraIntrinsics)
    depth_bias_m: float = 0.0  # added to every depth reading (a Kinect reads a few mm off)
    misregistration_px: float = 0.0  # depth registered to the colour image this many pixels off, per frame in a
    # random direction (the colour image, the masks and the poses agree; the depth is shifted)
    bleed_px: int = 0  # near surfaces read this many pixels wider in depth than in colour, over farther ones (a
    # correlation window's foreground fattening: geometry.noise.bleed), on top of the noise model's own
    base_fill: tuple[float, float] = (0.25, 0.5)  # share of the image's short side the base's diameter spans (sets the
    # camera distance when distance_range_m is None)

    def __post_init__(self):
        if isinstance(self.clutter, bool):
            object.__setattr__(self, "clutter", ("bench",) if self.clutter else ())
        elif isinstance(self.clutter, str):
            object.__setattr__(self, "clutter", tuple(k.strip() for k in self.clutter.split(",") if k.strip()))
        else:
            object.__setattr__(self, "clutter", tuple(self.clutter))

    def validate(self) -> None:
        def rng_ok(r, lo, hi, name, unit):
            if r is None:
                return
            a, b = r
            if not (lo <= a <= b <= hi) or (a == b and name != "distance"):
                raise RenderError(f"--{name}-range {a:g},{b:g}: expected min,max with {lo:g} <= min "
                                  f"{'<=' if name == 'distance' else '<'} max <= {hi:g} {unit}")
        if not 1 <= self.frames <= MAX_FRAMES:
            raise RenderError(f"--frames {self.frames}: expected 1 to {MAX_FRAMES} frames per step")
        if not 0 <= self.seed < 2 ** 32:
            raise RenderError(f"--seed {self.seed}: expected a whole number from 0 to {2 ** 32 - 1}")
        if self.noise not in NOISE_MODELS:
            raise RenderError(f"--noise {self.noise}: expected one of {', '.join(NOISE_MODELS)}")
        if self.base_pose not in BASE_POSES:
            raise RenderError(f"--base-pose {self.base_pose}: expected one of {', '.join(BASE_POSES)}")
        if not 0 <= self.noise_sigma_at_05m < 0.05:
            raise RenderError(f"--noise-sigma {self.noise_sigma_at_05m}: expected metres at 0.5 m, in [0, 0.05)")
        if not 1 <= self.views_per_scene <= self.frames:
            raise RenderError(f"--views-per-scene {self.views_per_scene}: expected 1 to --frames ({self.frames})")
        if not 0 <= self.distractors <= MAX_DISTRACTORS:
            raise RenderError(f"--distractors {self.distractors}: expected 0 to {MAX_DISTRACTORS} (more would not fit "
                              "on the table around the base)")
        rng_ok(self.yaw_range_deg, -360, 720, "yaw", "degrees")
        rng_ok(self.pitch_range_deg, 1, 90, "pitch", "degrees")
        unknown = [k for k in self.clutter if k not in CLUTTER_KINDS]
        if unknown:
            raise RenderError(f"--clutter {','.join(self.clutter)}: {unknown[0]!r} is not a kind of clutter; expected any of "
                              f"{', '.join(CLUTTER_KINDS)}, comma-separated")
        if self.trajectory and self.trajectory not in TRAJECTORIES:
            raise RenderError(f"--trajectory {self.trajectory}: expected one of {', '.join(TRAJECTORIES)}")
        if self.trajectory and self.views_per_scene > 1:
            raise RenderError("--trajectory with --views-per-scene: a trajectory is already every frame of a step seen from "
                              "one moving camera over one placement; give one of them")
        if "hidden" in self.clutter and self.trajectory:
            raise RenderError("--clutter hidden with --trajectory: the object that hides the base stands in front of one "
                              "camera; render a trajectory without it")
        if "hidden" in self.clutter and self.views_per_scene > 1:
            raise RenderError("--clutter hidden with --views-per-scene > 1: the object that hides the base stands in front "
                              "of one camera; render the views of a placement without it")
        if not -0.05 <= self.depth_bias_m <= 0.05:
            raise RenderError(f"--depth-bias {self.depth_bias_m * 1000:g}: expected millimetres from -50 to 50")
        if not 0 <= self.misregistration_px <= 20:
            raise RenderError(f"--misregistration {self.misregistration_px:g}: expected pixels from 0 to 20")
        if not (isinstance(self.bleed_px, int) and 0 <= self.bleed_px <= MAX_BLEED_PX):
            raise RenderError(f"--bleed {self.bleed_px}: expected whole pixels from 0 to {MAX_BLEED_PX}")
        a, b = self.base_fill
        if not 0.02 <= a <= b <= 1.0:
            raise RenderError(f"--base-fill {a:g},{b:g}: expected min,max with 0.02 <= min <= max <= 1 (the share of the "
                              "image's short side the base spans)")
        if self.distance_range_m is not None and self.distance_range_m[0] <= 0:
            raise RenderError("--distance-range: expected positive distances in metres")
        rng_ok(self.distance_range_m, 1e-3, 100, "distance", "m")


MAX_FRAMES = 100_000  # per step
MAX_DISTRACTORS = 50
MAX_BLEED_PX = 8


@dataclass
class SceneObject:
    """One body in a rendered scene. `part` is the part id, or None for the table and distractors."""

    part: str | None
    mesh: trimesh.Trimesh  # in the object's own frame
    T_world_obj: np.ndarray
    color: tuple[float, float, float]
    pattern: Pattern | None = None  # printed on it (`--clutter textured`)


@dataclass
class Scene:
    objects: list[SceneObject]  # bodies on the table; the table itself is the plane z = 0
    T_world_base: np.ndarray  # pose of base[0]
    base_centre: np.ndarray  # world point the camera looks at
    base_diameter: float
    table_color: tuple[float, float, float] = (0.6, 0.58, 0.55)
    table_radius: float = 2.0  # the table is a disc of this radius around the base
    n_base: int = 1  # objects[:n_base] are the base object's members
    table_pattern: Pattern | None = None  # printed on the table (`--clutter textured`)

    @property
    def table_label(self) -> int:
        """Label of table pixels: one past the last object."""
        return len(self.objects)


@dataclass
class RenderedFrame:
    """A rendered view. depth in metres (0 = no return)."""

    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres, after noise; 0 where invalid
    T_world_camera: np.ndarray
    scene: Scene
    hits: "Hits"
    noise_seed: int = 0

    @property
    def labels(self) -> np.ndarray:
        """(H, W) int32: index into scene.objects, scene.table_label, or -1 where nothing was hit."""
        return self.hits.labels


# --------------------------------------------------------------------------------- scene sampling


def _resting_pose(mesh: trimesh.Trimesh, yaw: float, xy) -> np.ndarray:
    """Pose that turns a mesh by `yaw` about z and sets it on the table (its lowest point at z = 0)."""
    R = se3.axis_angle_matrix((0, 0, 1), yaw)
    z_min = float((mesh.vertices @ R.T)[:, 2].min())
    return se3.make_T(R, (xy[0], xy[1], -z_min))


_DISTRACTORS: dict[float, list[trimesh.Trimesh]] = {}


def distractor_pool(base_diameter: float) -> list[trimesh.Trimesh]:
    """24 boxes, cylinders and balls sized for a base object, made once (their BVHs stay cached)."""
    key = round(base_diameter, 6)
    if key not in _DISTRACTORS:
        rng = np.random.default_rng(7)
        pool = []
        for k in range(24):
            size = base_diameter * rng.uniform(0.25, 0.5)
            if k % 3 == 0:
                pool.append(trimesh.creation.box(rng.uniform(0.4, 1.0, 3) * size))
            elif k % 3 == 1:
                pool.append(trimesh.creation.cylinder(radius=size * rng.uniform(0.2, 0.45),
                                                      height=size * rng.uniform(0.4, 1.2), sections=24))
            else:
                pool.append(trimesh.creation.icosphere(subdivisions=2, radius=size * rng.uniform(0.2, 0.4)))
        if len(_DISTRACTORS) > 16:
            _DISTRACTORS.clear()
        _DISTRACTORS[key] = pool
    return _DISTRACTORS[key]


def sample_scene(models: dict[str, PartModel], view: StepView, settings: RenderSettings,
                 rng: np.random.Generator, base: trimesh.Trimesh | None = None) -> Scene:
    """Base object on the table (fixed or random yaw and position), the loose part beside it, distractors."""
    base = base if base is not None else base_body_mesh(models, view)
    if settings.base_pose == "fixed":
        T_world_base = _resting_pose(base, 0.0, (0.0, 0.0))
    else:
        T_world_base = _resting_pose(base, rng.uniform(0, 2 * np.pi), rng.uniform(-0.1, 0.1, 2))
    base_world = se3.transform_points(T_world_base, base.vertices)
    centre = (base_world.min(axis=0) + base_world.max(axis=0)) / 2
    base_d = float(np.linalg.norm(base.extents))
    objects = [SceneObject(pid, models[pid].mesh, T_world_base @ T, models[pid].color)
               for pid, T in view.T_base_members.items()]

    placed = [(centre[:2], base_d / 2)]  # discs already taken on the table
    look = centre
    if settings.clutter:
        bench, look = clutter_around(base.copy().apply_transform(T_world_base), rng, touching=int(rng.integers(2, 4)))
        for mesh, T in bench:
            color = tuple(float(c) for c in rng.uniform(0.15, 0.95, 3))
            objects.append(SceneObject(None, mesh, T, color))
            placed.append((T[:2, 3], float(np.linalg.norm(mesh.extents[:2])) / 2))

    def free_spot(radius: float) -> np.ndarray:
        for _ in range(100):
            ang, dist = rng.uniform(0, 2 * np.pi), rng.uniform(1.05, 1.6) * (base_d / 2 + radius)
            xy = centre[:2] + dist * np.array([math.cos(ang), math.sin(ang)])
            if all(np.linalg.norm(xy - c) > r + radius for c, r in placed):
                placed.append((xy, radius))
                return xy
        return centre[:2] + np.array([3 * base_d + 3 * radius, 0.0])  # crowded: far away

    for twin in view.twins:  # the base's other instances (identical roots) stand on free spots around it
        mesh = models[twin].mesh
        spot = free_spot(float(np.linalg.norm(mesh.extents[:2])) / 2)
        objects.append(SceneObject(twin, mesh, _resting_pose(mesh, rng.uniform(0, 2 * np.pi), spot), models[twin].color))
    part = models[view.part]
    loose_r = float(np.linalg.norm(part.mesh.extents[:2])) / 2
    objects.append(SceneObject(view.part, part.mesh, _resting_pose(part.mesh, rng.uniform(0, 2 * np.pi),
                                                                     free_spot(loose_r)), part.color))
    pool = distractor_pool(base_d)
    for _ in range(settings.distractors):
        mesh = pool[rng.integers(len(pool))]
        r = float(np.linalg.norm(mesh.extents[:2])) / 2
        color = tuple(float(c) for c in rng.uniform(0.15, 0.95, 3))
        objects.append(SceneObject(None, mesh, _resting_pose(mesh, rng.uniform(0, 2 * np.pi), free_spot(r)), color))
    grey = float(rng.uniform(0.45, 0.75))
    scene = Scene(objects, T_world_base, look, base_d, (grey, grey * 0.97, grey * 0.92), max(2.0, 20 * base_d),
                  n_base=len(view.T_base_members))
    if "stacked" in settings.clutter:  # drawn after the objects above: they stay where they were (the camera, drawn
        # next, moves)
        on_top = stack_on(base.copy().apply_transform(T_world_base), rng)
        if on_top is not None:
            mesh, T = on_top
            objects.append(SceneObject(None, mesh, T, tuple(float(c) for c in rng.uniform(0.15, 0.95, 3))))
    if "textured" in settings.clutter:
        for o in objects:
            o.pattern = Pattern.draw(rng, base_d) if rng.random() < 0.7 else None
        scene.table_pattern = Pattern.draw(rng, base_d, table=True)
    return scene


def hide(scene: Scene, T_world_camera: np.ndarray, grid: RayGrid, rng: np.random.Generator) -> float:
    """`--clutter hidden`: an object in front of the base that leaves 20-35 % of it visible (clutter.hide_base),
    added to the scene; returns the share left visible by it alone."""
    base = scene.objects[:scene.n_base]

    def visible_share(mesh: trimesh.Trimesh, T: np.ndarray) -> float:
        hits = cast(Scene(base + [SceneObject(None, mesh, T, (0, 0, 0))], scene.T_world_base, scene.base_centre,
                          scene.base_diameter, n_base=len(base)), grid, T_world_camera)
        full = np.zeros(hits.labels.shape, bool)
        for i in range(len(base)):
            if i in hits.windows:
                (v0, v1, u0, u1), m = hits.windows[i]
                full[v0:v1, u0:u1] |= m
        return float((hits.labels[full] < len(base)).sum()) / max(int(full.sum()), 1)

    mesh, T, share = hide_base([(o.mesh, o.T_world_obj) for o in base], T_world_camera, rng, visible_share)
    colour = tuple(float(c) for c in rng.uniform(0.15, 0.95, 3))
    pattern = Pattern.draw(rng, scene.base_diameter) if scene.table_pattern is not None else None
    scene.objects.append(SceneObject(None, mesh, T, colour, pattern))
    return share


def auto_distance_range(base_diameter: float, cam: CameraIntrinsics,
                        fill: tuple[float, float] = (0.25, 0.5)) -> tuple[float, float]:
    """Distances at which the base object spans fill[1] down to fill[0] of the image's short side."""
    side = min(cam.width / cam.fx, cam.height / cam.fy)  # tan-extent of the short side at z = 1
    return base_diameter / (fill[1] * side), base_diameter / (fill[0] * side)


def sample_camera(rng: np.random.Generator, target: np.ndarray, settings: RenderSettings,
                  base_diameter: float) -> np.ndarray:
    """T_world_camera on the hemisphere around `target`, looking at it."""
    yaw = math.radians(rng.uniform(*settings.yaw_range_deg))
    pitch = math.radians(rng.uniform(*settings.pitch_range_deg))
    lo, hi = settings.distance_range_m or auto_distance_range(base_diameter, settings.camera, settings.base_fill)
    dist = rng.uniform(lo, hi)
    return se3.look_at(eye_at(target, dist, yaw, pitch), target)


def eye_at(target: np.ndarray, dist: float, yaw: float, pitch: float) -> np.ndarray:
    """The camera's position `dist` from `target` at `yaw` round it and `pitch` above the table (radians)."""
    return target + dist * np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])


# --------------------------------------------------------------------------------- ray casting


@dataclass
class Hits:
    depth: np.ndarray  # (H, W) float32 metres, 0 where no hit
    labels: np.ndarray  # (H, W) int32 index into the scene's objects, scene.table_label, or -1 (no hit)
    primitive_ids: np.ndarray  # (H, W) int32 triangle index within the object hit, 0 elsewhere
    windows: dict[int, tuple[tuple[int, int, int, int], np.ndarray]]  # object -> (window, its full mask there)

    def object_stats(self, i: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int] | None]:
        """(visible mask within the window, full mask within the window, window) of object i."""
        if i not in self.windows:
            return np.zeros((0, 0), bool), np.zeros((0, 0), bool), None
        (v0, v1, u0, u1), full = self.windows[i]
        return self.labels[v0:v1, u0:u1] == i, full, (v0, v1, u0, u1)


def cast(scene: Scene, grid: RayGrid, T_world_camera: np.ndarray) -> Hits:
    """One ray per pixel, nearest hit wins. Each body is cast alone, in its own frame against its
    cached BVH, over its image box only; that also yields its unoccluded mask. The table is the plane
    z = 0, intersected in closed form where no body was hit (bodies stand on it, so are always nearer).
    """
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    cam = grid.cam
    T_cam_world = se3.inv(T_world_camera)
    depth = np.full((cam.height, cam.width), np.inf, np.float32)
    labels = np.full((cam.height, cam.width), -1, np.int32)
    prims = np.zeros((cam.height, cam.width), np.int32)
    windows = {}
    for i, o in enumerate(scene.objects):
        b = body(o.mesh)
        w = pixel_window(b.corners, T_cam_world @ o.T_world_obj, cam)
        if w is None:
            continue
        rays = grid.rays(se3.inv(o.T_world_obj) @ T_world_camera, w)  # rigid: t along the ray is unchanged
        hit = b.scene.cast_rays(o3d.core.Tensor(rays), nthreads=0)
        t = hit["t_hit"].numpy()
        found = np.isfinite(t)
        windows[i] = (w, found)
        sl = (slice(w[0], w[1]), slice(w[2], w[3]))
        nearer = found & (t < depth[sl])
        depth[sl][nearer] = t[nearer]
        labels[sl][nearer] = i
        prims[sl][nearer] = hit["primitive_ids"].numpy().view(np.int32)[nearer]
    miss = labels < 0
    R, o_z = T_world_camera[:3, :3].astype(np.float32), np.float32(T_world_camera[2, 3])
    dz = grid.dirs[..., 0] * R[2, 0] + grid.dirs[..., 1] * R[2, 1] + R[2, 2]  # world z per unit depth
    with np.errstate(divide="ignore", invalid="ignore"):
        t_table = -o_z / dz
    on = miss & (dz < 0) & (t_table < scene.table_radius)
    labels[on] = scene.table_label
    depth[miss] = 0.0
    depth[on] = t_table[on]
    return Hits(depth, labels, prims, windows)


# --------------------------------------------------------------------------------- appearance and noise


def shade(hit: "Hits", scene: Scene, T_world_camera: np.ndarray, rng: np.random.Generator,
          grid: RayGrid | None = None, lighting: np.random.Generator | None = None) -> np.ndarray:
    """Flat Lambert shading with a random key light, ambient and a weak headlight; slight sensor noise.

    Computed only for the pixels each body covers, from its face normals (flat shading). Printed patterns
    (`--clutter textured`) need `grid` (the pixels' rays) to find the surface point each pixel shows.
    `lighting`: draws the light from this generator instead of `rng` (a trajectory's frames share one light).
    """
    lit = rng if lighting is None else lighting
    elev, azim = lit.uniform(0.5, 1.4), lit.uniform(0, 2 * np.pi)
    light = np.array([math.cos(elev) * math.cos(azim), math.cos(elev) * math.sin(azim), math.sin(elev)])
    ambient, key, gain = lit.uniform(0.25, 0.4), lit.uniform(0.55, 0.85), lit.uniform(0.85, 1.1)
    eye = T_world_camera[:3, 3]
    rgb = np.empty(hit.labels.shape + (3,), np.float32)
    rgb[:] = (0.08, 0.08, 0.1)  # background
    table_lit = ambient + key * max(light[2], 0.0) + 0.2 * max(float(-T_world_camera[2, 2]), 0.0)
    on_table = hit.labels == scene.table_label
    if scene.table_pattern is not None and grid is not None:
        rgb[on_table] = scene.table_pattern.colours(_surface_points(hit, on_table, T_world_camera, grid),
                                                    scene.table_color) * table_lit
    else:
        rgb[on_table] = np.asarray(scene.table_color) * table_lit
    for i, o in enumerate(scene.objects):
        if i not in hit.windows:
            continue
        (v0, v1, u0, u1), _ = hit.windows[i]
        lab = hit.labels[v0:v1, u0:u1]
        sel = lab == i
        if not sel.any():
            continue
        # per hit pixel, in the object's frame with its cached face normals
        b = body(o.mesh)
        faces = hit.primitive_ids[v0:v1, u0:u1][sel]
        R, t = o.T_world_obj[:3, :3], o.T_world_obj[:3, 3]
        n = b.normals[faces]
        to_eye = R.T @ (eye - t) - b.first[faces]
        facing = np.einsum("ij,ij->i", n, to_eye)
        sign = np.where(facing < 0, -1.0, 1.0)  # light the side that faces the camera
        lit = (ambient + key * np.clip(sign * (n @ (R.T @ light)), 0, None)
               + 0.2 * np.abs(facing) / np.maximum(np.linalg.norm(to_eye, axis=1), 1e-20))
        block = rgb[v0:v1, u0:u1]
        colour = np.asarray(o.color, np.float32)[None, :]
        if o.pattern is not None and grid is not None:
            window = np.zeros(hit.labels.shape, bool)
            window[v0:v1, u0:u1] = sel
            colour = o.pattern.colours(se3.transform_points(se3.inv(o.T_world_obj),
                                                            _surface_points(hit, window, T_world_camera, grid)), o.color)
        block[sel] = colour * lit[:, None].astype(np.float32)
    rgb = (np.clip(rgb * gain, 0, 1) * 255 + 0.5).astype(np.int16)
    h, w = rgb.shape[:2]
    dv, du = rng.integers(0, 64, 2)  # sensor noise: a random window of a fixed noise texture
    rgb += noise_texture(h, w)[dv:dv + h, du:du + w, None]
    return np.clip(rgb, 0, 255).astype(np.uint8)


def _surface_points(hit: "Hits", pixels: np.ndarray, T_world_camera: np.ndarray, grid: RayGrid) -> np.ndarray:
    """(N, 3) world points the chosen pixels show (row-major order, as rgb[pixels])."""
    return se3.transform_points(T_world_camera, grid.dirs[pixels] * hit.depth[pixels][:, None])


# --------------------------------------------------------------------------------- one frame


def render_frame(models: dict[str, PartModel], view: StepView, settings: RenderSettings, grid: RayGrid,
                 rng: np.random.Generator, base: trimesh.Trimesh | None = None, noise: bool = True) -> RenderedFrame:
    """One view of a step. With noise=False the depth is clean and `noisy_depth(frame, settings)` adds
    the noise later (the dataset writer does that in its threads); the result is the same either way."""
    scene = sample_scene(models, view, settings, rng, base)
    T_world_camera = sample_camera(rng, scene.base_centre, settings, scene.base_diameter)
    if "hidden" in settings.clutter:
        hide(scene, T_world_camera, grid, rng)
    return view_of(scene, T_world_camera, grid, rng, settings if noise else None)


def view_of(scene: Scene, T_world_camera: np.ndarray, grid: RayGrid, rng: np.random.Generator,
            settings: RenderSettings | None = None, lighting: np.random.Generator | None = None) -> RenderedFrame:
    """The scene seen from T_world_camera; with `settings`, its depth noise added (else clean). `lighting`:
    see `shade`."""
    hit = cast(scene, grid, T_world_camera)
    rgb = shade(hit, scene, T_world_camera, rng, grid, lighting)
    frame = RenderedFrame(rgb, hit.depth, T_world_camera, scene, hit, int(rng.integers(2**62)))
    if settings is not None:
        frame.depth = noisy_depth(frame, settings)
    return frame


def noisy_depth(frame: RenderedFrame, settings: RenderSettings) -> np.ndarray:
    """The frame's depth as the sensor gives it: its noise model, near surfaces bled `bleed_px` wider, then a
    constant bias (`depth_bias_m`) and the depth image shifted against the colour image by `misregistration_px` in
    a direction drawn per frame."""
    depth = add_depth_noise(frame.hits.depth, settings.noise, settings.noise_sigma_at_05m,
                            np.random.default_rng(frame.noise_seed), settings.camera.fx, rgb=frame.rgb)
    depth = bleed(depth, settings.bleed_px)
    if settings.depth_bias_m:
        depth = np.where(depth > 0, depth + np.float32(settings.depth_bias_m), 0).astype(np.float32)
    if settings.misregistration_px:
        du, dv = misregistration(frame.noise_seed, settings.misregistration_px)
        depth = shift_image(depth, du, dv)
    return depth


def misregistration(noise_seed: int, px: float) -> tuple[int, int]:
    """(du, dv): how far a frame's depth image is shifted against its colour image (`px` long, whole pixels,
    its direction drawn from the frame's noise seed)."""
    angle = np.random.default_rng([noise_seed, 1]).uniform(0, 2 * np.pi)
    return int(round(px * np.cos(angle))), int(round(px * np.sin(angle)))


