"""`apose estimate` and `apose eval`: one frame or a whole dataset (ours, a capture, a BOP scene or
split) through the estimator; the shared helpers of the command line's frame-handling commands."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from apose_studio.api import grasp_of, pose_estimate, robot_targets, run_registration
from apose_studio.assembly.model import Assembly, load_assembly
from apose_studio.cli.common import check_output_file, failed_exit, failed_words, finite, params_of, parse_prompt, pose_lines
from apose_studio.cli.views import cmd_estimate_views
from apose_studio.data.bop import BopScene, parse_obj_map, read_results_csv, results_from_eval, scene_folders, write_results_csv
from apose_studio.data.dataset import Dataset, Frame, write_json
from apose_studio.data.sources import open_frames
from apose_studio.errors import AposeError
from apose_studio.estimation import (
    MaskRequest,
    StepContext,
    array_mask,
    colour_registered,
    estimate_instances,
    estimate_pick,
    find_mask,
    region_truth_prompt,
    step_context,
)
from apose_studio.evaluate import evaluate, evaluate_split, format_table, score_frame, score_results
from apose_studio.geometry import se3
from apose_studio.masks.prompt import parse_box, parse_point
from apose_studio.registration.types import View
from apose_studio.robot.handeye import HandEye, capture_flange, read_hand_eye
from apose_studio.robot.ros2 import write_mcap


def open_estimate_input(args, path: str) -> tuple[Frame, Assembly, StepContext]:
    """(frame, assembly, step context) for `apose estimate` on `path`: a rendered dataset, a capture folder
    or a BOP scene folder."""
    src = open_frames(path)
    asm = load_assembly(args.assembly) if args.assembly else None
    if isinstance(src, Dataset):
        asm = asm or src.assembly
        _, ctx = step_context(asm, args.step)  # a step the assembly lacks says so first
        if args.step not in src.steps:
            raise AposeError(f"{src.root}: step {args.step} was not rendered; rendered steps: {', '.join(map(str, src.steps))}")
        return src.frame(args.step, args.frame), asm, ctx
    if asm is None:
        raise AposeError(f"{path}: a capture has no assembly of its own; give --assembly A.yaml (and --step)")
    _, ctx = step_context(asm, args.step)
    if isinstance(src, BopScene):
        src.obj_of_part = parse_obj_map(args.obj_map, asm.parts)
        src.check_obj_map(src.obj_of_part, ctx.view.base[0])
        return src.frame(args.frame, ctx.view), asm, ctx
    ignored = [flag for flag, given in (("--frame", args.frame not in (None, 0)), ("--obj-map", bool(args.obj_map))) if given]
    if ignored:
        what = {"--frame": "a capture folder holds one frame", "--obj-map": "a capture folder has no ground truth to map"}
        raise AposeError(f"{path}: {'; '.join(what[f] for f in ignored)}; remove {' and '.join(ignored)} "
                         f"({'it applies' if len(ignored) == 1 else 'they apply'} to datasets and BOP scene folders)")
    return replace(src, base=tuple(ctx.view.base), part=ctx.view.part, step=args.step), asm, ctx


def _robot_args(args) -> HandEye | None:
    """--hand-eye read and the robot flags checked before any work (None: no robot targets asked for)."""
    robot_flags = [f for f in ("grasp", "pick_box", "pick_point", "mcap") if getattr(args, f, None)]
    if not getattr(args, "hand_eye", None):
        if robot_flags:
            raise AposeError(f"--{robot_flags[0].replace('_', '-')} needs --hand-eye FILE (the camera's pose in the robot's "
                             "frame): the targets are given in the robot's frame")
        return None
    if args.pick_box and args.pick_point:
        raise AposeError("--pick-box and --pick-point: give one way to find the loose part")
    if args.mcap:
        check_output_file(Path(args.mcap), "--mcap", args.input)
    if args.tf_prefix and not all(c.isascii() and (c.isalnum() or c in "_/") for c in args.tf_prefix):
        raise AposeError(f"--tf-prefix {args.tf_prefix!r}: a ROS frame prefix is letters, digits, '_' and '/'"[:200])
    return read_hand_eye(args.hand_eye)


def _flange_of(frame: Frame, hand_eye: HandEye, path: str):
    """The arm's T_robot_flange at the capture (eye-in-hand): the capture's camera.json, else the calibration file's."""
    if hand_eye.kind != "eye_in_hand":
        return None
    flange = capture_flange(Path(path)) if Path(path, "camera.json").is_file() else None
    return flange if flange is not None else hand_eye.T_robot_flange


