"""Evaluation: estimate every frame of every step of a dataset (ours, or a BOP split), score it against
the ground truth with the paper's metrics, and tabulate it like the paper; also score another method's
BOP19 results file on one of our datasets. The estimates themselves come from `estimation`."""

from __future__ import annotations

import math
import multiprocessing as mp
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from apose_studio.assembly.mesh import PartModel, load_parts
from apose_studio.data.bop import BopResult, BopScene, best_per_image, scene_folders, step_truth
from apose_studio.data.dataset import Dataset, DatasetError, Frame, pose_entry
from apose_studio.errors import AposeError
from apose_studio.estimation import (
    StepContext,
    check_mask_source,
    estimate_frame,
    estimate_frames,
    frame_mask,
    region_truth_prompt,
    step_context,
)
from apose_studio.geometry import metrics, se3
from apose_studio.masks.segment import iou
from apose_studio.registration import TIE_MARGIN, Params, RegistrationResult
from apose_studio.registration.scoring import twin_placements
from apose_studio.registration.types import View


@dataclass
class FrameScore:
    scene_id: int
    im_id: int
    ok: bool
    reason: str = ""
    T_world_part_est: np.ndarray | None = None
    T_world_part_gt: np.ndarray | None = None
    adi: float | None = None
    mssd: float | None = None
    mssd_mod_base_sym: float | None = None  # MSSD to the nearest of the truth and its exact-symmetry twins (the same
    # assembly: symmetry.EXACT_SYMMETRY_MAX_M); near-symmetric twins are not forgiven
    mssd_best_tied: float | None = None  # the best MSSD among the placements tied with the estimate (its alternatives):
    # a wrong estimate whose truth was among them is a near-symmetric twin told apart wrongly
    te: float | None = None
    re_deg: float | None = None
    fitness: float | None = None
    inlier_rmse: float | None = None
    time_s: float = 0.0
    ambiguous: bool = False
    confident: bool = False
    candidates: list = field(default_factory=list)
    mask_iou: float | None = None  # predicted base mask against the ground truth (when not using gt)
    im_ids: list[int] | None = None  # the frames a fused estimate used (apose eval --views), im_id the first

    def set_errors(self, T: np.ndarray, part: PartModel, twins=()) -> None:
        """The estimate T (T_world_part) and its errors against T_world_part_gt; `twins`: the truth's
        placements that the base's exact symmetries make the same assembly (see `truth_twins`)."""
        G = self.T_world_part_gt
        self.T_world_part_est = T
        self.adi = metrics.adi(T, G, part.samples)
        self.mssd = metrics.mssd(T, G, part.samples, part.symmetries)
        self.mssd_mod_base_sym = min([self.mssd] + [metrics.mssd(T, G2, part.samples, part.symmetries) for G2 in twins])
        self.mssd_best_tied = self.mssd_mod_base_sym
        self.te, self.re_deg = metrics.te(T, G), metrics.re_deg(T, G)

    def near_twin(self, diameter: float) -> bool:
        """Wrong (exact twins aside), but right among the placements tied with it: a near-symmetric twin."""
        return bool(self.ok and self.mssd_mod_base_sym is not None and self.mssd_mod_base_sym >= 0.1 * diameter
                    and self.mssd_best_tied is not None and self.mssd_best_tied < 0.1 * diameter)

    def to_json(self) -> dict:
        out = {"scene_id": self.scene_id, "im_id": self.im_id, "ok": self.ok,
               "T_world_part_est": None if self.T_world_part_est is None else self.T_world_part_est.tolist(),
               "T_world_part_gt": None if self.T_world_part_gt is None else self.T_world_part_gt.tolist(),
               "adi": self.adi, "mssd": self.mssd, "mssd_mod_base_sym": self.mssd_mod_base_sym,
               "mssd_best_tied": self.mssd_best_tied, "te": self.te,
               "re_deg": self.re_deg, "fitness": self.fitness, "inlier_rmse": self.inlier_rmse,
               "time_s": self.time_s, "ambiguous": self.ambiguous, "confident": self.confident,
               "candidates": self.candidates, "mask_iou": self.mask_iou}
        if self.im_ids is not None:
            out["im_ids"] = list(self.im_ids)
        if not self.ok:
            out["reason"] = self.reason
        return out


