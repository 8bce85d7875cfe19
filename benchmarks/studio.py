#!/usr/bin/env python3
"""Studio responsiveness: loading a 500k-triangle part, picking its faces, switching frames with cached results.

    .venv/bin/python benchmarks/studio.py [--triangles 500000] [--frames 6] [--browser]

Part load: from pressing "Add part(s)" (a binary STL path typed on the server, in mm) until the part
is listed, checked (diameter, boxes, unit check, surface samples) and its mesh is a scene node: the
same callback the button runs. Frame switch: moving the Frame slider to a frame whose estimate is
cached: the frame is read from disk (JPEG, depth and mask PNGs), its scene cloud, boxes, 2D box
projection, clouds and metrics panel are rebuilt and queued to the browser. With --browser, a
headless Chromium is connected so the messages are really sent. Pick a face: a click in the 3D view
(the Mates folder's scene-click callback, a ray straight at a random triangle of the part): cast into
every shown part, the face grown from the nearest hit, fitted, highlighted; on a 500k-triangle bolt (a round shank of many facets and flat
ends) and on the torus (one smooth face of every triangle: the worst case). The face grouping is
built once per part when its step is selected (in the background; timed apart as "prepare").
Goals: < 2 s, < 200 ms (pick) and < 200 ms (switch).
"""

from __future__ import annotations

import apose_studio  # noqa: F401  (first: its thread settings apply only before numpy loads)

# isort: split

import argparse
import atexit
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from apose_studio.assembly.model import load_assembly  # noqa: E402
from apose_studio.studio import serve  # noqa: E402
from apose_studio.synth.frame import RenderSettings  # noqa: E402
from apose_studio.synth.render import render_dataset


def dense_torus(triangles: int):
    """A torus of about `triangles` triangles, 80 mm across (a stand-in for a fine CAD export)."""
    import trimesh

    n = int(np.sqrt(triangles / 2))
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n, endpoint=False), np.linspace(0, 2 * np.pi, n, endpoint=False))
    R, r = 30.0, 10.0
    verts = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    a, b, c, d = i * n + j, i * n + (j + 1) % n, ((i + 1) % n) * n + j, ((i + 1) % n) * n + (j + 1) % n
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(verts, faces, process=False)


