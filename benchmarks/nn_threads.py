#!/usr/bin/env python3
"""Nearest-neighbour queries (geometry/nn.py, ICP's hot path) by OpenMP threads and wait policy, on a quiet
machine and with every core busy with other work.

    .venv/bin/python benchmarks/nn_threads.py [--queries 300]

Each setting runs in its own process (OpenMP reads OMP_WAIT_POLICY once, when it loads): a k-d tree of
3,000 points, 2,500 query points within 1 cm, as an ICP step of the estimator asks (with a little other
numpy work between, as ICP does). "busy": as many processes as CPUs spin in plain Python beside it (a
robot PC's other work, a CI job, a second estimate). Prints the median and 90th percentile per query.
apose_studio sets OMP_WAIT_POLICY=PASSIVE unless the user set it (apose_studio/__init__.py).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def measure(n: int) -> None:
    sys.path.insert(0, str(REPO))
    import apose_studio  # noqa: F401  (first: its thread settings, as a program using it has them)

    # isort: split
    import numpy as np

    from apose_studio.geometry.nn import NN_THREADS, NearestTree

    rng = np.random.default_rng(0)
    tree = NearestTree(rng.random((3000, 3)) * 0.1)
    src = rng.random((2500, 3)) * 0.1
    ts = []
    for i in range(n):
        t = time.perf_counter()
        tree.query(src, distance_upper_bound=0.01)
        ts.append(time.perf_counter() - t)
        if i % 3 == 0:
            np.linalg.svd(rng.random((50, 50)))
    print(f"{NN_THREADS} {np.median(ts) * 1000:.3f} {np.percentile(ts, 90) * 1000:.3f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=300)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        measure(args.queries)
        return 0
    cpus = len(os.sched_getaffinity(0))
    rows = []
    for busy in (False, True):
        burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cpus if busy else 0)]
        try:
            time.sleep(0.5 if busy else 0.0)
            for threads in ("1", "2"):
                for policy in ("ACTIVE", "PASSIVE"):
                    env = {**os.environ, "APOSE_NN_THREADS": threads, "OMP_WAIT_POLICY": policy,
                           "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE", "Haswell")}
                    out = subprocess.run([sys.executable, __file__, "--child", "--queries", str(args.queries)], env=env,
                                         capture_output=True, text=True, check=True).stdout.split()
                    rows.append((("busy" if busy else "quiet"), out[0], policy, float(out[1]), float(out[2])))
        finally:
            for b in burners:
                b.kill()
                b.wait()
    print(f"nearest-neighbour query, 2,500 points in a 3,000-point tree, {cpus} CPUs "
          f"({time.strftime('%Y-%m-%d')})\n")
    print("| machine | threads | OMP_WAIT_POLICY | median ms | p90 ms |\n|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.2f} | {r[4]:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