def _pick(args, frame: Frame, ctx, params):
    """The loose part's own estimate (--pick-box / --pick-point), or None."""
    if not (args.pick_box or args.pick_point):
        return None
    box = parse_box(args.pick_box, "--pick-box") if args.pick_box else None
    point = parse_point(args.pick_point, "--pick-point") if args.pick_point else None
    mask, _ = array_mask(frame.rgb, frame.depth, frame.camera, box=box, point=point)
    return estimate_pick(replace(View.of(frame, mask), box=box), ctx.part, params)


def cmd_estimate(args) -> int:
    if getattr(args, "align_depth", False) and (len(args.input) > 1 or args.views > 1 or args.instances
                                                 or not (args.box or args.point)):
        raise AposeError("--align-depth compares the depth with the colour image around one frame's prompt: give it "
                         "with --box or --point and one frame")
    if len(args.input) > 1 or args.views > 1:
        if args.instances:
            raise AposeError("--instances all takes one frame; fused views find one instance")
        if getattr(args, "hand_eye", None):
            raise AposeError("--hand-eye takes one frame (one capture); fused views give no robot targets yet")
        return cmd_estimate_views(args)
    hand_eye = _robot_args(args)
    request = MaskRequest(args.mask, *(parse_prompt(args, flag) for flag in ("box", "point")))
    if args.instances and (request.box or request.point or args.mask or hand_eye is not None):
        raise AposeError("--instances all finds every instance without a prompt; give either it or --box/--point/--mask/"
                         "--hand-eye (a prompt picks one instance)")
    t0 = time.perf_counter()
    frame, asm, ctx = open_estimate_input(args, args.input[0])
    if args.instances:
        return _estimate_instances(args, frame, asm, ctx, t0)
    if hand_eye is not None:  # a wrong grasp name or pick prompt is said before any work
        grasp_of(asm, ctx.view.part, args.grasp)
        _ = (parse_box(args.pick_box, "--pick-box") if args.pick_box else None,
             parse_point(args.pick_point, "--pick-point") if args.pick_point else None)
    params = params_of(args, asm.registration)
    ctx.base.warm_up(params)
    t1 = time.perf_counter()
    shift = (0, 0)
    if getattr(args, "align_depth", False):  # the prompt is on the colour image: the depth moved onto it
        depth, shift = colour_registered(frame.rgb, frame.depth, request.box, request.point)
        frame = replace(frame, depth=depth)
    truth = None if request.box or request.point else region_truth_prompt(frame, ctx, request.source or "gt")
    if truth is not None:  # a region on a rendered frame: the box round what is seen of it, from the truth
        request = replace(request, box=truth[1], source=None)  # the truth's box is the prompt (not --mask's too)
    elif ctx.base.region is not None and request.box is None and request.point is None:  # bad input (exit 2); a
        # click is refused by the prompt itself
        raise AposeError(f"{ctx.view.base[0]} is a region of a larger part (its roi): its target is what a box drawn "
                         "round it holds; give --box X0,Y0,X1,Y1 round it, not a mask of the whole part or a click")
    mask, source = find_mask(frame, request, asm, args.input[0], region=ctx.base.region is not None)
    if truth is not None:
        source = "box round the region from the ground truth"
    est = run_registration(replace(View.of(frame, mask), box=request.box), source, ctx, params, args.orientation_prior, t0,
                           time.perf_counter() - t1, trace_iterations=True, t_load=t1 - t0)
    est.world = frame.world
    if shift != (0, 0):  # moved before the mask, as asked (the estimate then found none left to move)
        est.depth_shift_px = shift
    if hand_eye is not None:
        est.targets = robot_targets(est, asm, ctx, hand_eye, args.grasp, _pick(args, frame, ctx, params),
                                    _flange_of(frame, hand_eye, args.input[0]))
        if args.mcap:
            write_mcap(args.mcap, est.targets, args.tf_prefix)
    r = est.result
    sc = (score_frame(frame, r, ctx.part, None if source == "gt" else mask, ctx.base.symmetries)
          if frame.T_world_part is not None else None)
    if args.json:
        doc = est.to_json()  # its "mask": the result's (cut to the model's view); the prompt's beside it
        doc["mask"].update(prompt_source=source, prompt_pixels=int(mask.sum()))
        doc.update(step=args.step, frame=args.frame, preset=params.preset, part=ctx.part.id, base=list(ctx.view.base),
                   stages=[{"name": st.name, "T_world_base": st.T_world_base.tolist(), "fitness": st.fitness,
                            "inlier_rmse": st.inlier_rmse} for st in r.stages],
                   voxel_m=r.voxel, fitness=r.fitness, contradiction=finite(r.contradiction), out_of_time=r.out_of_time,
                   alternatives_scores=[c.score for c in r.alternatives])
        if r.input_error:  # bad input, found at the estimate: said as every refused input says it
            doc.update(refused=True, exit_code=failed_exit(r))
        if sc is not None:  # against the ground truth; also at the top level (mask_iou, adi, mssd, ...), where scripts read them
            doc["truth"] = sc.to_json()
            doc.update({k: v for k, v in doc["truth"].items() if k not in doc})
        print(json.dumps(doc, indent=1))
        if args.mcap:
            print(f"wrote {args.mcap}", file=sys.stderr)
        if not r.ok:  # the reason is in the JSON; said in words too, for whoever reads the terminal
            print(f"{failed_words(r)}: {r.reason}", file=sys.stderr)
        return 0 if r.ok else failed_exit(r)
    print(f"step {args.step}, frame {args.frame}: place {ctx.part.id} on [{', '.join(ctx.view.base)}]  (preset {params.preset})")
    print(f"mask: {source}, {int(mask.sum())} pixels ({est.timings['mask'] * 1000:.0f} ms; --json: mask.prompt_pixels)")
    used = est.to_json()["mask"].get("prompt_box_used")  # (the box as the API records it, as given and as used)
    if used is not None and used != [int(v) for v in est.prompt_box]:
        h, w = mask.shape
        print(f"box: {','.join(map(str, est.prompt_box))} reaches past the {w}x{h} image; used {','.join(map(str, used))}")
    if shift != (0, 0):
        print(f"depth: lay {shift[0]:+d}, {shift[1]:+d} px (right, down) off the colour image around the prompt; moved back "
              "before the mask and the registration")
    elif est.depth_shift_px != (0, 0):
        du, dv = est.depth_shift_px
        print(f"depth: its edges lay {du:+d}, {dv:+d} px (right, down) off the colour image's; moved back, and the pose "
              "estimated on it (--param move_depth_to_colour=false keeps the depth as given)")
    if not r.ok:
        print(f"{failed_words(r)}: {r.reason}")
        return failed_exit(r)
    print(f"T_world_part (estimated assembly pose; world: {frame.world}):")
    print("\n".join(pose_lines(r.T_world_part)))
    if est.T_world_part_approach is not None:
        print(f"T_world_part_approach (where the step's {ctx.view.approach.distance * 1000:.0f} mm approach starts):")
        print("\n".join(pose_lines(est.T_world_part_approach)))
    print("T_camera_part:")
    print("\n".join(pose_lines(est.T_camera_part)))
    print(f"registration: fitness {r.fitness:.4f}, inlier RMSE {r.inlier_rmse * 1000:.3f} mm, voxel {r.voxel * 1000:.2f} mm, "
          f"{len(r.stages) - 3} ICP iterations, {est.timings['registration'] * 1000:.0f} ms in all (--json: timings_s); the "
          f"pose's own estimate {r.seconds * 1000:.0f} ms ({', '.join(f'{k} {v * 1000:.0f}' for k, v in r.timings.items())}"
          " ms), the rest other readings of the mask and checks whose estimates were not kept")
    if sc is not None and sc.mask_iou is not None and ctx.base.region is None:  # a region's truth mask is its whole part's
        print(f"mask ({source}): IoU {sc.mask_iou:.3f} against the ground-truth base mask")
    if r.reading:  # the pose came from another reading of the mask (registration/hypotheses.py)
        print(f"the pose came from another reading of the mask: {r.reading}")
    print(f"the result's mask: {est.mask_source}, {int(est.mask.sum())} pixels (--json: mask.pixels)")
    print("confident: the data supports this one placement" if r.confident else f"not confident: {est.doubts}")
    if r.ambiguous:
        _print_alternatives(r, ctx.part.id)
    if r.equivalent:
        print(f"the base object is symmetric: {len(r.equivalent)} other placement(s) of {ctx.part.id} are the same "
              "assembly (listed as 'equivalent' in --json)")
    if r.base_alternatives:
        print(f"the base's own pose is not sure: turned {len(r.base_alternatives)} other way(s) it fits as well and "
              f"places {ctx.part.id} alike (the view hides what tells them apart; 'base_alternatives' in --json, "
              "base_confident false)")
    if sc is not None:
        print(f"against ground truth: ADI {sc.adi * 1000:.3f} mm, MSSD {sc.mssd * 1000:.3f} mm, "
              f"te {sc.te * 1000:.3f} mm, re {sc.re_deg:.3f}°")
        if sc.mssd_mod_base_sym is not None and sc.mssd_mod_base_sym < sc.mssd - 1e-9:  # the base's exact twin of it
            print(f"  the same assembly as the truth turned by the base's symmetry (an 'equivalent' placement): MSSD "
                  f"{sc.mssd_mod_base_sym * 1000:.3f} mm to that")
    if est.targets is not None:
        _print_targets(est.targets)
        if args.mcap:
            print(f"wrote {args.mcap} (ROS 2 messages: /tf_static, /apose/place/gripper, ...)")
    return 0


