"""SEG(): masks of the base object, learned from the user's own renders (torch), or from depth alone.

- A compact U-Net on RGB-D, classes = background + each part of the assembly, trained from scratch on
  `apose render` output (`train`), with colour, light, blur and depth-noise augmentation so it does not
  learn the renderer's exact look. "The base object of step k" is the union of its parts' classes.
- `depth_mask`: no training: remove the table plane, split what stands on it at depth edges, keep the
  blob nearest the image centre (or inside a given 2D box).

torch is imported inside the functions that use it, so the rest of apose_studio never loads it.
"""

from __future__ import annotations

import io
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from apose_studio import safeio
from apose_studio.errors import AposeError
from apose_studio.geometry.plane import fit_table

FORMAT = "apose-seg/1"
INPUT_SIZE = (160, 120)  # network input (width, height); outlines come back at full size from depth (refine_with_depth)


def _torch():
    """torch, with its thread count set to the machine's cores (apose_studio sets OMP_NUM_THREADS=1 for
    Open3D's sake, which torch would otherwise take as its own limit)."""
    import torch  # heavy (~1.1 s): loaded only where a model is trained or used

    if torch.get_num_threads() < (os.cpu_count() or 1):
        torch.set_num_threads(os.cpu_count() or 1)
    return torch


class SegmentationError(AposeError):
    """A model file that cannot be used here (wrong assembly, corrupt, other format)."""


# --------------------------------------------------------------------------------------------- network


def build_net(n_classes: int, width: int = 16):
    """A 4-level U-Net: 4 input channels (RGB + normalised depth), `n_classes` logits per pixel."""
    torch = _torch()
    from torch import nn  # heavy (~1.1 s): loaded only where a model is trained or used

    def block(a, b):
        return nn.Sequential(nn.Conv2d(a, b, 3, padding=1, bias=False), nn.BatchNorm2d(b), nn.ReLU(inplace=True),
                             nn.Conv2d(b, b, 3, padding=1, bias=False), nn.BatchNorm2d(b), nn.ReLU(inplace=True))

    class UNet(nn.Module):
        def __init__(self):
            super().__init__()
            c = [width, 2 * width, 4 * width, 8 * width]
            self.enc = nn.ModuleList([block(4, c[0]), block(c[0], c[1]), block(c[1], c[2]), block(c[2], c[3])])
            self.up = nn.ModuleList([nn.ConvTranspose2d(c[i + 1], c[i], 2, stride=2) for i in range(3)])
            self.dec = nn.ModuleList([block(2 * c[i], c[i]) for i in range(3)])
            self.head = nn.Conv2d(c[0], n_classes, 1)

        def forward(self, x):
            skips = []
            for i, e in enumerate(self.enc):
                x = e(x if i == 0 else nn.functional.max_pool2d(x, 2))
                skips.append(x)
            for i in (2, 1, 0):
                x = self.dec[i](torch.cat([self.up[i](x), skips[i]], dim=1))
            return self.head(x)

    return UNet()


def network_input(rgb: np.ndarray, depth: np.ndarray, size=INPUT_SIZE) -> np.ndarray:
    """(4, h, w) float32: RGB in [-0.5, 0.5] and depth relative to the frame's median (0 where missing)."""
    w, h = size
    rgb_s = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0 - 0.5
    d = np.nan_to_num(depth.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    d_s = cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST)
    valid = d_s > 0
    med = float(np.median(d_s[valid])) if valid.any() else 1.0
    dn = np.where(valid, (d_s - med) / (0.25 * med), 0.0).astype(np.float32)
    return np.concatenate([rgb_s.transpose(2, 0, 1), dn[None]], axis=0)


