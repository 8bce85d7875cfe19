"""Same input, same answer: a capture estimated in two fresh processes gives identical masks and poses,
bit for bit (depth masks with and without a box prompt; the default preset, deterministic by default),
also while other processes keep every core busy (the searches are bounded by counts, not by the clock)."""

import json
import os
import subprocess
import sys

import numpy as np

from ..conftest import SAMPLES, write_capture

SCRIPT = r"""
import hashlib, json, sys
from apose_studio.registration.types import View
from apose_studio.assembly.model import load_assembly
from apose_studio.data.dataset import load_capture
from apose_studio.estimation import StepContext
from apose_studio.assembly.mesh import load_parts
from apose_studio.registration import estimate, resolve_params
from apose_studio.masks.segment import depth_mask

cap, asm_path, box = sys.argv[1], sys.argv[2], tuple(json.loads(sys.argv[3]))
fr = load_capture(cap)
asm = load_assembly(asm_path)
ctx = StepContext(asm, load_parts(asm), 1)
out = []
for b in (None, box):
    m = depth_mask(fr.depth, fr.camera, box=b)
    for prior, upright in ((None, True), (None, False), ("cad", True)):  # upright search, free RANSAC search, prior
        r = estimate(View(fr.depth, m, fr.camera, fr.T_world_camera), ctx.base, ctx.view.T_base_part,
                     resolve_params("default", upright=upright),
                     prior_T_world_base=None if prior is None else __import__("numpy").eye(4))
        out.append([hashlib.sha256(m.tobytes()).hexdigest(), int(m.sum()), r.ok,
                    None if r.T_world_part is None else r.T_world_part.tobytes().hex(), r.reason])
print(json.dumps(out))
"""


def _capture(gearbox_dataset, tmp_path):
    from apose_studio.data.dataset import Dataset

    fr = Dataset(gearbox_dataset).frame(1, 1)
    cap = write_capture(fr, tmp_path / "capture")
    vs, us = np.nonzero(fr.base_mask())
    return cap, [int(us.min()) - 5, int(vs.min()) - 5, int(us.max()) + 5, int(vs.max()) + 5]


def _estimate_in_fresh_process(cap, box) -> list:
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}  # the shipped default
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(cap), str(SAMPLES / "helical_gearbox" / "assembly.yaml"),
                        json.dumps(box)], capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_two_fresh_processes_give_identical_masks_and_poses(gearbox_dataset, tmp_path):
    cap, box = _capture(gearbox_dataset, tmp_path)
    runs = [_estimate_in_fresh_process(cap, box) for _ in range(2)]
    assert runs[0] == runs[1]
    for digest, pixels, ok, pose, reason in runs[0]:
        assert pixels > 1000 and ok, reason  # a real mask and a pose, not two identical failures


def test_the_same_answer_while_every_core_is_busy(gearbox_dataset, tmp_path):
    """Two estimates run side by side in fresh processes while one busy loop per core runs beside them
    (three times the work the machine can do at once) give the poses of an idle run, bit for bit."""
    cap, box = _capture(gearbox_dataset, tmp_path)
    idle = _estimate_in_fresh_process(cap, box)
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 2)]
    try:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(2) as pool:
            loaded = list(pool.map(lambda _: _estimate_in_fresh_process(cap, box), range(2)))
    finally:
        for b in burners:
            b.kill()
            b.wait()
    assert loaded[0] == idle and loaded[1] == idle
    assert all(ok for _, _, ok, _, _ in idle)
