"""The runtime settings apose_studio makes when it loads (apose_studio/__init__.py): one Open3D thread (its
seeded RANSAC repeats), one OpenBLAS thread and sleeping OpenMP waits (speed on a busy machine,
benchmarks/nn_threads.py); each only where the user set nothing, and in time for the libraries that read them."""

import os
import subprocess
import sys

KEYS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_WAIT_POLICY")
SHOW = "import os, apose_studio, numpy; print(' '.join(os.environ[k] for k in %r))" % (KEYS,)


def run(env: dict) -> list[str]:
    clean = {k: v for k, v in os.environ.items() if k not in KEYS}
    out = subprocess.run([sys.executable, "-c", SHOW], env={**clean, **env}, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_defaults_are_set_and_a_users_own_values_win():
    assert run({}) == ["1", "1", "PASSIVE"]
    assert run({"OPENBLAS_NUM_THREADS": "2", "OMP_WAIT_POLICY": "ACTIVE"}) == ["1", "2", "ACTIVE"]


def test_the_nearest_neighbour_threads_still_answer_alike():
    """pykdtree's threads asleep between queries give the same neighbours as one thread."""
    code = ("import apose_studio, numpy as np; from apose_studio.geometry.nn import NearestTree; "
            "r = np.random.default_rng(1); t = NearestTree(r.random((3000, 3))); "
            "d, i = t.query(r.random((5000, 3)), k=3); print(hash((d.tobytes(), i.tobytes())))")
    outs = set()
    for threads in ("1", "2"):
        env = {**os.environ, "APOSE_NN_THREADS": threads, "PYTHONHASHSEED": "0"}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        outs.add(out.stdout.strip())
    assert len(outs) == 1