def label_map(frame, part_ids: list[str], size=INPUT_SIZE) -> np.ndarray:
    """(h, w) int64 class of each pixel at network size: 0 background, i + 1 for part_ids[i]."""
    labels = np.zeros(frame.depth.shape, np.int64)
    for pid, m in frame.masks.items():
        if pid in part_ids:
            labels[m] = part_ids.index(pid) + 1
    return cv2.resize(labels.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(np.int64)


def _augment(x, rng: np.random.Generator):
    """In place on a (B, 4, h, w) tensor: colour gains, brightness, contrast, blur, noise, depth noise
    and dropout, flips. Geometry-free except the flip, so labels only follow the flip."""
    torch = _torch()

    b = x.shape[0]
    g = torch.from_numpy(rng.uniform(0.75, 1.25, (b, 3, 1, 1)).astype(np.float32))
    off = torch.from_numpy(rng.uniform(-0.15, 0.15, (b, 1, 1, 1)).astype(np.float32))
    con = torch.from_numpy(rng.uniform(0.7, 1.3, (b, 1, 1, 1)).astype(np.float32))
    rgb = x[:, :3]
    mean = rgb.mean(dim=(1, 2, 3), keepdim=True)
    rgb = (rgb - mean) * con + mean
    rgb = (rgb + 0.5) * g - 0.5 + off
    if rng.random() < 0.5:
        k = torch.tensor([1.0, 2.0, 1.0]) / 4.0
        k2 = (k[:, None] * k[None, :]).expand(3, 1, 3, 3).contiguous()
        rgb = torch.nn.functional.conv2d(rgb, k2, padding=1, groups=3)
    rgb = rgb + torch.randn_like(rgb) * float(rng.uniform(0.0, 0.04))
    d = x[:, 3:]
    d = d + torch.randn_like(d) * float(rng.uniform(0.0, 0.03)) * (d != 0)
    drop = torch.from_numpy((rng.random(d.shape) < rng.uniform(0.0, 0.05)).astype(np.float32))
    d = d * (1 - drop)
    x[:, :3], x[:, 3:] = rgb.clamp(-0.5, 0.5), d
    return x


# --------------------------------------------------------------------------------------------- model file


@dataclass
class Segmenter:
    """A trained network and what it was trained for."""

    net: object
    part_ids: list[str]
    assembly: str
    size: tuple[int, int]
    device: str = "cpu"
    info: dict | None = None

    def predict(self, rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(H, W) uint8 class map at the frame's resolution (logits upsampled bilinearly)."""
        torch = _torch()

        x = torch.from_numpy(network_input(rgb, depth, self.size))[None].to(self.device)
        with torch.no_grad():
            logits = self.net(x)
            logits = torch.nn.functional.interpolate(logits, size=depth.shape, mode="bilinear", align_corners=False)
        return logits[0].argmax(0).to("cpu").numpy().astype(np.uint8)

    def mask(self, rgb: np.ndarray, depth: np.ndarray, parts, cam=None) -> np.ndarray:
        """Union of the predicted masks of `parts` (the base object of a step); with the camera
        intrinsics, outlines sharpened by depth (`refine_with_depth`)."""
        labels = self.predict(rgb, depth)
        classes = [self.part_ids.index(p) + 1 for p in parts if p in self.part_ids]
        pred = np.isin(labels, classes)
        return refine_with_depth(pred, depth, cam) if cam is not None else pred


def save_model(seg: Segmenter, path: str | Path) -> Path:
    torch = _torch()

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save({"format": FORMAT, "assembly": seg.assembly, "part_ids": seg.part_ids, "size": list(seg.size),
                "width": seg.info.get("width", 16) if seg.info else 16, "info": seg.info or {},
                "state_dict": {k: v.cpu() for k, v in seg.net.state_dict().items()}}, tmp)
    tmp.replace(path)
    return path


MAX_MODEL_BYTES = 512 * 2 ** 20  # our U-Nets are a few MB


def load_model(path: str | Path, asm=None, device: str = "cpu") -> Segmenter:
    """Load a model; with `asm`, refuse one trained for other parts (names the difference and the fix)."""
    torch = _torch()

    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise SegmentationError(f"{path}: no such model file (train one with `apose train-seg DATASET --out {path.name}`)")
    try:
        data = safeio.read_bytes(path, "a segmentation model", MAX_MODEL_BYTES)
    except AposeError as e:
        raise SegmentationError(str(e)) from None
    try:
        blob = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as e:
        raise SegmentationError(f"{path}: not a readable model file ({type(e).__name__}); retrain with `apose train-seg`") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise SegmentationError(f"{path}: not an apose segmentation model (format {FORMAT})")
    if asm is not None and list(asm.parts) != list(blob["part_ids"]):
        raise SegmentationError(
            f"{path}: trained for assembly {blob['assembly']!r} with parts {', '.join(blob['part_ids'])}; "
            f"{asm.name!r} has parts {', '.join(asm.parts)}. Train a model for it: apose train-seg DATASET --out MODEL.pt")
    net = build_net(len(blob["part_ids"]) + 1, int(blob.get("width", 16)))
    try:
        net.load_state_dict(blob["state_dict"])
    except (RuntimeError, KeyError, TypeError) as e:
        raise AposeError(f"{path}: the weights do not fit the network (damaged or edited file?): "
                         f"{str(e).splitlines()[0][:200]}; train it again with `apose train-seg`") from None
    net.eval().to(device)
    return Segmenter(net, list(blob["part_ids"]), blob["assembly"], tuple(blob["size"]), device, blob.get("info"))


# --------------------------------------------------------------------------------------------- training


def resolve_device(device: str) -> str:
    torch = _torch()

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise AposeError("--device cuda: no CUDA GPU is visible to torch here; use --device cpu")
    if device not in ("cpu", "cuda"):
        raise AposeError(f"--device {device}: expected cpu, cuda or auto")
    return device


def split_frames(ds, val_share: float = 0.15, seed: int = 0) -> tuple[list, list]:
    """(step, im_id) pairs for training and held-out validation, the split fixed by the seed."""
    pairs = [(s, i) for s in ds.steps for i in ds.image_ids(s)]
    if len(pairs) < 2:
        raise AposeError(f"{ds.root}: {len(pairs)} frame(s); render more (apose render --frames 50) to train")
    order = np.random.default_rng(seed).permutation(len(pairs))
    n_val = max(1, int(round(val_share * len(pairs))))
    return [pairs[k] for k in order[n_val:]], [pairs[k] for k in order[:n_val]]


def iou(pred: np.ndarray, gt: np.ndarray) -> float:
    """Intersection over union of two boolean masks; 1.0 when both are empty."""
    union = np.logical_or(pred, gt).sum()
    return 1.0 if union == 0 else float(np.logical_and(pred, gt).sum() / union)


def evaluate_masks(seg: Segmenter, ds, pairs) -> dict:
    """Mean IoU at full resolution: per part from the network alone (frames where the part is visible),
    and per step of the base object as the estimator gets it (network, then `refine_with_depth`) and
    from the network alone (`raw`)."""
    per_part: dict[str, list] = {p: [] for p in seg.part_ids}
    base: dict[int, list] = {}
    raw: dict[int, list] = {}
    for step, im_id in pairs:
        fr = ds.frame(step, im_id)
        labels = seg.predict(fr.rgb, fr.depth)
        for pid, m in fr.masks.items():
            if pid in per_part and m.any():
                per_part[pid].append(iou(labels == seg.part_ids.index(pid) + 1, m))
        gt = fr.base_mask()
        if gt.any():
            pred = np.isin(labels, [seg.part_ids.index(p) + 1 for p in fr.base])
            raw.setdefault(step, []).append(iou(pred, gt))
            base.setdefault(step, []).append(iou(refine_with_depth(pred, fr.depth, fr.camera), gt))

    def mean_all(d):
        return float(np.mean([x for v in d.values() for x in v])) if d else float("nan")

    return {"part_iou": {p: float(np.mean(v)) for p, v in per_part.items() if v},
            "base_iou": {int(s): float(np.mean(v)) for s, v in base.items()},
            "base_iou_raw": {int(s): float(np.mean(v)) for s, v in raw.items()},
            "mean_base_iou": mean_all(base), "mean_base_iou_raw": mean_all(raw), "frames": len(pairs)}


def train(ds, epochs: int = 60, device: str = "auto", batch: int = 8, lr: float = 3e-3, seed: int = 0,
          width: int = 16, size=INPUT_SIZE, max_minutes: float | None = None, progress: bool = True,
          log=print) -> tuple[Segmenter, dict]:
    """Train from scratch on a rendered dataset; returns the model and a report (losses, held-out IoU)."""
    torch = _torch()

    device = resolve_device(device)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    asm = ds.assembly
    part_ids = list(asm.parts)
    train_pairs, val_pairs = split_frames(ds, seed=seed)
    t0 = time.perf_counter()
    xs, ys = [], []
    for step, im_id in tqdm(train_pairs, desc="reading frames", disable=not progress, unit="frame"):
        fr = ds.frame(step, im_id)
        xs.append(network_input(fr.rgb, fr.depth, size))
        ys.append(label_map(fr, part_ids, size))
    X, Y = torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys))
    counts = np.bincount(Y.numpy().ravel(), minlength=len(part_ids) + 1).astype(float)
    weights = torch.tensor(np.clip((counts.sum() / np.maximum(counts, 1)) ** 0.5, 1.0, 30.0), dtype=torch.float32)
    net = build_net(len(part_ids) + 1, width).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    steps_per_epoch = math.ceil(len(X) / batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=epochs * steps_per_epoch)
    ce = torch.nn.CrossEntropyLoss(weight=weights.to(device))
    losses = []
    bar = tqdm(range(epochs), desc="training", disable=not progress, unit="epoch")
    stopped_early = False
    for epoch in bar:
        net.train()
        order = rng.permutation(len(X))
        total = 0.0
        for k in range(steps_per_epoch):
            idx = order[k * batch:(k + 1) * batch]
            xb, yb = _augment(X[idx].clone(), rng), Y[idx].clone()
            if rng.random() < 0.5:
                xb, yb = xb.flip(-1), yb.flip(-1)
            xb, yb = xb.to(device), yb.to(device)
            loss = ce(net(xb), yb)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(idx)
        losses.append(total / len(X))
        bar.set_postfix(loss=f"{losses[-1]:.3f}")
        if max_minutes is not None and time.perf_counter() - t0 > 60 * max_minutes:
            stopped_early = True
            log(f"stopping after epoch {epoch + 1}: the {max_minutes:g}-minute budget is spent")
            break
    net.eval()
    seg = Segmenter(net, part_ids, asm.name, tuple(size), device)
    report = evaluate_masks(seg, ds, val_pairs)
    report.update({"losses": losses, "epochs": len(losses), "train_frames": len(train_pairs),
                   "seconds": time.perf_counter() - t0, "device": device, "stopped_early": stopped_early,
                   "width": width, "dataset": str(ds.root)})
    seg.info = {k: v for k, v in report.items() if k != "losses"} | {"final_loss": losses[-1]}
    return seg, report


