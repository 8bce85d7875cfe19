"""`apose` command line: a thin shell over the core. Errors become one line each, never a traceback."""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
import time
from dataclasses import replace
from pathlib import Path

from apose_studio import __version__
from apose_studio.assembly.summary import show_json, show_text
from apose_studio.cli.common import Printable, check_output_file, estimator_args
from apose_studio.errors import AposeError, os_error_text
from apose_studio.safeio import check_path_text
from apose_studio.text import shorten_values

REPO = Path(__file__).resolve().parents[2]  # the checkout: apose_studio/cli/commands.py -> the repo
SAMPLES = REPO / "sample_assemblies"
DEFAULT_SAMPLE = SAMPLES / "helical_gearbox" / "assembly.yaml"


def cmd_estimate(args) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.cli.frames import cmd_estimate

    return cmd_estimate(args)


def cmd_track(args) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.cli.track import cmd_track

    return cmd_track(args)


def cmd_export_mcap(args) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.cli.track import cmd_export_mcap

    return cmd_export_mcap(args)


def cmd_capture(args) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.cli.track import cmd_capture

    return cmd_capture(args)


def cmd_eval(args) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.cli.frames import cmd_eval

    return cmd_eval(args)


def cmd_show(args) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.assembly.mesh import load_parts
    from apose_studio.assembly.model import load_assembly

    asm = load_assembly(args.assembly)
    models = load_parts(asm)
    if args.json:
        print(json.dumps(show_json(asm, models), indent=2))
    else:
        print(show_text(asm, models))
    return 0


def cmd_demo(args) -> int:
    """The slice end to end on a sample: summary, a small rendered dataset, one estimate per step."""
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.assembly.mesh import load_parts
    from apose_studio.assembly.model import load_assembly
    from apose_studio.data.dataset import Dataset
    from apose_studio.estimation import StepContext
    from apose_studio.evaluate import estimate_and_score
    from apose_studio.registration import doubts, resolve_params
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

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
    from apose_studio.studio.inspection import ResultCache

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
              + ("" if r.confident else f"  (not confident: {doubts(r)})"))
    print(f"\nnext: `apose eval {out}` for the per-step table, `apose estimate {out} --step 1` for one frame")
    if args.no_studio:
        return 0
    print("\nopening the studio on this assembly and dataset (the estimates above are cached in its Inspect tab)")
    return _serve_studio(path, out, args.host, args.port, cache, root=args.root, token=args.token)


def _serve_studio(assembly, dataset, host: str, port: int, cache=None, root=None, token=None, obj_map=None) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.studio import serve
    from apose_studio.studio.webguard import is_loopback_bind

    if root is not None and not Path(root).is_dir():
        raise AposeError(f"--root {root}: no such folder")
    server, studio = serve(assembly, dataset, host=host, port=port, cache=cache, root=root, token=token, obj_map=obj_map)
    print(f"studio: {studio.url}  (Ctrl-C to stop; open this address: the page needs the token in it)")
    print(f"workspace: the page may open and save files only under {', '.join(str(r) for r in studio.workspace.roots)}")
    if not is_loopback_bind(host):
        print(f"note: listening on {host}; the page and its websocket need the token in the address above. Anyone "
              "with that address can open and save files in the workspace: share it only with people you trust",
              file=sys.stderr)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        studio.shutdown()  # the player, a live camera, the background preparation
        server.stop()
    return 0


def _check_obj_map(obj_map: list[str] | None, assembly, scene=None, step: int | None = None) -> None:
    """--obj-map read now, in the CLI's words (the studio reads it again): against the assembly's parts, and
    when `scene` is a BOP scene folder, against the obj_ids it shows and (with `step`) the step's base."""
    if obj_map:
        from apose_studio.assembly.model import load_assembly
        from apose_studio.data.bop import BopScene, is_bop_scene, parse_obj_map

        if scene is not None and not is_bop_scene(Path(scene)):
            raise AposeError(f"--obj-map maps the parts to a BOP scene's obj_ids; {scene} is not a BOP scene folder "
                             "(scene_camera.json, depth/): remove --obj-map")
        if assembly is None:
            raise AposeError("--obj-map names the parts of an assembly: give the assembly file too")
        asm = load_assembly(assembly)
        mapped = parse_obj_map(obj_map, asm.parts)
        if scene is not None:
            base = asm.steps[step - 1].base[0] if step is not None and 0 < step <= len(asm.steps) else None
            BopScene(scene).check_obj_map(mapped, base)


