"""`apose estimate` on several views of one placement: a rendered dataset's frames of one placement
(`--frame I --views K`), or several capture folders whose camera.json files carry the camera's pose
(`cam_R_w2c`, `cam_t_w2c`). One fused estimate (registration.fusion), and where it is not confident,
the camera pose to look from next (registration.next_view)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from apose_studio.api import pose_estimate
from apose_studio.assembly.model import load_assembly
from apose_studio.cli.common import failed_exit, failed_words, params_of, parse_prompt, pose_lines
from apose_studio.data.dataset import Dataset, read_json
from apose_studio.data.sources import open_frames
from apose_studio.errors import AposeError
from apose_studio.estimation import MaskRequest, estimate_frames, find_mask, step_context
from apose_studio.evaluate import score_frame
from apose_studio.registration.next_view import next_view
from apose_studio.registration.types import View


def open_views(args) -> tuple[list, object, object]:
    """(frames, assembly, step context): the views `apose estimate` was given."""
    if len(args.input) == 1:
        src = open_frames(args.input[0])
        if not isinstance(src, Dataset):
            raise AposeError(f"{args.input[0]}: --views needs a dataset from `apose render`; for captures give several "
                             "capture folders (each camera.json with cam_R_w2c and cam_t_w2c)")
        asm = load_assembly(args.assembly) if args.assembly else src.assembly
        _, ctx = step_context(asm, args.step)
        if args.step not in src.steps:
            raise AposeError(f"{src.root}: step {args.step} was not rendered; rendered steps: "
                             f"{', '.join(map(str, src.steps))}")
        first = src.frame(args.step, args.frame)
        group = next((ids for ids in src.placements(args.step).values() if args.frame in ids), [args.frame])
        ids = [args.frame] + [i for i in group if i != args.frame]
        return [first] + [src.frame(args.step, i) for i in ids[1:args.views]], asm, ctx
    if not args.assembly:
        raise AposeError("several captures: give --assembly A.yaml (and --step)")
    asm = load_assembly(args.assembly)
    _, ctx = step_context(asm, args.step)
    frames = []
    for folder in args.input:
        fr = open_frames(folder)
        if isinstance(fr, Dataset) or not hasattr(fr, "rgb"):
            raise AposeError(f"{folder}: several inputs must each be a capture folder (rgb.png, depth.png, camera.json)")
        cam = read_json(Path(folder) / "camera.json")
        if not (isinstance(cam, dict) and "cam_R_w2c" in cam and "cam_t_w2c" in cam):
            raise AposeError(f"{Path(folder) / 'camera.json'}: several views are fused in one world frame; add the "
                             "camera's pose as cam_R_w2c (row-major 3x3) and cam_t_w2c (mm), e.g. from the robot's "
                             "kinematics")
        frames.append(replace(fr, base=tuple(ctx.view.base), part=ctx.view.part, step=args.step))
    return frames, asm, ctx


def view_masks(args, frames, asm) -> list[tuple[np.ndarray, str]]:
    """Each view's mask: --box/--point once per input (in order), else --mask (default: the ground truth
    where there is one, else depth)."""
    out = []
    for k, fr in enumerate(frames):
        request = MaskRequest(args.mask, *(parse_prompt(args, flag, k, len(frames)) for flag in ("box", "point")))
        out.append(find_mask(fr, request, asm, fr.source or args.input[0], region=asm.base_is_region(args.step)))
    return out


def cmd_estimate_views(args) -> int:
    frames, asm, ctx = open_views(args)
    params = params_of(args, asm.registration)
    masks = view_masks(args, frames, asm)
    views = [View.of(f, m) for f, (m, _) in zip(frames, masks)]
    r = estimate_frames(views, ctx, params, args.orientation_prior)
    T_wc = frames[0].T_world_camera
    est = pose_estimate(r, T_wc, ctx.view, masks[0][0], masks[0][1], r.timings)
    advice = next_view(r, ctx.base, [f.T_world_camera for f in frames], frames[0].camera) if r.ok else None
    sc = (score_frame(frames[0], r, ctx.part, None, ctx.base.symmetries) if frames[0].T_world_part is not None else None)
    if args.json:
        doc = est.to_json()
        doc.update(step=args.step, part=ctx.part.id, preset=params.preset,
                   views=[{"name": v.name, "T_world_camera": v.T_world_camera.tolist(),
                           "mask": {"source": s, "pixels": int(m.sum())}} for v, (m, s) in zip(views, masks)],
                   next_view=advice.to_json() if advice else None)
        if frames[0].T_world_part is not None:
            doc["im_ids"] = [int(f.im_id) for f in frames]
        if sc is not None:
            doc["truth"] = sc.to_json()
        print(json.dumps(doc, indent=1))
        return 0 if r.ok else failed_exit(r)
    print(f"step {args.step}: place {ctx.part.id} on [{', '.join(ctx.view.base)}] from {len(views)} views "
          f"({', '.join(v.name for v in views)})")
    if not r.ok:
        print(f"{failed_words(r)}: {r.reason}")
        return failed_exit(r)

    print("T_world_part (estimated assembly pose, fused):")
    print("\n".join(pose_lines(r.T_world_part)))
    print(f"{r.timings.get('total fused', r.seconds) * 1000:.0f} ms; coverage {r.coverage:.2f} (the worst view)")
    if not r.confident:
        print(f"not confident: {est.doubts}")
    if advice is not None:
        p = advice.T_world_camera[:3, 3] * 1000
        print(f"look next from camera at ({p[0]:+.0f}, {p[1]:+.0f}, {p[2]:+.0f}) mm (world), looking at the base: "
              f"{advice.why}")
    if sc is not None:
        print(f"against ground truth: MSSD {sc.mssd * 1000:.3f} mm (modulo exact symmetries "
              f"{sc.mssd_mod_base_sym * 1000:.3f} mm)")
    return 0