def truth_twins(T_world_part_gt: np.ndarray, T_base_part: np.ndarray, base_symmetries) -> list[np.ndarray]:
    """The ground truth's placements that the base's exact symmetries (T_base_base, identity first) make
    the same assembly: the base turned onto itself, the part with it."""
    if base_symmetries is None:
        return []
    return twin_placements(T_world_part_gt @ se3.inv(T_base_part), T_world_part_gt, base_symmetries)


def score_frame(frame: Frame, result: RegistrationResult, part: PartModel, mask: np.ndarray | None = None,
                base_symmetries: np.ndarray | None = None) -> FrameScore:
    """Metrics of one estimate against the frame's ground truth (metres, degrees); with the mask the
    estimate used, also its IoU against the ground-truth base mask. `base_symmetries`: the base's exact
    symmetries (StepContext.base.symmetries), which `mssd_mod_base_sym` forgives."""
    s = FrameScore(frame.step, frame.im_id, result.ok, result.reason, time_s=result.seconds,
                   T_world_part_gt=frame.T_world_part)
    if mask is not None and frame.masks:
        s.mask_iou = iou(mask, frame.base_mask())
    if not result.ok:
        return s
    G = frame.T_world_part
    twins = truth_twins(G, frame.T_base_part, base_symmetries)
    s.set_errors(result.T_world_part, part, twins)
    best = result.candidates[0].score if result.candidates else 0.0
    tied = [c for c in result.candidates if c.score >= best - TIE_MARGIN] or result.candidates
    s.mssd_best_tied = min([s.mssd_mod_base_sym] + [metrics.mssd(c.T_world_part, G2, part.samples, part.symmetries)
                                                    for c in tied for G2 in [G] + twins])
    s.fitness, s.inlier_rmse = result.fitness, result.inlier_rmse
    s.ambiguous, s.confident = bool(result.ambiguous), bool(result.confident)
    s.candidates = [{"T_world_part": c.T_world_part.tolist(), "score": c.score, "fitness": c.fitness,
                     "source_fitness": None if np.isnan(c.source_fitness) else c.source_fitness} for c in result.candidates]
    return s


def _stats(values) -> dict:
    v = np.array([x for x in values if x is not None], dtype=float)
    return {"mean": float(v.mean()) if len(v) else None, "std": float(v.std()) if len(v) else None}


def summarise_step(step: int, scores: list[FrameScore], part: PartModel) -> dict:
    times = np.array([s.time_s for s in scores])
    mssd = [s.mssd if s.ok else np.nan for s in scores]
    mssd_sym = [s.mssd_mod_base_sym if s.ok else np.nan for s in scores]
    return {
        "step": step, "n_frames": len(scores), "part": part.id, "part_diameter": part.diameter,
        "failed": int(sum(not s.ok for s in scores)),
        "fitness": _stats(s.fitness for s in scores), "inlier_rmse": _stats(s.inlier_rmse for s in scores),
        "adi": _stats(s.adi for s in scores), "mssd": _stats(s.mssd for s in scores),
        "te": _stats(s.te for s in scores), "re_deg": _stats(s.re_deg for s in scores),
        "time_s": {"mean": float(times.mean()), "median": float(np.median(times))},
        "recall_mssd": metrics.recall(mssd, part.diameter),
        "recall_mssd_mod_base_sym": metrics.recall(mssd_sym, part.diameter),
        "ar_mssd": metrics.average_recall(mssd, part.diameter),
        "ambiguous": int(sum(s.ambiguous for s in scores)),
        "near_twins": int(sum(s.near_twin(part.diameter) for s in scores)),
        "mask_iou": _stats(s.mask_iou for s in scores)["mean"],
        "frames": [s.to_json() for s in scores],
    }