def dense_bolt(triangles: int):
    """A bolt-like part of about `triangles` triangles: a 10 mm shank, 40 mm long, on a 16 mm head."""
    import trimesh

    sections = max(triangles // 8, 16)
    shank = trimesh.creation.cylinder(radius=5.0, height=40.0, sections=sections)
    head = trimesh.creation.cylinder(radius=8.0, height=6.0, sections=sections)
    head.apply_translation((0, 0, -23.0))
    return trimesh.util.concatenate([shank, head])


class Click:
    client = None


class Ray:
    client = None

    def __init__(self, origin, direction):
        self.ray_origin, self.ray_direction = tuple(origin), tuple(direction)


def time_picks(st, stl: Path, n: int = 20) -> tuple[float, list[float], int]:
    """(prepare seconds, pick seconds each, picks that found a flat or round face) for a part placed by a
    new step, clicked straight at random triangles."""
    from apose_studio.geometry import se3

    st.files.f_mesh.value = str(stl)
    st.guarded("add")(lambda c: st.files.on_add_parts(c))(Click())
    pid = [p for p in st.asm.parts if p.startswith(stl.stem)][-1]
    from apose_studio.assembly.model import Step
    from apose_studio.studio import authoring

    step = Step(pid, (st.asm.roots[0],), se3.make_T(t=np.array([0.1, 0.0, 0.0])))  # beside the base
    st.steps.step_index = len(st.asm.steps)
    st.guarded("add step")(lambda c: st.set_assembly(authoring.add_step(st.asm, step), c))(Click())
    st.show_view("Assembly")
    t0 = time.perf_counter()
    st.mates.picker(pid)
    prepare = time.perf_counter() - t0
    for other in st.steps.mesh_handles:  # a click is cast into every shown part: theirs are ready too
        if other in st.asm.parts:
            st.mates.picker(other)
    T = st.steps.T_world_shown(pid)
    mesh = st.model(pid).mesh
    rng = np.random.default_rng(0)
    picks, found = [], 0
    for f in rng.choice(len(mesh.faces), n, replace=False):  # straight at a random triangle, from outside
        p = se3.transform_points(T, mesh.triangles_center[f][None])[0]
        d = T[:3, :3] @ mesh.face_normals[f]
        t0 = time.perf_counter()
        st.guarded("pick")(lambda c: st.mates.on_click(Ray(p + 0.05 * d, -d)))(Click())
        picks.append(time.perf_counter() - t0)
        found += "part" in st.mates.picks  # the torus is refused: neither flat nor round
        st.mates.clear_picks()
    return prepare, picks, found


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=500_000)
    ap.add_argument("--frames", type=int, default=6, help="frames to render and switch between (default 6)")
    ap.add_argument("--browser", action="store_true", help="connect headless Chromium while measuring")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="apose-bench-studio-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # renders and copies: gone when the run ends
    mesh = dense_torus(args.triangles)
    stl = tmp / "dense_part.stl"
    mesh.export(stl)
    sample = REPO / "sample_assemblies" / "helical_gearbox" / "assembly.yaml"
    ds = tmp / "ds"
    render_dataset(load_assembly(sample), ds, RenderSettings(frames=args.frames, noise="realsense", base_pose="fixed", seed=2),
                   steps=[2], progress=False)

    server, st = serve(sample, ds, port=8765, root=tmp, tabs=False)  # the workspace: the part to load is in tmp
    pw = browser = None
    if args.browser:
        from playwright.sync_api import sync_playwright

        pw = sync_playwright().start()
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=[
            "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        page = browser.new_page()
        page.goto(st.url)
        page.get_by_role("button", name="Add part(s)").wait_for(timeout=30000)
    try:
        loads = []
        for k in range(3):  # each load adds a new part (dense_part, dense_part_2, ...): nothing is cached
            st.files.f_mesh.value = str(stl)
            t0 = time.perf_counter()
            st.guarded("add")(lambda c: st.files.on_add_parts(c))(Click())
            loads.append(time.perf_counter() - t0)
            pid = [p for p in st.asm.parts if p.startswith("dense_part")][-1]
            assert pid in st.steps.mesh_handles, "the part did not load"
        bolt = tmp / "dense_bolt.stl"
        dense_bolt(args.triangles).export(bolt)
        pick_rows = [(f"{n:,}-triangle {what}", *time_picks(st, f)) for what, f, n in (
            ("bolt", bolt, len(dense_bolt(args.triangles).faces)), ("torus", stl, len(mesh.faces)))]
        st.inspect.i_prior.value = True
        st.guarded("estimate")(lambda c: st.inspect.run_estimation(True, c))(Click())  # fills the cache
        assert len(st.cache) == args.frames, "estimation did not cache every frame"
        switches = []
        for rep in range(3):
            for f in range(args.frames):
                t0 = time.perf_counter()
                st.inspect.i_frame.value = f
                switches.append(time.perf_counter() - t0)
                assert st.inspect.result is not None
    finally:
        if browser is not None:
            browser.close()
            pw.stop()
        server.stop()
    print(f"\nmachine: {os.cpu_count()} cores; browser connected: {'yes' if args.browser else 'no'}\n")
    print(f"{'measure':<46} {'median':>9} {'max':>9} {'goal':>8}")
    print(f"{f'load a {len(mesh.faces):,}-triangle STL part (3 cold loads)':<46} {statistics.median(loads):>8.2f}s {max(loads):>8.2f}s {'< 2 s':>8}")
    for what, prepare, picks, found in pick_rows:
        print(f"{f'pick a face of the {what}':<46} {statistics.median(picks) * 1000:>7.0f}ms "
              f"{max(picks) * 1000:>7.0f}ms {'< 200 ms':>8}   {found}/{len(picks)} clicks found a flat or round face")
        print(f"{'  prepare its faces (once, in the background)':<46} {prepare:>8.2f}s {'':>9} {'':>8}")
    print(f"{f'switch frame, cached estimate ({len(switches)} switches)':<46} {statistics.median(switches) * 1000:>7.0f}ms "
          f"{max(switches) * 1000:>7.0f}ms {'< 200 ms':>8}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