# --------------------------------------------------------------------------------------------- depth only


@dataclass
class TableObjects:
    """What stands on the table in a depth image: one group id per above-table pixel (-1 = noise)."""

    u: np.ndarray  # (N,) pixel columns of the above-table points
    v: np.ndarray  # (N,) pixel rows
    group: np.ndarray  # (N,) DBSCAN group of each point
    shape: tuple[int, int]
    height: np.ndarray | None = None  # (H, W) metres above the table plane (NaN where no depth)
    median_depth: float = 0.0

    def groups(self, min_points: int = 150) -> list[np.ndarray]:
        """Boolean selectors (over the points) of the groups with at least min_points points."""
        out = []
        for k in range(int(self.group.max()) + 1 if len(self.group) else 0):
            sel = self.group == k
            if sel.sum() >= min_points:
                out.append(sel)
        return out

    def mask(self, sel: np.ndarray) -> np.ndarray:
        m = np.zeros(self.shape, bool)
        m[self.v[sel], self.u[sel]] = True
        return m


def table_objects(depth: np.ndarray, cam, plane_tol: float | None = None, gap: float | None = None,
                  keep: np.ndarray | None = None) -> TableObjects | None:
    """Fit the table plane (seeded RANSAC), keep what rises above it by more than `plane_tol`, group those
    points in 3D (DBSCAN: points closer than `gap` join). Tolerances default to fractions of the
    median depth (0.6 % and 2 %: 3 mm and 1 cm at 0.5 m). `keep` (H, W) bool limits the points to
    those pixels. None when the image has too little depth or nothing stands on the plane."""
    import open3d as o3d  # heavy (~0.9 s to import): loaded where it is used

    rng = np.random.default_rng(0)
    table = fit_table(depth, cam, plane_tol, rng)
    if table is None or table.plane is None:
        return None
    vs, us, pts, med, plane_tol = table.vs, table.us, table.pts, table.median_depth, table.tol
    gap = 0.02 * med if gap is None else gap
    heights = table.heights()
    above = heights > plane_tol
    if keep is not None:
        above &= keep[vs, us]
    if above.sum() < 30:
        return None
    obj = pts[above]
    pick = rng.choice(len(obj), min(len(obj), 15000), replace=False)
    groups = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(obj[pick])).cluster_dbscan(gap, 8))
    _, nearest = cKDTree(obj[pick]).query(obj)
    height = np.full(depth.shape, np.nan)
    height[vs, us] = heights
    return TableObjects(us[above], vs[above], groups[nearest], depth.shape, height, med)