def _estimate_instances(args, frame: Frame, asm: Assembly, ctx: StepContext, t0: float) -> int:
    """`apose estimate --instances all`: every instance of the step's base, left to right (estimation.estimate_instances)."""
    params = params_of(args, asm.registration)
    ctx.base.warm_up(params)
    t1 = time.perf_counter()
    found = estimate_instances(frame, ctx, params, args.orientation_prior)
    seconds = time.perf_counter() - t1
    ests = [pose_estimate(i.result, frame.T_world_camera, ctx.view,
                          i.result.model_mask if i.result.model_mask is not None else i.mask, "instance box",
                          {"registration": i.result.seconds}) for i in found]
    docs = []
    for i, est in zip(found, ests):
        doc = est.to_json()
        doc.update(box=list(i.box), fitness=i.result.fitness)
        docs.append(doc)
    confident = [k for k, e in enumerate(ests) if e.confident]
    best = confident[0] if confident else (0 if ests else None)
    if args.json:
        doc = dict(docs[best]) if best is not None else {"ok": False, "reason": "no instance of the base found"}
        doc.update(step=args.step, frame=args.frame, preset=params.preset, part=ctx.part.id, base=list(ctx.view.base),
                   instances=docs, instances_seconds=seconds, best_instance=best)
        print(json.dumps(doc, indent=1))
        return 0 if confident else 1
    print(f"step {args.step}, frame {args.frame}: every instance of [{', '.join(ctx.view.base)}] to place {ctx.part.id} "
          f"on (preset {params.preset}): {len(ests)} found, {len(confident)} confident, {seconds:.2f} s")
    for k, est in enumerate(ests):
        box = ",".join(map(str, found[k].box))
        if est.T_camera_part is None:  # a group of depth that no pose fits: said, not a traceback
            print(f"  {k + 1}. box {box}: no pose: {est.reason}")
            continue
        t = est.T_camera_part[:3, 3] * 1000
        state = "confident" if est.confident else f"not confident: {est.doubts}"
        print(f"  {k + 1}. box {box}: T_camera_part t = ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) mm, {state}")
    return 0 if confident else 1