def cmd_studio(args) -> int:
    if args.assembly and not Path(args.assembly).is_file():
        raise AposeError(f"{args.assembly}: no such assembly file")
    _check_obj_map(args.obj_map, args.assembly, args.dataset)
    return _serve_studio(args.assembly, args.dataset, args.host, args.port, root=args.root, token=args.token,
                         obj_map=args.obj_map)


def cmd_serve(args) -> int:
    from apose_studio.cli.common import param_overrides, params_of
    from apose_studio.service import EstimationService, is_loopback, make_server

    if not Path(args.assembly).is_file():
        raise AposeError(f"{args.assembly}: no such assembly file")
    if args.token is not None and (len(args.token) < 16 or not all(c.isascii() and (c.isalnum() or c in "-_")
                                                                    for c in args.token)):
        raise AposeError("--token: at least 16 characters of A-Z a-z 0-9 - _")
    from apose_studio.assembly.model import load_assembly

    asm = load_assembly(args.assembly)
    overrides = param_overrides(args)
    params_of(args, asm.registration)  # a bad --param is said now, not on the first request
    t0 = time.perf_counter()
    service = EstimationService(asm, args.preset, overrides, queue=args.queue,
                                **({"max_pixels": args.max_pixels} if args.max_pixels else {}),
                                **({"workers": args.workers} if args.workers else {}))
    try:
        server = make_server(service, args.host, args.port, args.token)
    except OSError as e:
        raise AposeError(f"--host {args.host} --port {args.port}: cannot listen there ({e.strerror or e}); choose "
                         "another port") from None
    host, port = server.server_address[:2]
    print(f"serve: http://{host}:{port} ({asm.name}: steps 1..{len(asm.steps)} warm in {time.perf_counter() - t0:.1f} s; "
          f"{service.workers} estimate(s) at once; GET /health, POST /estimate; docs/ROBOT.md)", flush=True)
    if server.token is not None:
        print(f"serve: token {server.token} (send 'Authorization: Bearer {server.token}')"
              + ("" if is_loopback(args.host) else "; required beyond loopback"), flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("serve: stopped")
    finally:
        server.server_close()
    return 0


def cmd_export_html(args) -> int:
    from apose_studio.assembly.fileio import atomic_write_text
    from apose_studio.studio.export import export_replay

    out = Path(args.out)
    check_output_file(out, "--out", inputs=[args.input])
    _check_obj_map(args.obj_map, args.assembly, args.input, args.step)
    page, result = export_replay(args.input, args.step, args.frame, args.assembly, args.orientation_prior, args.obj_map)
    atomic_write_text(out, page)
    from apose_studio.registration import doubts

    verdict = "confident" if result.confident else f"not confident ({doubts(result)})"
    print(f"wrote {out} ({len(page.encode('utf-8')) / 1e6:.1f} MB): step {args.step}, frame {args.frame}, {verdict}, "
          f"{len(result.stages)} stages; open it in any browser (no server, no network)")
    return 0


def _pair(text: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected two numbers as min,max (e.g. 20,70), got {text!r}") from None
    return a, b


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number of at least 1, got {text!r}")
    return n


VALUE_ARGUMENTS = {"box", "point", "pick_box", "pick_point", "param", "obj_map", "grasp", "tf_prefix", "preset",
                   "instances", "upright", "host", "token", "serial", "size", "device", "noise", "base_pose", "clutter",
                   "trajectory", "command"}  # text arguments that are values, not paths (said so in their refusals)


def _argument_labels(parser: argparse.ArgumentParser, args) -> dict[str, str]:
    """dest -> how the command line spells it (`--box`; a positional one by its name, `INPUT`) for the command run."""
    labels = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            sub = action.choices.get(getattr(args, "command", None))
            for a in (sub._actions if sub is not None else []):
                labels[a.dest] = a.option_strings[-1] if a.option_strings else a.dest.upper()
        elif action.option_strings:
            labels.setdefault(action.dest, action.option_strings[-1])
    return labels


def _check_argument_text(args, labels: dict[str, str] | None = None) -> None:
    """Every text argument without NUL bytes and control characters and within the system's path length (a path
    named on the command line reaches open() only after this); each named as the command line spells it."""
    labels = labels or {}
    for name, value in vars(args).items():
        for v in value if isinstance(value, list) else [value]:
            if isinstance(v, str):
                check_path_text(v, labels.get(name, f"--{name.replace('_', '-')}"), value=name in VALUE_ARGUMENTS)


def _count(lo: int, hi: int):
    """An argparse type: a whole number from lo to hi."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = None
        if v is None or not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected a whole number from {lo} to {hi}, got {text!r}")
        return v
    return parse


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
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.assembly.model import load_assembly
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    asm = load_assembly(args.assembly)
    settings = RenderSettings(frames=args.frames, seed=args.seed, noise=args.noise, noise_sigma_at_05m=args.noise_sigma,
                              base_pose=args.base_pose, distractors=args.distractors, clutter=args.clutter,
                              views_per_scene=args.views_per_scene, trajectory=args.trajectory, depth_bias_m=args.depth_bias / 1000.0,
                              misregistration_px=args.misregistration, bleed_px=args.bleed,
                              base_fill=args.base_fill)
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


def cmd_train_seg(args) -> int:
    # loaded per command: `apose --help` loads none of the core
    from apose_studio.data.dataset import Dataset
    from apose_studio.masks.segment import save_model, train

    ds = Dataset(args.dataset)
    out = Path(args.out)
    if out.suffix != ".pt":
        raise AposeError(f"--out {out}: name the model file *.pt")
    check_output_file(out, "--out")  # now, not after minutes of training
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
    p.add_argument("--token", default=None, help="the secret in the studio's address (/t/TOKEN/; at least 16 "
                   "characters of A-Z a-z 0-9 - _); default: a new random one each start, printed with the address")


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose usage errors (a missing or malformed option) end as a refusal does: with `--json`
    among the arguments (show, estimate), the JSON object on stdout too (`refused`)."""

    def error(self, message: str):
        self.print_usage(sys.stderr)
        argv = sys.argv[1:] if _ARGV[0] is None else _ARGV[0]
        wants_json = (any(a == "--json" or a.startswith("--json=") for a in argv)  # anywhere: before the command too
                      and any(a in ("show", "estimate") for a in argv))
        raise SystemExit(refused(argparse.Namespace(json=wants_json), f"{self.prog}: {message}", 2))


_ARGV: list = [None]  # the arguments main() was given (None: sys.argv's)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="apose", description="6D assembly pose estimation by point-cloud "
                                 "registration, with a browser studio.")
    ap.add_argument("--version", action="version", version=f"apose_studio {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="show debug logging and tracebacks")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_show, _add_render, _add_estimate, _add_track, _add_eval, _add_train_seg, _add_demo, _add_studio,
                _add_export_html, _add_serve):
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
    p.add_argument("--views-per-scene", type=int, default=1, metavar="K",
                   help="camera poses per placement of the base, at least 30 degrees apart, as an eye-in-hand camera "
                   "takes them (default 1); --frames stays the number of images per step")
    p.add_argument("--trajectory", nargs="?", const="approach", default="", choices=["approach", "orbit"],
                   help="one placement per step seen by a camera moving along a path, a frame per point (alone: "
                   "approach, an eye-in-hand camera closing in and turning 40 degrees; orbit: 90 degrees round at one "
                   "distance); for `apose track`")
    p.add_argument("--seed", type=_count(0, 2 ** 32 - 1), default=0, help="random seed; the same seed gives the same dataset")
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
    p.add_argument("--distractors", type=_count(0, 50), default=2, help="random boxes, cylinders and balls on the table (default 2)")
    p.add_argument("--clutter", nargs="?", const="bench", default="", metavar="KINDS",
                   help="what a real bench adds, comma-separated (alone: bench): bench (objects of the base's height "
                   "standing against it and around it, the base off-centre in the image), stacked (a flat object "
                   "lying on top of the base), hidden (an object in front leaves 20-35%% of the base visible), "
                   "textured (printed patterns on the table, the clutter and the base); tests prompted masks")
    p.add_argument("--depth-bias", type=float, default=0.0, metavar="MM",
                   help="added to every depth reading, millimetres (a Kinect reads a few mm off; default 0)")
    p.add_argument("--misregistration", type=float, default=0.0, metavar="PX",
                   help="the depth image shifted against the colour image by this many pixels, in a direction drawn "
                   "per frame (masks and poses agree with the colour image; default 0)")
    p.add_argument("--bleed", type=int, default=0, metavar="PX",
                   help="near surfaces read this many pixels wider in depth than in colour, over farther ones (a "
                   "sensor's correlation window fattens foreground objects; kinect noise bleeds 1 px of its own; "
                   "default 0)")
    p.add_argument("--base-fill", type=lambda t: _pair(t, "--base-fill"), default=(0.25, 0.5), metavar="MIN,MAX",
                   help="the share of the image's short side the base spans, which sets the camera distance unless "
                   "--distance-range is given (default 0.25,0.5; a far, small base: 0.1,0.2)")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset already in --out")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_render)


def _add_estimate(sub) -> None:
    p = sub.add_parser("estimate", help="estimate the assembly pose in one frame: a rendered dataset, a capture or a BOP scene",
                       description="Exit codes: 0 a pose, 1 the estimate failed (the reason is printed), 2 bad input.")
    p.add_argument("input", nargs="+", help="dataset folder from `apose render`, capture folder (rgb.png, depth.png, camera.json "
                   "with fx,fy,cx,cy or BOP's cam_K) or BOP scene folder (scene_camera.json, rgb/, depth/); several "
                   "capture folders of one placement (camera.json with cam_R_w2c, cam_t_w2c) give one fused estimate")
    p.add_argument("--assembly", help="assembly YAML (needed for a capture or BOP scene; a dataset has its own)")
    p.add_argument("--step", type=int, required=True, help="assembly step (1-based)")
    p.add_argument("--frame", type=int, default=0, help="image id within the step or BOP scene (default 0)")
    p.add_argument("--views", type=_count(1, 64), default=1, metavar="K",
                   help="a dataset: fuse up to K frames of --frame's placement (default 1); several capture folders are "
                   "fused whatever this says")
    p.add_argument("--instances", choices=["all"], help="find every instance of the step's base (identical roots, e.g. "
                   "four motors on a bench; or a region, `roi`, at each place of its part alike to it, e.g. the eight "
                   "seats of an engine head) without a prompt: each estimated on its own, listed left to right "
                   "('instances' in --json)")
    p.add_argument("--box", metavar="X0,Y0,X1,Y1", action="append",
                   help="a box around the base object in pixels: the mask from depth and colour (several views: once per view)")
    p.add_argument("--point", metavar="U,V", action="append",
                   help="a click on the base object in pixels: the mask from depth and colour (several views: once per view)")
    p.add_argument("--align-depth", action="store_true",
                   help="with --box/--point: find how far the depth lies shifted against the colour image around the "
                   "prompt (a Kinect v1 registered a few pixels off) and move it back before the mask and the "
                   "registration (docs/CAPTURES_AND_BOP.md)")
    p.add_argument("--obj-map", action="append", metavar="PART=OBJ_ID",
                   help="BOP scene: which BOP obj_id each part is (repeatable), for the ground truth in scene_gt.json")
    p.add_argument("--json", action="store_true", help="print JSON (metres, 4x4 matrices): ok, reason, T_world_base, "
                   "T_world_part, T_camera_part, T_world_camera, confident, doubts, coverage, ambiguous, alternatives, "
                   "equivalent, base_confident, depth_shift_px, mask, timings_s, stages (and with --hand-eye the robot "
                   "targets: T_robot_part, T_robot_gripper_place, ...); every field: docs/CAPTURES_AND_BOP.md")
    robot = p.add_argument_group("robot targets (docs/ROBOT.md)")
    robot.add_argument("--hand-eye", metavar="FILE", help="the camera in the robot's frame: JSON/YAML with T_robot_camera "
                       "(eye-to-hand) or T_flange_camera (eye-in-hand; the arm's T_robot_flange in the capture's "
                       "camera.json or in FILE), an easy_handeye2 calibration, or a 4x4 matrix; adds the gripper's "
                       "place, pre-place (and pick, lift) poses in the robot's frame")
    robot.add_argument("--grasp", metavar="NAME", help="which of the part's grasps (default: its first)")
    robot.add_argument("--pick-box", metavar="X0,Y0,X1,Y1", help="a box around the loose part in the same frame: "
                       "where to pick it (T_robot_part_pick, T_robot_gripper_pick, T_robot_gripper_lift)")
    robot.add_argument("--pick-point", metavar="U,V", help="a click on the loose part (instead of --pick-box)")
    robot.add_argument("--mcap", metavar="OUT.mcap", help="also write the targets as ROS 2 messages (/tf_static, "
                       "PoseStamped, PoseArray) in an MCAP file: ros2 bag play OUT.mcap, or open it in Foxglove")
    robot.add_argument("--tf-prefix", default="", metavar="PREFIX", help="prefix of the target frames in /tf_static "
                       "(default none: apose_gripper_place, ...)")
    estimator_args(p, mask_default=None)
    p.set_defaults(func=cmd_estimate)


def _add_track(sub) -> None:
    p = sub.add_parser("track", help="follow a step's pose through a sequence of frames (`apose render --trajectory`)",
                       description="Each frame is tracked from the last confident pose (a short ICP, judged like any "
                       "estimate); the first frame, and any frame where tracking loses the base, is estimated anew. "
                       "Prints a line per frame and a summary. Exit codes: 0 at least one confident pose, 1 none, "
                       "2 bad input.")
    p.add_argument("input", help="dataset folder from `apose render --trajectory` (frames of one placement, in order), or "
                   "a ROS 2 recording: an .mcap file or a rosbag2 folder holding one (colour and aligned depth "
                   "sensor_msgs/Image, CameraInfo; docs/ESTIMATOR.md#recordings)")
    p.add_argument("--assembly", help="assembly YAML (needed for a recording; a dataset has its own)")
    p.add_argument("--step", type=int, required=True, help="assembly step (1-based)")
    p.add_argument("--first", type=_count(0, 10 ** 9), default=0, help="the first frame (image id) to track (default 0)")
    p.add_argument("--count", type=_count(0, 10 ** 9), default=0, help="at most this many frames (default: all)")
    p.add_argument("--box", metavar="X0,Y0,X1,Y1", action="append",
                   help="a box around the base in the first frame (pixels), instead of --mask")
    p.add_argument("--point", metavar="U,V", action="append", help="a click on the base in the first frame, instead of --mask")
    p.add_argument("--json", metavar="OUT", help="also write the summary and every frame's result as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="the summary only, no line per frame")
    estimator_args(p, mask_default=None)
    p.set_defaults(func=cmd_track)
    p = sub.add_parser("export-mcap", help="write a rendered step as a ROS 2 recording (MCAP), as a RealSense node publishes",
                       description="Colour (rgb8), depth aligned to it (16UC1, mm), the colour camera_info and the camera's "
                       "pose (/apose/camera_pose, geometry_msgs/PoseStamped) per frame, at --rate frames per second: what "
                       "`apose track` and `ros2 bag play` read.")
    p.add_argument("dataset", help="dataset folder from `apose render` (--trajectory plays best)")
    p.add_argument("--step", type=int, required=True, help="assembly step (1-based)")
    p.add_argument("--out", required=True, help="the .mcap file to write")
    p.add_argument("--rate", type=float, default=30.0, help="frames per second (default 30)")
    p.set_defaults(func=cmd_export_mcap)
    p = sub.add_parser("capture", help="save frames of an Intel RealSense as capture folders (`apose estimate` reads them)",
                       description="Colour (rgb8) and depth aligned to it by the SDK, the colour camera's intrinsics as "
                       "cam_K and the device's depth unit as depth_scale: rgb.png, depth.png, camera.json per frame. Needs "
                       "the [realsense] extra (pip install 'apose_studio[realsense]').")
    p.add_argument("--out", required=True, help="the capture folder to write (with --count N: a folder of N of them)")
    p.add_argument("--serial", help="the camera's serial number (default: the first found)")
    p.add_argument("--size", default="640x480", help="colour and depth size, WIDTHxHEIGHT (default 640x480)")
    p.add_argument("--fps", type=_count(1, 300), default=30, help="frames per second (default 30)")
    p.add_argument("--count", type=_count(1, 100000), default=1, help="how many frames to save (default 1)")
    p.add_argument("--settle", type=_count(0, 10000), default=30,
                   help="frames skipped first while auto-exposure settles (default 30)")
    p.set_defaults(func=cmd_capture)


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="evaluate the estimator on a dataset: the paper's per-step table")
    p.add_argument("dataset", help="dataset folder made by `apose render`, or a BOP split folder (e.g. lmo/test: "
                   "numbered scene folders) with --assembly, --step and --obj-map")
    estimator_args(p)
    p.add_argument("--steps", type=_steps, help="only these steps, e.g. 1,3")
    p.add_argument("--frames", type=int, help="at most this many frames per step (default: all)")
    p.add_argument("--workers", type=int, default=1, help="processes in parallel (default 1; --views runs in one)")
    p.add_argument("--views", type=_count(1, 64), default=1, metavar="K",
                   help="group the frames by placement (apose render --views-per-scene) and fuse up to K per estimate "
                   "(default 1: every frame alone); the JSON records list the frames in im_ids")
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
    p.add_argument("--seed", type=_count(0, 2 ** 32 - 1), default=0, help="seed of the split, the initial weights and the augmentation")
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
    p.add_argument("--dataset", help="dataset folder (from `apose render`), capture folder or BOP scene folder to open "
                   "in the Inspect tab")
    p.add_argument("--obj-map", action="append", metavar="PART=OBJ_ID",
                   help="BOP scene: which BOP obj_id each part is (repeatable), for the ground truth in scene_gt.json")
    _server_args(p)
    p.set_defaults(func=cmd_studio)


def _add_serve(sub) -> None:
    p = sub.add_parser("serve", help="a warm estimation service over HTTP/JSON for robot programs (POST /estimate)",
                       description="Loads ASSEMBLY once and keeps every step warm; answers POST /estimate with the "
                       "JSON of `apose estimate --json` (docs/ROBOT.md#apose-serve).")
    p.add_argument("assembly", help="assembly YAML file")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only; "
                   "any other address requires the token)")
    p.add_argument("--port", type=_port, default=8765, help="port (default 8765)")
    p.add_argument("--token", default=None, help="the token clients send as 'Authorization: Bearer TOKEN' (at least 16 "
                   "characters of A-Z a-z 0-9 - _); default: none on loopback, a new random one otherwise")
    p.add_argument("--queue", type=_count(1, 256), default=8, help="requests in the service at once (--workers estimating, "
                   "the rest waiting); the next gets 503 (default 8)")
    p.add_argument("--workers", type=_count(1, 16), default=None, metavar="N", help="estimates at once (default: 2, or 1 "
                   "on one core); each answer is the same whatever runs beside it")
    p.add_argument("--max-pixels", type=_count(10_000, 50_000_000), default=None, metavar="N",
                   help="the largest frame taken, in pixels (default 2304000: 1920x1200); a bigger one gets 413")
    estimator_args(p, per_frame=False)
    p.set_defaults(func=cmd_serve)