def estimate_and_score(frame: Frame, ctx: StepContext, params: Params, mask_source: str = "gt",
                       orientation_prior: bool = False, trace_iterations: bool = False,
                       mask: np.ndarray | None = None,
                       box: tuple[int, int, int, int] | None = None) -> tuple[RegistrationResult, FrameScore | None]:
    """Estimate one frame and score it against its ground truth (None for a capture without one).
    The mask comes from `mask_source` unless given (`box`: the prompt's box that gave it); a mask that is
    not the ground truth is scored too."""
    region = region_truth_prompt(frame, ctx, mask_source) if mask is None or ctx.base.region is not None else None
    if region is not None:  # a region's truth: the box round what is seen of it (its part's truth mask is the whole part)
        mask, box = region
    elif mask is None:
        mask = frame_mask(frame, mask_source)
    result = estimate_frame(frame, ctx, params, orientation_prior=orientation_prior,
                            trace_iterations=trace_iterations, mask=mask, box=box)
    if frame.T_world_part is None:
        return result, None
    scored = None if mask_source == "gt" or ctx.base.region is not None else mask  # a region's mask against its part's
    return result, score_frame(frame, result, ctx.part, scored, ctx.base.symmetries)


_WORKER: dict = {}


def _score_frame_of(ds: Dataset, step: int, im_id: int, ctx: "StepContext", params: Params, mask_source: str,
                    orientation_prior: bool) -> FrameScore:
    """One frame's score; a frame whose files are missing or broken counts as a failed frame (with the
    reason) instead of ending the whole evaluation."""
    try:
        frame = ds.frame(step, im_id)
    except DatasetError as e:
        return FrameScore(scene_id=step, im_id=im_id, ok=False, reason=f"unreadable frame: {e}")
    return estimate_and_score(frame, ctx, params, mask_source, orientation_prior)[1]


def _worker_init(root: str) -> None:
    ds = Dataset(root)
    _WORKER.update(ds=ds, models=load_parts(ds.assembly), ctx={})


def _worker_run(task) -> FrameScore:
    step, im_id, params, mask_source, orientation_prior = task
    ds, ctxs = _WORKER["ds"], _WORKER["ctx"]
    if step not in ctxs:
        ctxs[step] = StepContext(ds.assembly, _WORKER["models"], step)
    return _score_frame_of(ds, step, im_id, ctxs[step], params, mask_source, orientation_prior)


def _score_group_of(ds: Dataset, step: int, ids: list[int], ctx: "StepContext", params: Params, mask_source: str,
                    orientation_prior: bool) -> FrameScore:
    """One fused estimate over frames of one placement (registration.fusion), scored against the first
    frame's ground truth (the placement's); its record lists the frames in `im_ids`."""
    try:
        frames = [ds.frame(step, i) for i in ids]
    except DatasetError as e:
        return FrameScore(scene_id=step, im_id=ids[0], ok=False, reason=f"unreadable frame: {e}", im_ids=list(ids))
    views = [View.of(f, frame_mask(f, mask_source)) for f in frames]
    r = estimate_frames(views, ctx, params, orientation_prior)
    s = score_frame(frames[0], r, ctx.part, None if mask_source == "gt" else views[0].mask, ctx.base.symmetries)
    s.time_s = float(r.timings.get("total fused", r.seconds))
    s.im_ids = list(ids)
    return s


def placement_groups(ds: Dataset, step: int, ids: list[int], views: int) -> list[list[int]]:
    """The frames `ids` grouped by placement, in groups of at most `views` (a placement with more
    frames gives several groups); frames of a dataset without placements are each their own."""
    wanted = set(ids)
    out = []
    for members in ds.placements(step).values():
        members = [i for i in members if i in wanted]
        out += [members[k:k + views] for k in range(0, len(members), views)]
    return sorted(out)