def _print_targets(t) -> None:
    print(f"robot targets in {t.robot_frame} (metres inside; shown in mm; q is w,x,y,z, ROS's x,y,z,w is in --json):")
    for name, T in t.poses().items():
        if name != "T_robot_camera":
            print(f"{name}:" + (f" (grasp {t.grasp})" if "gripper" in name else ""))
            print("\n".join(pose_lines(T)[-2:]))
    if t.gripper_alternatives:
        print(f"{len(t.gripper_alternatives)} other gripper targets at the place (symmetries; 'gripper_alternatives' "
              "in --json)")
    if t.pick is not None and not t.pick["ok"]:
        print(f"pick: no pose: {t.pick['reason']}")
    elif t.pick is not None and not t.pick["confident"]:
        print(f"pick: not confident: {t.pick['doubts']}")
    for note in t.notes:
        print(f"note: {note}")


def _print_alternatives(r, part: str) -> None:
    print(f"ambiguous: {len(r.alternatives) + 1} placements of {part} fit the data equally (the base object is "
          "(nearly) symmetric, and what tells them apart is not in view); the estimate and the others:")

    def xyz(T) -> str:
        return "xyz ({:+.1f}, {:+.1f}, {:+.1f}) mm".format(*(T[:3, 3] * 1000))

    print(f"  estimate {xyz(r.T_world_part)}")
    for c in r.alternatives:
        apart = np.linalg.norm(c.T_world_part[:3, 3] - r.T_world_part[:3, 3]) * 1000
        turn = se3.rotation_angle_deg(c.T_world_part[:3, :3].T @ r.T_world_part[:3, :3])
        print(f"  other    {xyz(c.T_world_part)}, score {c.score:.3f}, {apart:.1f} mm and {turn:.0f}° from the estimate")


