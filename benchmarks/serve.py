#!/usr/bin/env python3
"""`apose serve` under load: latency, overhead, memory and bad requests, against issue #29's goals.

    .venv/bin/python benchmarks/serve.py [--clients 4] [--per-client 200] [--sequential 200] [--bad 100]

Starts `apose serve` on the planetary reducer sample as its own process (its memory is read from
/proc), renders a few RealSense-like frames of step 2 once, and sends them as PNGs in the request JSON:

1. sequential: one client, one request after the other. Per request: the client's latency, the
   estimate's own compute (`timings_s.total`, from reading the images to the answer) and the service's
   overhead (latency - compute: HTTP, JSON, base64, PNG decoding), split into what the service spends
   (`timings_s.service` - compute) and the rest (connection, transfer, client); each request is sent twice,
   as JSON with PNGs and as an NPZ body of raw arrays (Content-Type application/x-npz), interleaved.
2. concurrent: `--clients` clients, `--per-client` requests each, all at once (the queue is sized for
   them): latency, failures. The service estimates one frame at a time (both cores serve that one's
   queries), so a request waits for those ahead of it: the p95 latency of k concurrent clients is about
   k x the compute, which the table prints beside the goal.
3. memory: the service's resident memory after the warm-up and after every request above.
4. bad requests: `--bad` malformed requests of ten kinds (bad JSON, wrong sizes, NaN intrinsics, a huge
   declared body, an unknown step, ...): each must get a 4xx, and the service must answer a good request after.

Goals (#29): p95 latency <= 1.5 x one warm call's compute under 4 clients; memory growth <= 50 MB over
1,000 requests; 0 failed good requests; every bad request a 4xx; warm overhead <= 10 ms.
"""

from __future__ import annotations

import apose_studio  # noqa: F401  (first: its thread settings apply only before numpy loads)

# isort: split

import argparse
import base64
import http.client
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
PLANETARY = REPO / "sample_assemblies" / "planetary_reducer" / "assembly.yaml"


def frames(n: int) -> list[dict]:
    """n rendered frames of planetary step 2 as request bodies (with a box prompt from the truth)."""
    from apose_studio.assembly.mesh import base_mesh, load_parts
    from apose_studio.assembly.model import load_assembly
    from apose_studio.estimation import truth_box
    from apose_studio.geometry.raycast import RayGrid
    from apose_studio.synth.frame import RenderSettings, render_frame

    asm = load_assembly(PLANETARY)
    models = load_parts(asm)
    s = RenderSettings(noise="realsense", seed=29, camera=asm.camera or RenderSettings().camera)
    view = asm.step_view(2)
    mesh = base_mesh(models, view)
    out = []
    for i in range(n):
        fr = render_frame(models, view, s, RayGrid(s.camera), np.random.default_rng([29, 2, i]), mesh)
        mask = np.zeros(fr.depth.shape, bool)
        for j, o in enumerate(fr.scene.objects):
            if o.part in view.T_base_members:
                mask |= fr.labels == j
        c = s.camera
        png = lambda img: base64.b64encode(cv2.imencode(".png", img)[1].tobytes()).decode()  # noqa: E731
        out.append({"rgb_png_b64": png(fr.rgb[..., ::-1]), "depth_png_b64": png((fr.depth * 1000).astype(np.uint16)),
                    "camera": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "depth_scale": 1.0}, "step": 2,
                    "box": list(truth_box(mask)),
                    "hand_eye": {"T_robot_camera": np.eye(4).tolist()}})
    return out


