"""Depth sensor noise models for synthetic frames (metres in and out; 0 means no depth)."""

from __future__ import annotations

import cv2
import numpy as np

from apose_studio.geometry.sensor import nearest_within

NOISE_MODELS = ("none", "gaussian", "realsense", "kinect")
KINECT_FB = 580.0 * 0.075  # Kinect v1: IR focal length 580 px x baseline 75 mm: 1/8 px steps are 2.9 mm at 1 m

_NOISE: dict[tuple[int, int], np.ndarray] = {}


def noise_texture(h: int, w: int) -> np.ndarray:
    """A fixed (h + 64, w + 64) field of integer pixel noise (sigma 3 grey levels), cut at a random offset per frame."""
    if (h, w) not in _NOISE:
        _NOISE[(h, w)] = np.round(np.random.default_rng(12345).normal(0, 3.0, (h + 64, w + 64))).astype(np.int16)
    return _NOISE[(h, w)]


def depth_edges(z: np.ndarray, rel: float = 0.02, floor: float = 0.004) -> np.ndarray:
    """(H, W) bool: pixels beside a depth jump larger than max(floor, rel * z) to a 4-neighbour."""
    jump = np.zeros_like(z)
    jump[:, :-1] = np.abs(np.diff(z, axis=1))
    jump[:, 1:] = np.maximum(jump[:, 1:], jump[:, :-1])
    dv = np.abs(np.diff(z, axis=0))
    jump[:-1] = np.maximum(jump[:-1], dv)
    jump[1:] = np.maximum(jump[1:], dv)
    return jump > np.maximum(floor, rel * z)


def quantise_disparity(z: np.ndarray, fb: float, step: float) -> np.ndarray:
    """Depth rounded to the sensor's disparity steps (fb = focal length x baseline, pixel-metres)."""
    disparity = np.round(np.float32(fb) / np.maximum(z, 1e-6) / np.float32(step)) * np.float32(step)
    return np.float32(fb) / np.maximum(disparity, 1e-6)


def projector_shadow(z: np.ndarray, fb: float) -> np.ndarray:
    """(H, W) bool: pixels the structured-light projector (baseline to the camera's right) cannot light.

    A pixel u at depth z is lit along the projector's column u_p = u - fb / z. It is in shadow when a
    pixel to its right has a smaller u_p: a nearer surface stands on the projector's ray (the band of
    missing depth Kinect v1 leaves on the far side of every object's left edge)."""
    up = np.where(z > 0, np.arange(z.shape[1], dtype=np.float32)[None, :] - np.float32(fb) / np.maximum(z, 1e-6), np.inf)
    right_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]
    later = np.full_like(up, np.inf)
    later[:, :-1] = right_min[:, 1:]
    return (z > 0) & (up > later + 0.5)