def cmd_eval(args) -> int:
    _check_outputs(args)  # first: nothing is read or computed for an output that cannot (or must not) be written
    if not (Path(args.dataset) / "dataset_info.json").is_file():
        if scene_folders(Path(args.dataset)):
            return _eval_bop_split(args)
    ds = Dataset(args.dataset)
    if args.score_results:
        doc = score_results(ds, read_results_csv(Path(args.score_results)), args.steps)
        print(format_table(doc))
        return _write_outputs(args, doc, None)
    params = params_of(args, ds.assembly.registration)
    if args.frames is not None and args.frames < 1:
        raise AposeError(f"--frames {args.frames}: expected at least 1")
    if args.workers < 1:
        raise AposeError(f"--workers {args.workers}: expected at least 1")
    for step in ds.missing_steps:
        print(f"warning: step {step} is listed in {ds.root / 'dataset_info.json'} but its folder "
              f"test/{step:06d} is missing; it is left out", file=sys.stderr)
    if args.views < 1:
        raise AposeError(f"--views {args.views}: expected at least 1")
    doc = evaluate(ds, params, args.steps, args.frames, args.mask, args.orientation_prior,
                   progress=sys.stderr.isatty(), workers=args.workers, views=args.views)
    print(format_table(doc))
    unreadable = [f"step {st['step']} frame {f['im_id']}" for st in doc["steps"] for f in st.get("frames", [])
                  if str(f.get("reason", "")).startswith("unreadable frame")]
    if unreadable:
        print(f"warning: {len(unreadable)} frame(s) could not be read and count as failed: {', '.join(unreadable[:5])}",
              file=sys.stderr)
    if args.mask != "gt" and not args.no_gt_compare:  # the same frames with ground-truth masks, beside
        gt = evaluate(ds, params, args.steps, args.frames, "gt", args.orientation_prior,
                      progress=sys.stderr.isatty(), workers=args.workers, views=args.views)
        print(f"\nthe same frames with ground-truth masks (recall with {args.mask} masks -> with gt masks):")
        for st, sg in zip(doc["steps"], gt["steps"]):
            iou = f", mask IoU {st['mask_iou']:.3f}" if st.get("mask_iou") is not None else ""  # none for a region
            print(f"  step {st['step']}: recall {st['recall_mssd']:.2f} -> {sg['recall_mssd']:.2f} "
                  f"({100 * (st['recall_mssd'] - sg['recall_mssd']):+.0f} points){iou}")
        doc["gt_masks"] = [{"step": sg["step"], "recall_mssd": sg["recall_mssd"], "adi": sg["adi"], "mssd": sg["mssd"]}
                           for sg in gt["steps"]]

    return _write_outputs(args, doc, results_from_eval(ds, doc) if args.bop_results else None)


def _check_outputs(args) -> None:
    """--json and --bop-results must be writable file paths outside the data read, checked before any long work."""
    inputs = [getattr(args, "dataset", None), getattr(args, "score_results", None)]
    for flag in ("json", "bop_results"):
        if getattr(args, flag):
            check_output_file(Path(getattr(args, flag)), "--" + flag.replace("_", "-"), [i for i in inputs if i])


def _write_outputs(args, doc: dict, rows) -> int:
    """Write --json (the evaluation document) and --bop-results (BOP19 rows), as asked."""
    if args.json:
        write_json(Path(args.json), doc)
        print(f"wrote {args.json}")
    if args.bop_results and rows is not None:
        write_results_csv(Path(args.bop_results), rows)
        print(f"wrote {args.bop_results} (BOP19 results)")
    return 0


def _eval_bop_split(args) -> int:
    if not args.assembly or args.step is None:
        raise AposeError(f"{args.dataset}: a BOP split; give --assembly A.yaml, --step K and --obj-map PART=OBJ_ID for the "
                         "base's parts")
    if args.score_results:
        raise AposeError("--score-results scores a results file on an apose dataset; on BOP data use bop_toolkit")
    asm = load_assembly(args.assembly)
    params = params_of(args, asm.registration)
    doc, rows = evaluate_split(Path(args.dataset), asm, args.step, parse_obj_map(args.obj_map, asm.parts), params,
                               args.mask, args.frames, progress=sys.stderr.isatty())
    print(format_table(doc))
    return _write_outputs(args, doc, rows)