def _add_export_html(sub) -> None:
    p = sub.add_parser("export-html", help="estimate one frame and write the studio's inspect view and registration "
                       "replay as one HTML page that opens without a server")
    p.add_argument("input", help="dataset folder from `apose render`, or a capture or BOP scene folder (with --assembly)")
    p.add_argument("--assembly", help="assembly YAML (needed for a capture or BOP scene; a dataset has its own)")
    p.add_argument("--step", type=int, required=True, help="assembly step (1-based)")
    p.add_argument("--frame", type=int, default=0, help="image id within the step or BOP scene (default 0)")
    p.add_argument("--orientation-prior", action="store_true", help="take the CAD orientation as the base's")
    p.add_argument("--obj-map", action="append", metavar="PART=OBJ_ID",
                   help="BOP scene: which BOP obj_id each part is (repeatable), for the ground truth in scene_gt.json")
    p.add_argument("--out", required=True, help="the HTML file to write")
    p.set_defaults(func=cmd_export_html)


def main(argv=None) -> int:
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = Printable(out), Printable(err)
    try:
        return _main(argv)
    finally:
        sys.stdout, sys.stderr = out, err


PIXEL_FLAGS = ("--box", "--point", "--pick-box")  # values that may start with a minus (a box reaching off the image)


def joined_pixel_values(argv: list[str]) -> list[str]:
    """`--box -5,-5,20,20` as `--box=-5,-5,20,20`: argparse takes a value that starts with '-' (and is not a
    plain negative number) for an option and said only "expected one argument"."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a in PIXEL_FLAGS and i + 1 < len(argv) and re.match(r"-[0-9.]", argv[i + 1]):
            out.append(f"{a}={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def _main(argv=None) -> int:
    parser = build_parser()
    _ARGV[0] = None if argv is None else list(argv)
    args = parser.parse_args(joined_pixel_values(list(sys.argv[1:] if argv is None else argv)))
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        _check_argument_text(args, _argument_labels(parser, args))
        return args.func(args)
    except AposeError as e:  # bad input: the message names the thing and the fix
        return refused(args, "\n".join(shorten_values(line) for line in str(e).splitlines()), 2)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `apose show ... | head`: the reader left; say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as e:  # the system refused: a full disk, a read-only folder, a name too long
        return refused(args, os_error_text(e), 2)
    except MemoryError:
        return refused(args, "out of memory; use smaller inputs (fewer frames, a decimated mesh, a smaller image)", 2)
    except Exception as e:  # a bug: one line, plus the traceback with --verbose
        if args.verbose:
            raise
        return refused(args, f"unexpected {type(e).__name__}: {shorten_values(str(e))} (run with -v for the traceback, "
                       "and please report it)", 1)


def refused(args, message: str, code: int) -> int:
    """Say why a command did nothing (`error: ...` on stderr, a line each) and return its exit code. Where the
    command was asked for JSON on stdout (`--json` as a flag: show, estimate), the refusal is JSON there too
    ({"ok": false, "refused": true, "reason": ..., "exit_code": ...}), so that a script reading it needs no second
    way of failing."""
    for line in message.splitlines():
        print(f"error: {line}", file=sys.stderr)
    if getattr(args, "json", None) is True:
        print(json.dumps({"ok": False, "refused": True, "reason": message, "exit_code": code}))
    return code


if __name__ == "__main__":
    sys.exit(main())