def evaluate(ds: Dataset, params: Params, steps: list[int] | None = None, frames: int | None = None,
             mask_source: str = "gt", orientation_prior: bool = False, progress: bool = True,
             models: dict[str, PartModel] | None = None, workers: int = 1, views: int = 1) -> dict:
    """The evaluation document (docs/ESTIMATOR.md describes it): per step, means and stds, times, recall, per-frame records.
    `views` > 1: one fused estimate per group of frames of one placement (at most `views` each), one
    record per group (in one process)."""
    models = models or load_parts(ds.assembly)
    mask_source = check_mask_source(mask_source, ds.assembly)
    steps = steps or ds.steps
    for s in steps:
        if s not in ds.steps:
            raise DatasetError(f"{ds.root}: step {s} was not rendered; rendered steps: {', '.join(map(str, ds.steps))}")
    todo = [(s, ds.image_ids(s)[:frames] if frames else ds.image_ids(s)) for s in steps]
    bar = tqdm(total=sum(len(ids) for _, ids in todo), unit="frame", desc=f"eval {params.preset}",
               disable=not progress, leave=False)
    doc = {"preset": params.preset, "dataset": str(ds.root), "mask": mask_source,
           "orientation_prior": orientation_prior, "steps": [], "missing_steps": ds.missing_steps}
    t0 = time.perf_counter()
    if views > 1:
        doc["views"] = views
        try:
            for step, ids in todo:
                ctx = StepContext(ds.assembly, models, step)
                scores = []
                for group in placement_groups(ds, step, ids, views):
                    scores.append(_score_group_of(ds, step, group, ctx, params, mask_source, orientation_prior))
                    bar.update(len(group))
                doc["steps"].append(summarise_step(step, scores, ctx.part))
        finally:
            bar.close()
        doc["wall_s"] = time.perf_counter() - t0
        return doc
    if workers > 1:  # separate processes (Open3D holds the GIL); each loads the dataset once

        tasks = [(step, im_id, params, mask_source, orientation_prior) for step, ids in todo for im_id in ids]
        by_step: dict[int, list[FrameScore]] = {step: [] for step, _ in todo}
        with mp.get_context("spawn").Pool(workers, _worker_init, (str(ds.root),)) as pool:
            try:
                for sc in pool.imap(_worker_run, tasks):
                    by_step[sc.scene_id].append(sc)
                    bar.update(1)
            finally:
                bar.close()
        for step, _ in todo:
            view = ds.assembly.step_view(step)
            doc["steps"].append(summarise_step(step, by_step[step], models[view.part]))
        doc["wall_s"] = time.perf_counter() - t0
        return doc
    try:
        for step, ids in todo:
            ctx = StepContext(ds.assembly, models, step)
            scores = []
            for im_id in ids:
                scores.append(_score_frame_of(ds, step, im_id, ctx, params, mask_source, orientation_prior))
                bar.update(1)
            doc["steps"].append(summarise_step(step, scores, ctx.part))
    finally:
        bar.close()
    doc["wall_s"] = time.perf_counter() - t0
    return doc


def format_table(doc: dict) -> str:
    """The paper's table: per step mean/std of fitness, l_rmse, ADI, MSSD (mm); time; recall."""
    def mm(st, k):
        v = st[k]["mean"]
        return f"{v * 1000:8.3f}" if v is not None else "       -"

    def mm_std(st, k):
        v = st[k]["std"]
        return f"{v * 1000:7.3f}" if v is not None else "      -"
    lines = [f"preset {doc['preset']}, masks {doc['mask']}" + (", orientation prior" if doc.get("orientation_prior") else ""),
             f"{'step':>4} {'part':<12} {'n':>4} {'fail':>4} {'fitness':>8} {'l_rmse mm':>9} {'ADI mm':>8} {'± std':>7} "
             f"{'MSSD mm':>8} {'± std':>7} {'t mean s':>8} {'t med s':>7} {'recall':>6} {'rec~sym':>7} {'AR':>5}"]
    for st in doc["steps"]:
        fit = st["fitness"]["mean"]
        lines.append(f"{st['step']:>4} {st['part'][:12]:<12} {st['n_frames']:>4} {st['failed']:>4} "
                     f"{f'{fit:.4f}' if fit is not None else '-':>8} {mm(st, 'inlier_rmse'):>9} {mm(st, 'adi')} "
                     f"{mm_std(st, 'adi')} {mm(st, 'mssd')} {mm_std(st, 'mssd')} {st['time_s']['mean']:>8.3f} "
                     f"{st['time_s']['median']:>7.3f} {st['recall_mssd']:>6.2f} {st['recall_mssd_mod_base_sym']:>7.2f} "
                     f"{st['ar_mssd']:>5.2f}" + (f"  mask IoU {st['mask_iou']:.3f}" if st.get("mask_iou") is not None else "")
                     + (f"  near-symmetric twins {st['near_twins']}" if st.get("near_twins") else ""))
    lines.append("recall: share of frames with MSSD < 0.1 x part diameter (failures count as misses); "
                 "rec~sym: the same modulo the base object's exact symmetries (twins that are the same assembly: "
                 "no surface point moves more than 1 mm); near-symmetric twins: wrong placements that tied with the right one; "
                 "AR: BOP average over 0.05..0.5")
    return "\n".join(lines)


