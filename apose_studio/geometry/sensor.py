"""The depth sensor, modelled from the frame itself: how coarsely it quantises depth where the object
is (no calibration file: a Kinect v1 reads in disparity steps that grow with z squared, most sensors in
whole millimetres, a render in 0.1 mm). With the noise measured from the depth's second differences
(noise.estimate_depth_noise) it sets how far a model surface may lie from the depth and still agree.
Pure functions of numpy arrays; metres.
"""

from __future__ import annotations

import numpy as np


def quantisation_step(depth: np.ndarray, region: np.ndarray) -> float:
    """The sensor's depth step at the region's depth (metres): the median gap between neighbouring distinct
    depth values there (a Kinect v1 reads in disparity steps, about 3 mm apart at 1 m; most sensors in
    whole millimetres). 0 when too few distinct values are seen (a fine or float depth)."""
    d = depth[region & np.isfinite(depth) & (depth > 0)]
    if len(d) < 200:
        return 0.0
    lo, hi = np.percentile(d, [10, 90])
    values = np.unique(np.round(d[(d >= lo) & (d <= hi)], 6))
    if len(values) < 8:
        return float(np.median(np.diff(values))) if len(values) > 1 else 0.0
    counts = len(d) / len(values)
    return float(np.median(np.diff(values))) if counts >= 4 else 0.0  # sparse values: not steps but noise