def depth_mask(depth: np.ndarray, cam, box: tuple[int, int, int, int] | None = None, min_points: int = 150,
               keep: np.ndarray | None = None, **tolerances) -> np.ndarray:
    """The object standing on the table nearest the image centre (or most inside `box` = x0, y0, x1, y1),
    from depth alone (see `table_objects`). `keep` (H, W) bool limits the object to those pixels (e.g. a
    3D crop box drawn in the studio). An empty mask when nothing stands on a plane."""
    h, w = depth.shape
    objs = table_objects(depth, cam, keep=keep, **tolerances)
    if objs is None:
        return np.zeros((h, w), bool)
    best, best_score = None, 0.0
    for sel in objs.groups(min_points):
        count = int(sel.sum())
        u, v = objs.u[sel], objs.v[sel]
        if box is not None:
            x0, y0, x1, y1 = box
            inside = int(((u >= x0) & (u < x1) & (v >= y0) & (v < y1)).sum())
            score = inside - 0.5 * (count - inside)
        else:
            dist2 = ((u.mean() - w / 2) ** 2 + (v.mean() - h / 2) ** 2) / ((w ** 2 + h ** 2) / 16)
            score = count / (1.0 + 4.0 * dist2)
        if score > best_score:
            best, best_score = sel, score
    return objs.mask(best) if best is not None else np.zeros((h, w), bool)


def refine_with_depth(pred: np.ndarray, depth: np.ndarray, cam, min_points: int = 150,
                      table_share: float = 0.003) -> np.ndarray:
    """Sharpen a predicted object mask with depth: every 3D group standing on the table that the
    prediction mostly covers joins whole (depth gives its exact outline); predicted pixels on the
    table plane, or in a group the prediction mostly does not cover, leave; predicted pixels without
    depth (sensor holes) stay."""
    objs = table_objects(depth, cam)
    if objs is None:
        return pred
    # "on the table" is judged at half the grouping tolerance: the object's last few millimetres above
    # the table are too close to it to group reliably, but the prediction may keep them
    on_table = objs.height < table_share * objs.median_depth
    out = pred & ~on_table
    for sel in objs.groups(min_points):
        share = pred[objs.v[sel], objs.u[sel]].mean()
        if share >= 0.5:
            out[objs.v[sel], objs.u[sel]] = True
        else:
            out[objs.v[sel], objs.u[sel]] = False
    return out