# ---- BOP results files and splits ---------------------------------------------------------------------

UNMEASURED_TIME = -1.0  # BOP19's time of an image whose time was not measured
MAX_RESULT_SECONDS = 1e6  # one image's time in a results file (11 days): beyond it, a unit or column mistake


def check_results(rows: list[BopResult]) -> None:
    """Every row of a BOP19 results file is a pose and a time that can be scored, else a DatasetError
    naming the row (counted after the header: row 1 is line 2 of a file without blank lines), its ids,
    the value and the fix: a finite score; R a rotation (orthonormal, determinant +1: a reflection or a
    scaled matrix is refused, as the camera path refuses them, not scored as a miss); t in mm within
    10 km; time in seconds, 0 or more, or -1 for "not measured" (BOP's convention)."""
    for n, r in enumerate(rows, start=1):
        where = f"--score-results: row {n} after the header (scene_id {r.scene_id}, im_id {r.im_id}, obj_id {r.obj_id})"
        if not math.isfinite(r.score):
            raise DatasetError(f"{where}: score is {r.score:g}; write a finite number (the highest score per image is "
                               "the estimate that counts)")
        T = np.asarray(r.T_camera_obj, float)
        with np.errstate(all="ignore"):  # a t of 1e308 mm is refused below, not warned about
            t_mm = T[:3, 3] * 1000.0
        pose_entry(T[:3, :3].ravel().tolist(), t_mm.tolist(), where, "R", "t")
        time_s = float(r.time)
        if time_s != UNMEASURED_TIME and not (math.isfinite(time_s) and 0.0 <= time_s <= MAX_RESULT_SECONDS):
            raise DatasetError(f"{where}: time is {time_s:g}; write the seconds the method took for the image (0 to "
                               f"{MAX_RESULT_SECONDS:g}), or -1 when it was not measured (BOP's convention)")


def score_results(ds, rows: list[BopResult], steps: list[int] | None = None, models=None) -> dict:
    """Score any method's BOP19 results on one of our datasets with our metrics and tables: per step,
    the highest-scoring estimate of base[0] per image, composed with the step's T_base_part into the
    assembly pose; an image without an estimate counts as failed (time -1, "not measured", counts as 0 s).
    Exact symmetries of the base are forgiven in `mssd_mod_base_sym`, as for our own estimates. Every row
    is checked first (`check_results`): a row that cannot be scored is refused, never scored as a miss."""
    check_results(rows)
    models = models or load_parts(ds.assembly)
    doc = {"preset": "results file", "dataset": str(ds.root), "mask": "-", "orientation_prior": False, "steps": [],
           "missing_steps": ds.missing_steps}
    wanted = {(step, im_id, step_truth(ds, step)[2]) for step in steps or ds.steps for im_id in ds.image_ids(step)}
    if rows and not any((r.scene_id, r.im_id, r.obj_id) in wanted for r in rows):
        r = rows[0]
        raise DatasetError(f"--score-results: none of its {len(rows)} rows names an image of this dataset (its first: "
                           f"scene_id {r.scene_id}, im_id {r.im_id}, obj_id {r.obj_id}; the dataset's scene_id is the step, "
                           f"obj_id the step's base: {sorted({(s, o) for s, _, o in wanted})[:6]}); check the ids")
    for step in steps or ds.steps:
        frames, T_base_part, obj_id = step_truth(ds, step)
        best = best_per_image(rows, obj_id)
        part = models[ds.assembly.step_view(step).part]
        symmetries = StepContext(ds.assembly, models, step).base.symmetries
        scores = []
        for im_id in ds.image_ids(step):
            fr = frames[str(im_id)]
            G = np.asarray(fr["T_world_part"], float)
            r = best.get((step, im_id))
            if r is None:
                scores.append(FrameScore(step, im_id, False, "no estimate in the results file", T_world_part_gt=G))
                continue
            T = np.asarray(fr["T_world_camera"], float) @ r.T_camera_obj @ T_base_part
            s = FrameScore(step, im_id, True, T_world_part_gt=G, time_s=max(r.time, 0.0))
            s.set_errors(T, part, truth_twins(G, T_base_part, symmetries))
            s.confident = r.score >= 1.0
            scores.append(s)
        doc["steps"].append(summarise_step(step, scores, part))
    return doc