def add_depth_noise(depth: np.ndarray, model: str, sigma_at_05m: float, rng: np.random.Generator,
                    fx: float = 615.0, rgb: np.ndarray | None = None) -> np.ndarray:
    """Depth noise, metres in and out; 0 stays 0.

    gaussian: axial N(0, sigma(z)), sigma(z) = sigma_at_05m * (z / 0.5)^2 (stereo error grows with z^2).
    realsense: that, plus dropouts at depth edges (stereo matching fails at occlusion borders), a few
    random holes, and quantisation in disparity (baseline 50 mm, 1/12-pixel subpixel steps).
    kinect (v1, LINEMOD's sensor): that Gaussian, coarser quantisation (baseline 75 mm, 1/8-pixel
    steps: ~3 mm at 1 m), the projector's shadow band beside every near edge, near surfaces bleeding a
    pixel into far ones (the 9x9 correlation window), edge dropouts, and no depth on dark or glossy
    (near-white) surfaces (the speckle is absorbed or mirrored away; needs `rgb`).
    """
    if model == "none":
        return depth
    z = depth
    valid = z > 0
    noisy = z + rng.standard_normal(z.shape, dtype=np.float32) * np.float32(sigma_at_05m / 0.25) * z * z
    if model == "realsense":
        edge = depth_edges(z)
        u = rng.random(z.shape, dtype=np.float32)
        drop = (edge & (u < 0.6)) | (u > 0.998)
        noisy = quantise_disparity(noisy, fx * 0.05, 1.0 / 12)  # baseline 50 mm, 1/12 px disparity steps
        valid &= ~drop
    elif model == "kinect":
        fb = fx * 0.075
        edge = depth_edges(z)
        near = nearest_within(np.where(valid, noisy, np.inf), 1)
        noisy = np.where(edge & np.isfinite(near), near, noisy)  # near surfaces bleed into far ones at edges
        u = rng.random(z.shape, dtype=np.float32)
        wide_edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        drop = projector_shadow(z, fb) | (wide_edge & (u < 0.5)) | (u > 0.997)
        if rgb is not None:
            lum = rgb.astype(np.float32) @ np.float32([0.299, 0.587, 0.114])
            drop |= ((lum < 30) | (lum > 245)) & (u < 0.85)
        noisy = quantise_disparity(noisy, KINECT_FB, 1.0 / 8)  # the sensor's own steps, whatever the image's fx
        valid &= ~drop
    return np.where(valid & (noisy > 0), noisy, 0.0).astype(np.float32)


BLEED_FLOOR, BLEED_REL = 0.004, 0.02  # a near surface bleeds over one farther than this (depth_edges' jump)


def bleed(depth: np.ndarray, px: int) -> np.ndarray:
    """Near surfaces widened by `px` pixels over farther ones: each pixel with depth within `px` pixels (the
    (2 px + 1)-wide square) of a surface nearer by more than depth_edges' jump reads that nearer depth; holes stay
    holes. What a correlation window does to an object's outline: a structured-light or stereo sensor matches a
    window of pixels, and where it straddles an edge the nearer surface's pattern wins, so foreground objects come
    out wider in depth than in colour. `kinect` bleeds one pixel already; this is more of it."""
    if px <= 0:
        return depth
    z = np.where(depth > 0, depth, np.inf).astype(np.float32)
    near = nearest_within(z, px)
    with np.errstate(invalid="ignore"):
        over = (depth > 0) & np.isfinite(near) & (near < z - np.maximum(BLEED_FLOOR, BLEED_REL * near))
    return np.where(over, near, depth).astype(np.float32)


def estimate_depth_noise(depth: np.ndarray, region: np.ndarray | None = None) -> float:
    """The frame's own axial depth noise (metres, one sigma), from second differences along rows and
    columns: on a smooth surface d[i-1] - 2 d[i] + d[i+1] is noise with sigma * sqrt(6). The median
    absolute value over `region` (default all) ignores edges and curvature. NaN when too few pixels."""
    if region is not None:  # only the region's box and a pixel around it: the same values, not the whole frame's work
        rows, cols = np.flatnonzero(region.any(axis=1)), np.flatnonzero(region.any(axis=0))
        if not len(rows):
            return float("nan")
        y0, y1 = max(rows[0] - 1, 0), rows[-1] + 2
        x0, x1 = max(cols[0] - 1, 0), cols[-1] + 2
        depth, region = depth[y0:y1, x0:x1], region[y0:y1, x0:x1]
    z = np.where(np.isfinite(depth), depth, 0.0)
    parts = []
    for a in (z, z.T):
        d2 = a[:, :-2] - 2 * a[:, 1:-1] + a[:, 2:]
        ok = (a[:, :-2] > 0) & (a[:, 1:-1] > 0) & (a[:, 2:] > 0)
        if region is not None:
            r = region if a is z else region.T
            ok &= r[:, 1:-1]
        parts.append(np.abs(d2[ok]))
    vals = np.concatenate(parts)
    if len(vals) < 200:
        return float("nan")
    return float(np.median(vals) * 1.4826 / np.sqrt(6.0))