def npz_of(doc: dict) -> bytes:
    """The same request as an NPZ body (Content-Type application/x-npz): raw arrays, no base64, no PNG."""
    import io

    f = io.BytesIO()
    rgb = cv2.imdecode(np.frombuffer(base64.b64decode(doc["rgb_png_b64"]), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    depth = cv2.imdecode(np.frombuffer(base64.b64decode(doc["depth_png_b64"]), np.uint8), cv2.IMREAD_UNCHANGED)
    keys = {k: v for k, v in doc.items() if not k.endswith("_png_b64")}
    np.savez(f, rgb=np.ascontiguousarray(rgb), depth=depth, request=np.array(json.dumps(keys)))
    return f.getvalue()


NPZ = {"Content-Type": "application/x-npz"}


def post(port: int, body: bytes, headers: dict | None = None) -> tuple[int, dict, float]:
    t = time.perf_counter()
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=600)
    conn.request("POST", "/estimate", body=body, headers={"Content-Type": "application/json", **(headers or {})})
    r = conn.getresponse()
    doc = json.loads(r.read() or b"{}")
    conn.close()
    return r.status, doc, time.perf_counter() - t


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def pct(xs, q) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--per-client", type=int, default=200)
    ap.add_argument("--sequential", type=int, default=200)
    ap.add_argument("--bad", type=int, default=100)
    ap.add_argument("--frames", type=int, default=6)
    args = ap.parse_args()
    bodies = [json.dumps(b).encode() for b in frames(args.frames)]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "apose_studio.cli.commands", "serve", str(PLANETARY), "--port",
                             str(port), "--queue", str(max(args.clients, 1) + 1)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        print(proc.stdout.readline().strip())
        for b in bodies:  # warm-up: the first call of each frame size and the imports behind the first answer
            post(port, b)
        rss0 = rss_mb(proc.pid)
        seq_lat, seq_compute, seq_over, seq_in, failed = [], [], [], [], 0
        npz_over, npz_in = [], []
        npz_bodies = [npz_of(json.loads(b)) for b in bodies]
        post(port, npz_bodies[0], NPZ)
        for i in range(args.sequential):
            for fmt in ("json", "npz"):  # interleaved: both formats see the same machine
                status, doc, lat = (post(port, bodies[i % len(bodies)]) if fmt == "json" else
                                    post(port, npz_bodies[i % len(bodies)], NPZ))
                failed += status != 200
                if status != 200:
                    continue
                over = lat - doc["timings_s"]["total"]
                inside = doc["timings_s"]["service"] - doc["timings_s"]["total"]  # reading, decoding, answering
                if fmt == "npz":
                    npz_over.append(over)
                    npz_in.append(inside)
                    continue
                seq_lat.append(lat)
                seq_compute.append(doc["timings_s"]["total"])
                seq_over.append(over)
                seq_in.append(inside)
        conc_lat: list[float] = []
        conc_failed = [0]
        lock = threading.Lock()

        def client(k: int) -> None:
            for i in range(args.per_client):
                status, _, lat = post(port, bodies[(k + i) % len(bodies)])
                with lock:
                    conc_lat.append(lat)
                    conc_failed[0] += status != 200

        t0 = time.perf_counter()
        threads = [threading.Thread(target=client, args=(k,)) for k in range(args.clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
        rss1 = rss_mb(proc.pid)
        n_total = len(bodies) + 1 + 2 * args.sequential + args.clients * args.per_client
        good = json.loads(bodies[0])
        kinds = [
            b"{not json", json.dumps([1]).encode(), json.dumps(dict(good, step=99)).encode(),
            json.dumps(dict(good, camera=dict(good["camera"], fx=float("nan")))).encode().replace(b"NaN", b"NaN"),
            json.dumps(dict(good, camera=dict(good["camera"], fx=-1))).encode(),
            json.dumps(dict(good, rgb_png_b64="@@@")).encode(),
            json.dumps(dict(good, depth_png_b64=good["rgb_png_b64"])).encode(),
            json.dumps(dict(good, box=[1, 2])).encode(), json.dumps(dict(good, extra=1)).encode(),
            None,  # a body declared at 1 GB
        ]
        bad_status = []
        for i in range(args.bad):
            body = kinds[i % len(kinds)]
            if body is None:
                status, _, _ = post(port, b"x", {"Content-Length": str(2 ** 30)})
            else:
                status, _, _ = post(port, body)
            bad_status.append(status)
        after_status, after_doc, _ = post(port, bodies[0])
        rss2 = rss_mb(proc.pid)
    finally:
        proc.terminate()
        proc.wait(30)
    compute = statistics.median(seq_compute)
    goal_p95 = 1.5 * compute
    print(f"\napose serve, planetary step 2 (640x480 RealSense-like frames as PNG), {os.cpu_count()} CPUs")
    print("| measure | value | goal |\n|---|---|---|")
    print(f"| sequential: latency median / p95 | {statistics.median(seq_lat) * 1000:.0f} / {pct(seq_lat, 95) * 1000:.0f} ms | |")
    print(f"| sequential: compute median (timings_s.total) | {compute * 1000:.0f} ms | |")
    print(f"| sequential, JSON body (PNGs in base64): overhead (latency - compute) median / p95 | {statistics.median(seq_over) * 1000:.1f} / "
          f"{pct(seq_over, 95) * 1000:.1f} ms | <= 10 ms: {'met' if statistics.median(seq_over) <= 0.010 else 'NOT met'} |")
    print(f"| sequential, NPZ body (raw arrays: no base64, no PNG): overhead median / p95; in the service | "
          f"{statistics.median(npz_over) * 1000:.1f} / {pct(npz_over, 95) * 1000:.1f} ms; "
          f"{statistics.median(npz_in) * 1000:.1f} ms | <= 10 ms: {'met' if statistics.median(npz_over) <= 0.010 else 'NOT met'} |")
    inside = statistics.median(seq_in)
    print(f"| overhead: in the service (body read, base64, PNG decoding, JSON) / outside it (connection, transfer, "
          f"client) median | {inside * 1000:.1f} / {(statistics.median(seq_over) - inside) * 1000:.1f} ms | |")
    print(f"| {args.clients} clients x {args.per_client}: latency median / p95 | {statistics.median(conc_lat) * 1000:.0f} / "
          f"{pct(conc_lat, 95) * 1000:.0f} ms ({args.clients * args.per_client / wall:.1f} requests/s) | p95 <= 1.5 x compute "
          f"= {goal_p95 * 1000:.0f} ms: {'met' if pct(conc_lat, 95) <= goal_p95 else 'NOT met'} |")
    print(f"| failed good requests | {failed + conc_failed[0]} of {2 * args.sequential + args.clients * args.per_client} | 0: "
          f"{'met' if failed + conc_failed[0] == 0 else 'NOT met'} |")
    print(f"| memory: after warm-up, after {n_total} requests, after the bad ones | {rss0:.0f} / {rss1:.0f} / {rss2:.0f} MB "
          f"(growth {rss1 - rss0:+.0f} MB) | <= 50 MB: {'met' if rss1 - rss0 <= 50 else 'NOT met'} |")
    n4 = sum(400 <= s < 500 for s in bad_status)
    print(f"| bad requests answered 4xx | {n4} of {len(bad_status)}; then a good one: {after_status} "
          f"({'ok' if after_doc.get('ok') else after_doc.get('error', '')}) | all, and 200 after: "
          f"{'met' if n4 == len(bad_status) and after_status == 200 else 'NOT met'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
