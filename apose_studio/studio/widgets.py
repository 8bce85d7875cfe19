"""Small pieces every panel uses: constants, HTML escaping, colours, poses for viser (wxyz, position), the
scene point under a click."""

from __future__ import annotations

import html

import numpy as np

from apose_studio.errors import AposeError
from apose_studio.geometry import se3
from apose_studio.geometry.units import MAX_ANGLE_DEG, MAX_COORDINATE_M
from apose_studio.studio import inspection

MAX_UPLOAD_BYTES = 200 * 1024 * 1024  # a CAD part above this is almost surely the wrong file
UNITS = ("m", "cm", "mm", "in")
VIEWS = ("Assembly", "Inspect")
ACTIVE = "● "  # marks the 3D view on show in the button group
# Ranges of the number fields (the page's input is checked against them on the server, viser_adapter.py):
MM_RANGE = {"min": -MAX_COORDINATE_M * 1000.0, "max": MAX_COORDINATE_M * 1000.0}  # a length or position in mm: 10 km, the core's coordinate limit
DEG_RANGE = {"min": -MAX_ANGLE_DEG, "max": MAX_ANGLE_DEG}  # a typed angle in degrees (ten turns either way)
VECTOR_MM = {k: (v,) * 3 for k, v in MM_RANGE.items()}
VECTOR_DEG = {k: (v,) * 3 for k, v in DEG_RANGE.items()}
LAYERS = ("scene cloud", "target cloud", "source cloud", "boxes", "part at estimate", "base at estimate", "gripper",
          "robot base", "labels", "camera")


SHARP_EDGE_DEG = 30.0  # faces meeting at a sharper angle than this are drawn with a crease, not smoothed over


def shaded(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float32, faces uint32) of a mesh as the 3D view should draw it: faces split apart along
    edges sharper than SHARP_EDGE_DEG, so the browser's smooth shading keeps a box's edges crisp and a
    cylinder round (shared vertices averaged every normal and made faceted CAD look melted)."""
    from trimesh import graph

    m = graph.smooth_shade(mesh, angle=np.radians(SHARP_EDGE_DEG))
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)


def esc(text) -> str:
    """User- or file-derived text made safe to place in HTML or markdown (part ids, file names, messages)."""
    return html.escape(str(text), quote=True)


def hex_colour(color) -> str:
    return "#" + "".join(f"{int(round(255 * c)):02x}" for c in color)


def legend_html(shown=None) -> str:
    """The colours of the Inspect view, each with its name; `shown`: the names drawn now (an entry is
    listed when its name before any " (" is one of them: "truth" lists "truth (dashed)"; "estimate on truth", the
    label of both boxes in one place, lists both), None: all of them. A capture has no truth, and a frame not yet
    estimated no estimate: the legend lists only what is there."""
    if shown is not None and "estimate on truth" in shown:
        shown = set(shown) | {"estimate", "truth"}
    entries = [(name, rgb) for name, rgb in inspection.LEGEND if shown is None or name.split(" (")[0] in shown]
    items = "".join(f"<span style='white-space:nowrap;margin-right:10px'><span style='display:inline-block;width:14px;"
                    f"height:4px;vertical-align:middle;background:{hex_colour([c / 255 for c in rgb])}'></span> {esc(name)}</span>"
                    for name, rgb in entries)
    return f"<div style='font-size:0.8em;line-height:1.8'>{items}</div>"


def wxyz(T: np.ndarray) -> tuple:
    return tuple(float(v) for v in se3.matrix_to_quat_wxyz(T[:3, :3]))


def pos(T: np.ndarray) -> tuple:
    return tuple(float(v) for v in T[:3, 3])


def scene_point_at_ray(frame, origin, direction) -> np.ndarray:
    """The first depth point of `frame` on a click's ray (world, metres); AposeError when the ray meets none."""
    pts, _ = inspection.scene_cloud(frame.depth, frame.rgb, frame.camera, frame.T_world_camera)
    hit = inspection.point_on_ray(pts, np.asarray(origin, float), np.asarray(direction, float),
                                  max_offset=0.01 * float(np.median(frame.depth[frame.depth > 0])))
    if hit is None:
        raise AposeError("the click hit no depth point; click on the object itself")
    return hit


def pixel_at_ray(frame, origin, direction) -> str:
    """The pixel "u,v" of `frame` that a click's ray meets first (scene_point_at_ray), as a point prompt's text."""
    hit = scene_point_at_ray(frame, origin, direction)
    u, v = frame.camera.project(se3.transform_points(se3.inv(frame.T_world_camera), hit[None]))
    return f"{int(round(float(u[0])))},{int(round(float(v[0])))}"


def send_download(client, filename: str, content: bytes) -> None:
    """`content` saved by the browser of `client` as `filename` at once, as a button's click promises
    (viser's `save_immediately`): viser's default shows a link in a notification that a second click saves,
    and users took the first click's notification for the download done."""
    if client is None:
        raise AposeError("no browser to send the download to")
    client.send_file_download(filename, content, save_immediately=True)
