"""Depth sensor noise models for synthetic frames (metres in and out; 0 means no depth)."""

from __future__ import annotations

import numpy as np

NOISE_MODELS = ("none", "gaussian", "realsense")

_NOISE: dict[tuple[int, int], np.ndarray] = {}


def noise_texture(h: int, w: int) -> np.ndarray:
    """A fixed (h + 64, w + 64) field of integer pixel noise (sigma 3 grey levels), cut at a random offset per frame."""
    if (h, w) not in _NOISE:
        _NOISE[(h, w)] = np.round(np.random.default_rng(12345).normal(0, 3.0, (h + 64, w + 64))).astype(np.int16)
    return _NOISE[(h, w)]


def add_depth_noise(depth: np.ndarray, model: str, sigma_at_05m: float, rng: np.random.Generator,
                    fx: float = 615.0) -> np.ndarray:
    """Depth noise, metres in and out; 0 stays 0.

    gaussian: axial N(0, sigma(z)), sigma(z) = sigma_at_05m * (z / 0.5)^2 (stereo error grows with z^2).
    realsense: that, plus dropouts at depth edges (stereo matching fails at occlusion borders), a few
    random holes, and quantisation in disparity (baseline 50 mm, 1/12-pixel subpixel steps).
    """
    if model == "none":
        return depth
    z = depth
    valid = z > 0
    noisy = z + rng.standard_normal(z.shape, dtype=np.float32) * np.float32(sigma_at_05m / 0.25) * z * z
    if model == "realsense":
        jump = np.zeros_like(z)
        jump[:, :-1] = np.abs(np.diff(z, axis=1))
        jump[:, 1:] = np.maximum(jump[:, 1:], jump[:, :-1])
        dv = np.abs(np.diff(z, axis=0))
        jump[:-1] = np.maximum(jump[:-1], dv)
        jump[1:] = np.maximum(jump[1:], dv)
        edge = jump > np.maximum(0.004, 0.02 * z)
        u = rng.random(z.shape, dtype=np.float32)
        drop = (edge & (u < 0.6)) | (u > 0.998)
        fb, subpixel = np.float32(fx * 0.05), np.float32(1.0 / 12)  # baseline 50 mm, 1/12 px disparity steps
        disparity = np.round(fb / np.maximum(noisy, 1e-6) / subpixel) * subpixel
        noisy = fb / np.maximum(disparity, 1e-6)
        valid &= ~drop
    return np.where(valid & (noisy > 0), noisy, 0.0).astype(np.float32)