def evaluate_split(split: Path, asm, step: int, obj_of_part: dict[str, int], params, mask_source: str = "gt",
                   frames: int | None = None, progress: bool = False) -> tuple[dict, list[BopResult]]:
    """`apose eval` on a BOP split folder (real captures with downloaded ground truth): every image of
    every scene whose scene_gt.json shows the step's base[0] (its obj_id from obj_of_part) is one frame;
    the truth is T_world_base = that object's pose, composed with the step's T_base_part. Returns the
    evaluation document (one step) and the BOP19 rows of the estimates."""
    _, ctx = step_context(asm, step)
    view = ctx.view
    missing = [p for p in view.base if p not in obj_of_part]
    if view.base[0] in missing:
        raise AposeError(f"step {step} places {view.part} on {', '.join(view.base)}: map {view.base[0]} to its BOP object "
                         f"id with --obj-map {view.base[0]}=ID")
    scenes = scene_folders(split)
    if not scenes:
        raise DatasetError(f"{split}: no BOP scene folders here (numbered folders with scene_camera.json and depth/)")
    todo = []
    for folder in scenes:
        sc = BopScene(folder, obj_of_part)
        ids = [i for i in sc.image_ids() if any(int(g["obj_id"]) == obj_of_part[view.base[0]] for g in sc.gt.get(str(i), []))]
        todo += [(sc, i) for i in (ids[:frames] if frames else ids)]
    if not todo:
        raise DatasetError(f"{split}: no image shows obj_id {obj_of_part[view.base[0]]} ({view.base[0]}) in scene_gt.json")
    ctx.base.warm_up(params)
    scores, rows = [], []
    obj_id = obj_of_part[view.base[0]]
    for sc, im_id in tqdm(todo, unit="frame", desc=f"eval {params.preset}", disable=not progress, leave=False):
        try:
            frame = sc.frame(im_id, view)
        except DatasetError as e:
            scores.append(FrameScore(sc.scene_id, im_id, False, f"unreadable frame: {e}"))
            continue
        if mask_source == "gt" and not frame.base_mask().any():
            scores.append(FrameScore(sc.scene_id, im_id, False, "no mask_visib for the base in this image",
                                     T_world_part_gt=frame.T_world_part))
            continue
        mask = frame_mask(frame, mask_source)
        r, s = estimate_and_score(frame, ctx, params, mask_source, mask=mask)
        s.scene_id = sc.scene_id
        scores.append(s)
        if r.ok:
            T = se3.inv(frame.T_world_camera) @ r.T_world_base
            rows.append(BopResult(sc.scene_id, im_id, obj_id, 1.0 if r.confident else 0.5, T, r.seconds))
    doc = {"preset": params.preset, "dataset": str(split), "mask": mask_source, "orientation_prior": False,
           "steps": [summarise_step(step, scores, ctx.part)], "missing_steps": []}
    return doc, rows
