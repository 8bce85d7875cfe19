"""`apose` command line: a thin shell over the core. Errors become one line each, never a traceback."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__, se3
from .errors import AposeError
from .summary import show_json, show_text

REPO = Path(__file__).resolve().parent.parent
SAMPLES = REPO / "sample_assemblies"
DEFAULT_SAMPLE = SAMPLES / "helical_gearbox" / "assembly.yaml"


def cmd_show(args) -> int:
    from .assembly import load_assembly
    from .mesh import load_parts

    asm = load_assembly(args.assembly)
    models = load_parts(asm)
    if args.json:
        print(json.dumps(show_json(asm, models), indent=2))
    else:
        print(show_text(asm, models))
    return 0


def cmd_demo(args) -> int:
    """The slice end to end on a sample: summary, a small rendered dataset, one estimate per step."""
    from .assembly import load_assembly
    from .dataset import Dataset
    from .evaluate import StepContext, estimate_and_score
    from .mesh import load_parts
    from .registration import doubts, resolve_params
    from .render import RenderSettings, render_dataset

    path = Path(args.assembly) if args.assembly else DEFAULT_SAMPLE
    if not path.is_file():
        raise AposeError(f"{path}: sample assembly not found; run `python sample_assemblies/generate.py` "
                         "in the repository to create it")
    print(f"apose demo: the sample assembly {path.resolve()}\n")
    asm = load_assembly(path)
    models = load_parts(asm)
    print(show_text(asm, models))
    out = Path(args.out)
    settings = RenderSettings(frames=args.frames, noise="realsense", seed=1)
    print(f"\nrendering {args.frames} RealSense-like views per step into {out} ...")
    summary = render_dataset(asm, out, settings, overwrite=True, progress=sys.stderr.isatty(), models=models)
    print(f"  {summary['frames']} frames in {summary['seconds']:.1f} s")
    ds = Dataset(out)
    params = resolve_params("default", asm.registration)
    print("\nestimating each step's assembly pose (preset default; no orientation prior: the base stands on the "
          "table at an unknown yaw; ground-truth masks):")
    from .inspection import ResultCache

    cache = ResultCache()
    for step in ds.steps:
        ctx = StepContext(ds.assembly, models, step)
        frame = ds.frame(step, 0)
        r, sc = estimate_and_score(frame, ctx, params, trace_iterations=True)
        cache.put(cache.key(Path(out).resolve(), step, frame.im_id, "default", "gt", False), (r, sc if r.ok else None))
        if not r.ok:
            print(f"  step {step}: place {ctx.part.id}: failed: {r.reason}")
            continue
        t = r.T_world_part[:3, 3] * 1000
        print(f"  step {step}: place {ctx.part.id:<8} at ({t[0]:+7.1f}, {t[1]:+7.1f}, {t[2]:+7.1f}) mm in the world; "
              f"error vs truth: MSSD {sc.mssd * 1000:.2f} mm, ADI {sc.adi * 1000:.2f} mm; {r.seconds * 1000:.0f} ms"
              + ("  (ambiguous: symmetric base)" if r.ambiguous else "")
              + ("" if r.confident else f"  (low confidence: {doubts(r)}; likely wrong)"))
    print(f"\nnext: `apose eval {out}` for the per-step table, `apose estimate {out} --step 1` for one frame")
    if args.no_studio:
        return 0
    print("\nopening the studio on this assembly and dataset (the estimates above are cached in its Inspect tab)")
    return _serve_studio(path, out, args.host, args.port, cache, root=args.root)


def _serve_studio(assembly, dataset, host: str, port: int, cache=None, root=None) -> int:
    from .studio import serve
    from .webguard import is_loopback_bind

    if root is not None and not Path(root).is_dir():
        raise AposeError(f"--root {root}: no such folder")
    server, studio = serve(assembly, dataset, host=host, port=port, cache=cache, root=root)
    print(f"studio: {studio.url}  (Ctrl-C to stop)")
    print(f"workspace: the page may open and save files only under {', '.join(str(r) for r in studio.workspace.roots)}")
    if not is_loopback_bind(host):
        print(f"note: listening on {host}; the page and its websocket need the token in the address above. Anyone "
              "with that address can open and save files in the workspace: share it only with people you trust",
              file=sys.stderr)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()
    return 0


def cmd_studio(args) -> int:
    if args.assembly and not Path(args.assembly).is_file():
        raise AposeError(f"{args.assembly}: no such assembly file")
    return _serve_studio(args.assembly, args.dataset, args.host, args.port, root=args.root)


def _pair(text: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected two numbers as min,max (e.g. 20,70), got {text!r}") from None
    return a, b


def _finite(x: float) -> float | None:
    """JSON has no NaN: an unknown number is null."""
    return float(x) if np.isfinite(x) else None


def _check_output_file(path: Path, flag: str) -> None:
    """Refuse an output path that cannot take a file, before any long work."""
    if path.is_dir():
        raise AposeError(f"{flag} {path}: a folder; give a file name (e.g. {path / 'out.json'})")
    if not path.parent.is_dir():
        raise AposeError(f"{flag} {path}: folder {path.parent} does not exist")


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of at least 1, got {text!r}")
    return n


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 < port < 65536:
        raise argparse.ArgumentTypeError(f"expected a port number from 1 to 65535, got {text!r}")
    return port


def _steps(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected step numbers such as 1,2, got {text!r}") from None


def cmd_render(args) -> int:
    from dataclasses import replace

    from .assembly import load_assembly
    from .render import RenderSettings, render_dataset

    asm = load_assembly(args.assembly)
    settings = RenderSettings(frames=args.frames, seed=args.seed, noise=args.noise, noise_sigma_at_05m=args.noise_sigma,
                              base_pose=args.base_pose, distractors=args.distractors, clutter=args.clutter)
    if asm.camera is not None:
        settings = replace(settings, camera=asm.camera)
    for name, attr in (("yaw_range", "yaw_range_deg"), ("pitch_range", "pitch_range_deg"),
                       ("distance_range", "distance_range_m")):
        if getattr(args, name) is not None:
            settings = replace(settings, **{attr: getattr(args, name)})
    summary = render_dataset(asm, args.out, settings, args.steps, overwrite=args.overwrite,
                             progress=not args.quiet and sys.stderr.isatty())
    print(f"rendered {summary['frames']} frames of {asm.name} into {args.out} in {summary['seconds']:.1f} s "
          f"({summary['fps']:.1f} frames/s, plus {summary['setup_seconds']:.1f} s loading parts)")
    return 0


def _pose_lines(T: np.ndarray) -> list[str]:
    q = se3.matrix_to_quat_wxyz(T[:3, :3])
    M = T.copy()
    M[:3, 3] *= 1000.0  # people read millimetres; --json keeps metres
    rows = [" ".join(f"{v:+10.4f}" for v in row) for row in M]
    return [f"  [{r}]   (translation in mm)" if i == 0 else f"  [{r}]" for i, r in enumerate(rows)] + [
        f"  xyz (mm)    = ({M[0, 3]:+.2f}, {M[1, 3]:+.2f}, {M[2, 3]:+.2f})",
        f"  q (w,x,y,z) = ({q[0]:+.5f}, {q[1]:+.5f}, {q[2]:+.5f}, {q[3]:+.5f})"]


def _open_estimate_input(args):
    """(frame, assembly) for `apose estimate`: a rendered dataset, a capture folder or a BOP scene folder."""
    from .api import step_context
    from .assembly import load_assembly
    from .bop import BopScene
    from .dataset import Dataset, open_frames

    src = open_frames(args.input)
    asm = load_assembly(args.assembly) if args.assembly else None
    if isinstance(src, Dataset):
        asm = asm or src.assembly
        if args.step not in src.steps:
            step_context(asm, args.step)  # a step the assembly lacks says so first
            raise AposeError(f"{src.root}: step {args.step} was not rendered; rendered steps: {', '.join(map(str, src.steps))}")
        return src.frame(args.step, args.frame), asm
    if asm is None:
        raise AposeError(f"{args.input}: a capture has no assembly of its own; give --assembly A.yaml (and --step)")
    _, ctx = step_context(asm, args.step)
    if isinstance(src, BopScene):
        from .bop import parse_obj_map

        src.obj_of_part = parse_obj_map(args.obj_map, asm.parts)
        return src.frame(args.frame, ctx.view), asm
    src.base, src.part, src.step = tuple(ctx.view.base), ctx.view.part, args.step
    return src, asm


def _estimate_mask(args, frame, asm) -> tuple[np.ndarray, str]:
    from .api import check_mask, find_mask
    from .evaluate import check_mask_source, frame_mask
    from .prompt import parse_box, parse_point

    box = parse_box(args.box) if args.box else None
    point = parse_point(args.point) if args.point else None
    if box is not None or point is not None:
        if args.mask not in (None, "depth"):
            raise AposeError(f"--mask {args.mask} and --box/--point: give one way to find the object")
        return find_mask(frame.rgb, frame.depth, frame.camera, box=box, point=point)
    source = args.mask or ("gt" if frame.masks else "depth")
    if source.lower().endswith((".png", ".jpg", ".bmp", ".tif", ".tiff")):
        import cv2

        from .dataset import _read_image

        return check_mask(_read_image(Path(source), cv2.IMREAD_GRAYSCALE), frame.depth.shape, source), source
    if source == "gt" and not frame.masks:
        raise AposeError(f"{args.input}: no ground-truth masks here; use --box x0,y0,x1,y1, --point u,v, --mask depth "
                         "or --mask MASK.png")
    return frame_mask(frame, check_mask_source(source, asm)), source


def cmd_estimate(args) -> int:
    from .api import run_registration, step_context
    from .evaluate import score_frame
    from .registration import resolve_params

    t0 = time.perf_counter()
    frame, asm = _open_estimate_input(args)
    _, ctx = step_context(asm, args.step)
    params = resolve_params(args.preset, asm.registration, **_upright(args))
    mask, source = _estimate_mask(args, frame, asm)
    est = run_registration(frame.depth, mask, source, frame.camera, frame.T_world_camera, asm, ctx, params,
                           args.orientation_prior, t0, time.perf_counter() - t0, trace_iterations=True)
    r = est.result
    sc = score_frame(frame, r, ctx.part, None if source == "gt" else mask) if frame.T_world_part is not None else None
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
    from .dataset import Dataset
    from .evaluate import evaluate, format_table
    from .registration import resolve_params

    if not (Path(args.dataset) / "dataset_info.json").is_file():
        from .bop import scene_folders

        if scene_folders(Path(args.dataset)):
            return _eval_bop_split(args)
    ds = Dataset(args.dataset)
    if args.score_results:
        from .bop import read_results_csv, score_results

        doc = score_results(ds, read_results_csv(Path(args.score_results)), args.steps)
        print(format_table(doc))
        if args.json:
            from .dataset import write_json
            write_json(Path(args.json), doc)
        return 0
    params = resolve_params(args.preset, ds.assembly.registration, **_upright(args))
    if args.frames is not None and args.frames < 1:
        raise AposeError(f"--frames {args.frames}: expected at least 1")
    if args.workers < 1:
        raise AposeError(f"--workers {args.workers}: expected at least 1")
    if args.json:
        _check_output_file(Path(args.json), "--json")
    if args.bop_results:
        _check_output_file(Path(args.bop_results), "--bop-results")
    for step in ds.missing_steps:
        print(f"warning: step {step} is listed in {ds.root / 'dataset_info.json'} but its folder "
              f"test/{step:06d} is missing; it is left out", file=sys.stderr)
    doc = evaluate(ds, params, args.steps, args.frames, args.mask, args.orientation_prior,
                   progress=sys.stderr.isatty(), workers=args.workers)
    print(format_table(doc))
    unreadable = [f"step {st['step']} frame {f['im_id']}" for st in doc["steps"] for f in st.get("frames", [])
                  if str(f.get("reason", "")).startswith("unreadable frame")]
    if unreadable:
        print(f"warning: {len(unreadable)} frame(s) could not be read and count as failed: {', '.join(unreadable[:5])}",
              file=sys.stderr)
    if args.mask != "gt" and not args.no_gt_compare:  # the same frames with ground-truth masks, beside
        gt = evaluate(ds, params, args.steps, args.frames, "gt", args.orientation_prior,
                      progress=sys.stderr.isatty(), workers=args.workers)
        print(f"\nthe same frames with ground-truth masks (recall with {args.mask} masks -> with gt masks):")
        for st, sg in zip(doc["steps"], gt["steps"]):
            print(f"  step {st['step']}: recall {st['recall_mssd']:.2f} -> {sg['recall_mssd']:.2f} "
                  f"({100 * (st['recall_mssd'] - sg['recall_mssd']):+.0f} points), mask IoU {st['mask_iou']:.3f}")
        doc["gt_masks"] = [{"step": sg["step"], "recall_mssd": sg["recall_mssd"], "adi": sg["adi"], "mssd": sg["mssd"]}
                           for sg in gt["steps"]]
    if args.json:
        from .dataset import write_json
        write_json(Path(args.json), doc)
        print(f"wrote {args.json}")
    if args.bop_results:
        from .bop import results_from_eval, write_results_csv

        write_results_csv(Path(args.bop_results), results_from_eval(ds, doc))
        print(f"wrote {args.bop_results} (BOP19 results)")
    return 0


def _eval_bop_split(args) -> int:
    from .assembly import load_assembly
    from .bop import evaluate_split, parse_obj_map, write_results_csv
    from .evaluate import format_table
    from .registration import resolve_params

    if not args.assembly or args.step is None:
        raise AposeError(f"{args.dataset}: a BOP split; give --assembly A.yaml, --step K and --obj-map PART=OBJ_ID for the "
                         "base's parts")
    if args.score_results:
        raise AposeError("--score-results scores a results file on an apose dataset; on BOP data use bop_toolkit")
    asm = load_assembly(args.assembly)
    for flag in ("json", "bop_results"):
        if getattr(args, flag):
            _check_output_file(Path(getattr(args, flag)), "--" + flag.replace("_", "-"))
    params = resolve_params(args.preset, asm.registration, **_upright(args))
    doc, rows = evaluate_split(Path(args.dataset), asm, args.step, parse_obj_map(args.obj_map, asm.parts), params,
                               args.mask, args.frames, progress=sys.stderr.isatty())
    print(format_table(doc))
    if args.json:
        from .dataset import write_json
        write_json(Path(args.json), doc)
        print(f"wrote {args.json}")
    if args.bop_results:
        write_results_csv(Path(args.bop_results), rows)
        print(f"wrote {args.bop_results} (BOP19 results)")
    return 0


def _upright(args) -> dict:
    if args.upright is None:
        return {}
    if args.preset == "paper" and args.upright:
        raise AposeError("--upright is a search of ours; the paper preset has no such mode (use --preset default)")
    return {"upright": args.upright}


def _estimator_args(p: argparse.ArgumentParser, mask_default: str | None = "gt") -> None:
    p.add_argument("--preset", default="default", choices=["default", "paper"], help="estimator settings (default: ours)")
    p.add_argument("--mask", default=mask_default, metavar="gt|depth|box|MODEL.pt|MASK.png",
                   help="the base object's mask: gt (the data's ground truth; the default where there is one), depth "
                   "(table-plane removal and 3D clustering, no training; the default for captures), box (eval: the "
                   "prompted mask from the ground truth's visible box, as a detector would give), a model from "
                   "`apose train-seg`, or a mask image")
    p.add_argument("--orientation-prior", action="store_true",
                   help="take the CAD's orientation as the base's orientation in the world (true for --base-pose fixed renders)")
    p.add_argument("--upright", action=argparse.BooleanOptionalAction, default=None,
                   help="where a table is seen, first search the yaw of the base standing on it as modelled (its CAD "
                   "z axis along the table's normal), then freely if that fits poorly: on by default in the default "
                   "preset; --no-upright searches freely from the start")


def cmd_train_seg(args) -> int:
    from .dataset import Dataset
    from .segment import save_model, train

    ds = Dataset(args.dataset)
    out = Path(args.out)
    if out.suffix != ".pt":
        raise AposeError(f"--out {out}: name the model file *.pt")
    _check_output_file(out, "--out")  # now, not after minutes of training
    print(f"training a segmentation network for {ds.assembly.name} ({len(ds.assembly.parts)} parts + background) "
          f"on {args.dataset}")
    seg, rep = train(ds, epochs=args.epochs, device=args.device, batch=args.batch, seed=args.seed,
                     max_minutes=args.max_minutes, progress=sys.stderr.isatty())
    save_model(seg, out)
    print(f"trained {rep['epochs']} epochs on {rep['train_frames']} frames in {rep['seconds']:.0f} s ({rep['device']}); "
          f"loss {rep['losses'][0]:.3f} -> {rep['losses'][-1]:.3f}")
    print(f"held-out frames ({rep['frames']}): mean IoU of the base object {rep['mean_base_iou']:.3f} "
          f"(network alone {rep['mean_base_iou_raw']:.3f}; outlines sharpened with depth)")
    for step, v in rep["base_iou"].items():
        print(f"  step {step} base object: IoU {v:.3f}")
    for pid, v in rep["part_iou"].items():
        print(f"  part {pid}: IoU {v:.3f}")
    print(f"wrote {out}; use it with --mask {out}")
    return 0


def _server_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0 exposes the studio to the network)")
    p.add_argument("--port", type=_port, default=8080, help="port (default 8080; the next free one if taken)")
    p.add_argument("--root", default=None, help="the folder whose files the page may open and save (default: the "
                   "current directory, or the assembly file's folder when it lies outside)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="apose", description="6D assembly pose estimation by point-cloud "
                                 "registration, with a browser studio.")
    ap.add_argument("--version", action="version", version=f"apose_studio {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="show debug logging and tracebacks")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_show, _add_render, _add_estimate, _add_eval, _add_train_seg, _add_demo, _add_studio):
        add(sub)
    return ap


def _add_show(sub) -> None:
    p = sub.add_parser("show", help="summarise an assembly file: parts, sizes, steps and poses")
    p.add_argument("assembly", help="assembly YAML file (format apose-assembly/1)")
    p.add_argument("--json", action="store_true", help="print JSON (metres, 4x4 row-major lists)")
    p.set_defaults(func=cmd_show)


def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render a synthetic RGB-D dataset (BOP layout), one scene per assembly step",
                       description="Render N views of every assembly step into a BOP-layout dataset: RGB, depth, "
                       "visible masks, object and camera poses, and each step's ground-truth assembly pose.")
    p.add_argument("assembly", help="assembly YAML file")
    p.add_argument("--out", required=True, help="output folder (must be empty unless --overwrite)")
    p.add_argument("--frames", type=int, default=10, help="views per step (default 10)")
    p.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives the same dataset")
    p.add_argument("--steps", type=_steps, help="only these steps, e.g. 1,3 (default: all)")
    p.add_argument("--noise", default="none", choices=["none", "gaussian", "realsense", "kinect"],
                   help="depth noise: none; gaussian (axial, grows with z^2); realsense (gaussian + edge "
                   "dropouts + disparity quantisation); kinect (Kinect v1 as in LINEMOD: coarser quantisation, "
                   "projector shadows beside edges, no depth on dark or glossy surfaces)")
    p.add_argument("--noise-sigma", type=float, default=0.001, help="axial depth noise at 0.5 m, metres (default 0.001)")
    p.add_argument("--base-pose", default="yaw", choices=["yaw", "fixed"],
                   help="yaw: base at a random position and yaw on the table (default); fixed: base at a known pose, "
                   "only the camera moves (the paper's protocol)")
    p.add_argument("--yaw-range", type=lambda t: _pair(t, "--yaw-range"), metavar="MIN,MAX",
                   help="camera yaw around the base, degrees (default 0,360)")
    p.add_argument("--pitch-range", type=lambda t: _pair(t, "--pitch-range"), metavar="MIN,MAX",
                   help="camera elevation above the table, degrees (default 25,75)")
    p.add_argument("--distance-range", type=lambda t: _pair(t, "--distance-range"), metavar="MIN,MAX",
                   help="camera distance to the base centre, metres (default: the base fills 25-50%% of the image)")
    p.add_argument("--distractors", type=int, default=2, help="random boxes, cylinders and balls on the table (default 2)")
    p.add_argument("--clutter", action="store_true",
                   help="a cluttered bench: objects of the base's height standing against it and around it, the base "
                   "off-centre in the image (tests prompted masks: --box / --point)")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset already in --out")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_render)


def _add_estimate(sub) -> None:
    p = sub.add_parser("estimate", help="estimate the assembly pose in one frame: a rendered dataset, a capture or a BOP scene",
                       description="Exit codes: 0 a pose, 1 the estimate failed (the reason is printed), 2 bad input.")
    p.add_argument("input", help="dataset folder from `apose render`, capture folder (rgb.png, depth.png, camera.json "
                   "with fx,fy,cx,cy or BOP's cam_K) or BOP scene folder (scene_camera.json, rgb/, depth/)")
    p.add_argument("--assembly", help="assembly YAML (needed for a capture or BOP scene; a dataset has its own)")
    p.add_argument("--step", type=int, required=True, help="assembly step (1-based)")
    p.add_argument("--frame", type=int, default=0, help="image id within the step or BOP scene (default 0)")
    p.add_argument("--box", metavar="X0,Y0,X1,Y1", help="a box around the base object in pixels: the mask from depth and colour")
    p.add_argument("--point", metavar="U,V", help="a click on the base object in pixels: the mask from depth and colour")
    p.add_argument("--obj-map", action="append", metavar="PART=OBJ_ID",
                   help="BOP scene: which BOP obj_id each part is (repeatable), for the ground truth in scene_gt.json")
    p.add_argument("--json", action="store_true", help="print JSON (metres): ok, reason, T_world_base, T_world_part, "
                   "T_camera_part, confident, coverage, ambiguous, alternatives, mask, timings, stages")
    _estimator_args(p, mask_default=None)
    p.set_defaults(func=cmd_estimate)


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="evaluate the estimator on a dataset: the paper's per-step table")
    p.add_argument("dataset", help="dataset folder made by `apose render`, or a BOP split folder (e.g. lmo/test: "
                   "numbered scene folders) with --assembly, --step and --obj-map")
    _estimator_args(p)
    p.add_argument("--steps", type=_steps, help="only these steps, e.g. 1,3")
    p.add_argument("--frames", type=int, help="at most this many frames per step (default: all)")
    p.add_argument("--workers", type=int, default=1, help="processes in parallel (default 1)")
    p.add_argument("--json", metavar="OUT", help="also write the full results (per frame) as JSON")
    p.add_argument("--no-gt-compare", action="store_true",
                   help="with --mask depth|MODEL.pt, skip the second run with ground-truth masks")
    p.add_argument("--assembly", help="BOP split: the assembly whose step to evaluate")
    p.add_argument("--step", type=int, help="BOP split: the assembly step (1-based)")
    p.add_argument("--obj-map", action="append", metavar="PART=OBJ_ID",
                   help="BOP split: the BOP obj_id of a part (repeatable), e.g. --obj-map can=5")
    p.add_argument("--bop-results", metavar="OUT.csv", help="also write the estimates as a BOP19 results CSV "
                   "(scene_id = step, obj_id = base[0], R and t of base[0] in the camera, mm)")
    p.add_argument("--score-results", metavar="CSV", help="score a BOP19 results CSV from any method on this dataset "
                   "with our metrics and table, instead of running the estimator")
    p.set_defaults(func=cmd_eval)


def _add_train_seg(sub) -> None:
    p = sub.add_parser("train-seg", help="train a segmentation network (torch) on a rendered dataset of one assembly")
    p.add_argument("dataset", help="dataset folder made by `apose render` (noisy renders with --noise realsense transfer best)")
    p.add_argument("--out", required=True, help="model file to write (*.pt)")
    p.add_argument("--epochs", type=_positive_int, default=60, help="passes over the training frames (default 60)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="default: cuda when torch sees a GPU")
    p.add_argument("--batch", type=_positive_int, default=8, help="frames per step (default 8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the split, the initial weights and the augmentation")
    p.add_argument("--max-minutes", type=float, help="stop after the epoch that passes this wall time")
    p.set_defaults(func=cmd_train_seg)


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on the embedded sample assembly: show, render, estimate, then open the studio")
    p.add_argument("assembly", nargs="?", help="another assembly file instead of the sample")
    p.add_argument("--out", default="out/demo", help="where the demo dataset goes (default out/demo; an earlier demo there is replaced, anything else refused)")
    p.add_argument("--frames", type=int, default=2, help="views per step (default 2)")
    p.add_argument("--no-studio", action="store_true", help="stop after the estimates instead of opening the studio")
    _server_args(p)
    p.set_defaults(func=cmd_demo)


def _add_studio(sub) -> None:
    p = sub.add_parser("studio", help="open the browser studio: author assemblies, inspect datasets and registrations")
    p.add_argument("assembly", nargs="?", help="assembly YAML file to open (default: a new, empty assembly)")
    p.add_argument("--dataset", help="dataset folder (from `apose render`) or capture folder to open in the Inspect tab")
    _server_args(p)
    p.set_defaults(func=cmd_studio)


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return args.func(args)
    except AposeError as e:  # bad input: the message names the thing and the fix
        for line in str(e).splitlines():
            print(f"error: {line}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a bug: one line, plus the traceback with --verbose
        if args.verbose:
            raise
        print(f"error: unexpected {type(e).__name__}: {e} (run with -v for the traceback, and please report it)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
