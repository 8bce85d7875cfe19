"""Many instances of a base in one frame (`apose estimate --instances all`): three identical casings (three roots
with one mesh file) rendered on a cluttered bench; every instance checked against the renderer's truth, which
the finder never sees."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from apose_studio.assembly.model import load_assembly
from apose_studio.data.dataset import Dataset
from apose_studio.estimation import estimate_instances, step_context
from apose_studio.geometry import se3
from apose_studio.params import resolve_params
from apose_studio.synth.frame import RenderSettings
from apose_studio.synth.render import render_dataset
from tests.conftest import SAMPLES, mssd_to_truth

CASINGS = ("casing", "casing_b", "casing_c")


@pytest.fixture(scope="module")
def three_casings(tmp_path_factory):
    """The helical gearbox with two more casings as roots (the same casing.stl): step 1 (the pinion onto the
    casing) has two twins; 6 RealSense-like frames of a bench with clutter touching the casing."""
    d = tmp_path_factory.mktemp("instances")
    shutil.copytree(SAMPLES / "helical_gearbox", d / "asm")
    path = d / "asm" / "assembly.yaml"
    path.write_text(path.read_text().replace("parts:\n", "parts:\n  casing_b: {mesh: casing.stl}\n"
                                             "  casing_c: {mesh: casing.stl}\n", 1))
    asm = load_assembly(path)
    render_dataset(asm, d / "ds", RenderSettings(frames=6, noise="realsense", clutter=("bench",), base_fill=(0.18, 0.28),
                                                 seed=1), steps=[1], progress=False)
    return path, Dataset(d / "ds")


def test_twins_are_the_other_roots_of_the_same_mesh_and_the_dataset_lists_their_obj_ids(three_casings):
    path, ds = three_casings
    asm = load_assembly(path)
    assert asm.step_view(1).twins == ("casing_b", "casing_c") and asm.step_view(2).twins == ()  # base [casing, pinion]
    info = json.loads((ds.root / "dataset_info.json").read_text())["obj_ids"]
    doc = json.loads((ds.root / "test" / "000001" / "scene_assembly.json").read_text())
    assert sorted(doc["instance_obj_ids"]) == sorted(info[p] for p in CASINGS)
    fr = ds.frame(1, 0)
    assert all(fr.masks[p].any() for p in CASINGS)  # all three rendered and annotated


def test_every_instance_found_none_confident_and_wrong_in_image_order(three_casings):
    path, ds = three_casings
    asm, ctx = step_context(ds.assembly, 1)
    params = resolve_params("default", asm.registration)
    found_right = total = 0
    for im_id in ds.image_ids(1):
        fr = ds.frame(1, im_id)
        truths = {p: fr.poses[p] @ ctx.view.T_base_part for p in CASINGS}  # the pinion placed on each instance
        found = estimate_instances(fr, ctx, params)
        hits = set()
        for inst in found:
            errs = {p: mssd_to_truth(inst.result.T_world_part, T, path, ctx.part.id) for p, T in truths.items()}
            p = min(errs, key=errs.get)
            right = errs[p] < 0.1 * ctx.part.diameter
            assert right or not inst.result.confident, (im_id, p, errs[p])  # never confident and wrong
            if right:
                hits.add(p)
        total += len(CASINGS)
        found_right += len(hits)
        # left to right in the image, by the base's centre
        centre = ctx.base.samples.mean(axis=0)
        us = [fr.camera.project(se3.transform_points(se3.inv(fr.T_world_camera) @ i.result.T_world_base, centre[None]))[0][0]
              for i in found]
        assert us == sorted(us)
    assert found_right >= 0.8 * total, (found_right, total)


def test_apose_estimate_instances_all_json(three_casings):
    path, ds = three_casings
    run = [sys.executable, "-m", "apose_studio.cli", "estimate", str(ds.root), "--step", "1", "--frame", "5",
           "--instances", "all"]
    p = subprocess.run(run + ["--json"], capture_output=True, text=True)
    assert p.returncode in (0, 1), p.stderr
    doc = json.loads(p.stdout)
    assert isinstance(doc["instances"], list) and doc["instances"]
    for inst in doc["instances"]:
        assert {"T_world_base", "T_world_part", "T_world_camera", "ok", "confident", "box"} <= inst.keys()
    if doc["best_instance"] is not None:
        assert doc["T_world_part"] == doc["instances"][doc["best_instance"]]["T_world_part"]
    p = subprocess.run(run + ["--box", "1,1,50,50"], capture_output=True, text=True)
    assert p.returncode == 2 and "--instances all" in p.stderr and "Traceback" not in p.stderr
    fr = ds.frame(1, 5)
    cams = [np.asarray(i["T_world_camera"]) for i in doc["instances"]]
    assert all(np.allclose(T, fr.T_world_camera) for T in cams)


def test_first_confident_stops_at_the_first_confident_instance_largest_group_first(three_casings):
    """`first_confident` (a region's part found whole: only one is used): the estimator runs on the groups largest
    first and stops once one is confident; without it every group is estimated."""
    from apose_studio.registration.types import RegistrationResult

    _, ds = three_casings
    asm, ctx = step_context(ds.assembly, 1)
    fr = ds.frame(1, 0)
    seen = []

    def fake(view):  # every group "confident" at the identity
        seen.append(int(view.mask.sum()))
        return RegistrationResult(ok=True, T_world_base=np.eye(4), T_world_part=np.eye(4), coverage=1.0)

    everything = estimate_instances(fr, ctx, resolve_params("default"), estimate=fake)
    groups = list(seen)
    assert len(groups) >= 3  # the three casings at least
    seen.clear()
    first = estimate_instances(fr, ctx, resolve_params("default"), estimate=fake, first_confident=True)
    assert seen == groups[:1] and len(first) == 1 and len(everything) >= 1


def test_apose_estimate_instances_all_text_names_an_instance_without_a_pose(three_casings, monkeypatch, capsys):
    """A group of depth that no pose fits is an instance with ok=False: the text output says so with its reason
    (it had ended in "unexpected TypeError" for the whole command, the fitted instances unprinted)."""
    from apose_studio.cli import commands, frames
    from apose_studio.estimation import Instance
    from apose_studio.registration.types import failed

    _, ds = three_casings
    real = frames.estimate_instances

    def with_a_failed_one(frame, ctx, params, orientation_prior=False):
        found = real(frame, ctx, params, orientation_prior)
        return [*found, Instance((1, 2, 30, 40), np.zeros(frame.depth.shape, bool), failed("nothing fits this group"))]

    monkeypatch.setattr(frames, "estimate_instances", with_a_failed_one)
    code = commands.main(["estimate", str(ds.root), "--step", "1", "--frame", "5", "--instances", "all"])
    out = capsys.readouterr()
    assert code in (0, 1) and "unexpected" not in out.err, out.err
    assert "box 1,2,30,40: no pose: nothing fits this group" in out.out
    assert "T_camera_part t = (" in out.out  # the others are printed as before
