"""`apose estimate` and `apose eval`: one frame or a whole dataset (ours, a capture, a BOP scene or
split) through the estimator; the shared helpers of the command line's frame-handling commands."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from apose_studio.geometry import se3
from apose_studio.errors import AposeError


def _finite(x: float) -> float | None:
    """JSON has no NaN: an unknown number is null."""
    return float(x) if np.isfinite(x) else None


def _check_output_file(path: Path, flag: str, inputs=()) -> None:
    """Refuse an output path that cannot take a file, or that would replace a file of an input folder
    (`apose eval --json DS/dataset_info.json` would leave the dataset unreadable), before any long work."""
    for folder in inputs:
        folder = Path(folder).resolve()
        target = path.resolve()
        if target.exists() and (target == folder or target.is_relative_to(folder)):
            raise AposeError(f"{flag} {path}: a file of the input {folder}, which this would replace; write the "
                             "output elsewhere (or under a new name)")
    if path.is_dir():
        raise AposeError(f"{flag} {path}: a folder; give a file name (e.g. {path / 'out.json'})")
    if not path.parent.is_dir():
        raise AposeError(f"{flag} {path}: folder {path.parent} does not exist")


def _pose_lines(T: np.ndarray) -> list[str]:
    q = se3.matrix_to_quat_wxyz(T[:3, :3])
    M = T.copy()
    M[:3, 3] *= 1000.0  # people read millimetres; --json keeps metres
    rows = [" ".join(f"{v:+10.4f}" for v in row) for row in M]
    return [f"  [{r}]   (translation in mm)" if i == 0 else f"  [{r}]" for i, r in enumerate(rows)] + [
        f"  xyz (mm)    = ({M[0, 3]:+.2f}, {M[1, 3]:+.2f}, {M[2, 3]:+.2f})",
        f"  q (w,x,y,z) = ({q[0]:+.5f}, {q[1]:+.5f}, {q[2]:+.5f}, {q[3]:+.5f})"]


def _open_estimate_input(args):
    """(frame, assembly, step context) for `apose estimate`: a rendered dataset, a capture folder or a BOP
    scene folder."""
    from apose_studio.api import step_context
    from apose_studio.assembly.model import load_assembly
    from apose_studio.data.bop import BopScene
    from apose_studio.data.dataset import Dataset, open_frames

    src = open_frames(args.input)
    asm = load_assembly(args.assembly) if args.assembly else None
    if isinstance(src, Dataset):
        asm = asm or src.assembly
        _, ctx = step_context(asm, args.step)  # a step the assembly lacks says so first
        if args.step not in src.steps:
            raise AposeError(f"{src.root}: step {args.step} was not rendered; rendered steps: {', '.join(map(str, src.steps))}")
        return src.frame(args.step, args.frame), asm, ctx
    if asm is None:
        raise AposeError(f"{args.input}: a capture has no assembly of its own; give --assembly A.yaml (and --step)")
    _, ctx = step_context(asm, args.step)
    if isinstance(src, BopScene):
        from apose_studio.data.bop import parse_obj_map

        src.obj_of_part = parse_obj_map(args.obj_map, asm.parts)
        return src.frame(args.frame, ctx.view), asm, ctx
    ignored = [flag for flag, given in (("--frame", args.frame not in (None, 0)), ("--obj-map", bool(args.obj_map))) if given]
    if ignored:
        raise AposeError(f"{args.input}: a capture folder holds one frame and no BOP object ids; remove "
                         f"{' and '.join(ignored)} (they apply to datasets and BOP scene folders)")
    src.base, src.part, src.step = tuple(ctx.view.base), ctx.view.part, args.step
    return src, asm, ctx


def _estimate_mask(args, frame, asm) -> tuple[np.ndarray, str]:
    from apose_studio.api import check_mask, find_mask
    from apose_studio.evaluate import check_mask_source, frame_mask
    from apose_studio.masks.prompt import parse_box, parse_point

    box = parse_box(args.box) if args.box else None
    point = parse_point(args.point) if args.point else None
    if box is not None or point is not None:
        if args.mask not in (None, "depth"):
            raise AposeError(f"--mask {args.mask} and --box/--point: give one way to find the object")
        return find_mask(frame.rgb, frame.depth, frame.camera, box=box, point=point)
    source = args.mask or ("gt" if frame.masks else "depth")
    if source.lower().endswith((".png", ".jpg", ".bmp", ".tif", ".tiff")):
        import cv2

        from apose_studio.data.dataset import _read_image

        return check_mask(_read_image(Path(source), cv2.IMREAD_GRAYSCALE), frame.depth.shape, source), source
    if source == "gt" and not frame.masks:
        raise AposeError(f"{args.input}: no ground-truth masks here; use --box x0,y0,x1,y1, --point u,v, --mask depth "
                         "or --mask MASK.png")
    return frame_mask(frame, check_mask_source(source, asm)), source


def cmd_estimate(args) -> int:
    from apose_studio.api import run_registration

    if len(args.input) > 1 or args.views > 1:
        from apose_studio.cli.views import cmd_estimate_views

        return cmd_estimate_views(args)
    args.input = args.input[0]
    for flag in ("box", "point"):
        given = getattr(args, flag) or []
        if len(given) > 1:
            raise AposeError(f"--{flag} given {len(given)} times for one view; give it once")
        setattr(args, flag, given[0] if given else None)
    from apose_studio.evaluate import score_frame
    from apose_studio.registration import resolve_params

    t0 = time.perf_counter()
    frame, asm, ctx = _open_estimate_input(args)
    params = resolve_params(args.preset, asm.registration, **_upright(args))
    mask, source = _estimate_mask(args, frame, asm)
    est = run_registration(frame.depth, mask, source, frame.camera, frame.T_world_camera, ctx, params,
                           args.orientation_prior, t0, time.perf_counter() - t0, trace_iterations=True)
    r = est.result
    sc = (score_frame(frame, r, ctx.part, None if source == "gt" else mask, ctx.base.symmetries)
          if frame.T_world_part is not None else None)
    if args.json:
        doc = est.to_json()
        doc.update(step=args.step, frame=args.frame, preset=params.preset, part=ctx.part.id, base=list(ctx.view.base),
                   stages=[{"name": st.name, "T_world_base": st.T_world_base.tolist(), "fitness": st.fitness,
                            "inlier_rmse": st.inlier_rmse} for st in r.stages],
                   voxel_m=r.voxel, fitness=r.fitness, contradiction=_finite(r.contradiction), out_of_time=r.out_of_time,
                   alternatives_scores=[c.score for c in r.alternatives])
        if sc is not None:  # against the ground truth; also at the top level, as before (mask_iou, adi, mssd, ...)
            doc["truth"] = sc.to_json()
            doc.update({k: v for k, v in doc["truth"].items() if k not in doc})
        print(json.dumps(doc, indent=1))
        return 0 if r.ok else 1
    print(f"step {args.step}, frame {args.frame}: place {ctx.part.id} on [{', '.join(ctx.view.base)}]  (preset {params.preset})")
    print(f"mask: {source}, {int(mask.sum())} pixels ({est.timings['mask'] * 1000:.0f} ms)")
    if not r.ok:
        print(f"estimation failed: {r.reason}")
        return 1
    print("T_world_part (estimated assembly pose):")
    print("\n".join(_pose_lines(r.T_world_part)))
    if est.T_world_part_approach is not None:
        print(f"T_world_part_approach (where the step's {ctx.view.approach.distance * 1000:.0f} mm approach starts):")
        print("\n".join(_pose_lines(est.T_world_part_approach)))
    print("T_camera_part:")
    print("\n".join(_pose_lines(est.T_camera_part)))
    print(f"registration: fitness {r.fitness:.4f}, inlier RMSE {r.inlier_rmse * 1000:.3f} mm, voxel {r.voxel * 1000:.2f} mm, "
          f"{len(r.stages) - 3} ICP iterations, {r.seconds * 1000:.0f} ms "
          f"({', '.join(f'{k} {v * 1000:.0f}' for k, v in r.timings.items())} ms)")
    if sc is not None and sc.mask_iou is not None:
        print(f"mask ({source}): IoU {sc.mask_iou:.3f} against the ground-truth base mask")
    if not r.confident:
        print(f"low confidence: {est.doubts}; this pose is likely wrong")
    if r.ambiguous:
        _print_alternatives(r, ctx.part.id)
    if r.equivalent:
        print(f"the base object is symmetric: {len(r.equivalent)} other placement(s) of {ctx.part.id} are the same "
              "assembly (listed as 'equivalent' in --json)")
    if sc is not None:
        print(f"against ground truth: ADI {sc.adi * 1000:.3f} mm, MSSD {sc.mssd * 1000:.3f} mm, "
              f"te {sc.te * 1000:.3f} mm, re {sc.re_deg:.3f}°")
    return 0


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
    from apose_studio.data.dataset import Dataset
    from apose_studio.evaluate import evaluate, format_table
    from apose_studio.registration import resolve_params

    _check_outputs(args)  # first: nothing is read or computed for an output that cannot (or must not) be written
    if not (Path(args.dataset) / "dataset_info.json").is_file():
        from apose_studio.data.bop import scene_folders

        if scene_folders(Path(args.dataset)):
            return _eval_bop_split(args)
    ds = Dataset(args.dataset)
    if args.score_results:
        from apose_studio.data.bop import read_results_csv, score_results

        doc = score_results(ds, read_results_csv(Path(args.score_results)), args.steps)
        print(format_table(doc))
        return _write_outputs(args, doc, None)
    params = resolve_params(args.preset, ds.assembly.registration, **_upright(args))
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
            print(f"  step {st['step']}: recall {st['recall_mssd']:.2f} -> {sg['recall_mssd']:.2f} "
                  f"({100 * (st['recall_mssd'] - sg['recall_mssd']):+.0f} points), mask IoU {st['mask_iou']:.3f}")
        doc["gt_masks"] = [{"step": sg["step"], "recall_mssd": sg["recall_mssd"], "adi": sg["adi"], "mssd": sg["mssd"]}
                           for sg in gt["steps"]]
    from apose_studio.data.bop import results_from_eval

    return _write_outputs(args, doc, results_from_eval(ds, doc) if args.bop_results else None)


def _check_outputs(args) -> None:
    """--json and --bop-results must be writable file paths outside the data read, checked before any long work."""
    inputs = [getattr(args, "dataset", None), getattr(args, "score_results", None)]
    for flag in ("json", "bop_results"):
        if getattr(args, flag):
            _check_output_file(Path(getattr(args, flag)), "--" + flag.replace("_", "-"), [i for i in inputs if i])


def _write_outputs(args, doc: dict, rows) -> int:
    """Write --json (the evaluation document) and --bop-results (BOP19 rows), as asked."""
    from apose_studio.data.bop import write_results_csv
    from apose_studio.data.dataset import write_json

    if args.json:
        write_json(Path(args.json), doc)
        print(f"wrote {args.json}")
    if args.bop_results and rows is not None:
        write_results_csv(Path(args.bop_results), rows)
        print(f"wrote {args.bop_results} (BOP19 results)")
    return 0


def _eval_bop_split(args) -> int:
    from apose_studio.assembly.model import load_assembly
    from apose_studio.data.bop import evaluate_split, parse_obj_map
    from apose_studio.evaluate import format_table
    from apose_studio.registration import resolve_params

    if not args.assembly or args.step is None:
        raise AposeError(f"{args.dataset}: a BOP split; give --assembly A.yaml, --step K and --obj-map PART=OBJ_ID for the "
                         "base's parts")
    if args.score_results:
        raise AposeError("--score-results scores a results file on an apose dataset; on BOP data use bop_toolkit")
    asm = load_assembly(args.assembly)
    params = resolve_params(args.preset, asm.registration, **_upright(args))
    doc, rows = evaluate_split(Path(args.dataset), asm, args.step, parse_obj_map(args.obj_map, asm.parts), params,
                               args.mask, args.frames, progress=sys.stderr.isatty())
    print(format_table(doc))
    return _write_outputs(args, doc, rows)


def _upright(args) -> dict:
    if args.upright is None:
        return {}
    if args.preset == "paper" and args.upright:
        raise AposeError("--upright is a search of ours; the paper preset has no such mode (use --preset default)")
    return {"upright": args.upright}
