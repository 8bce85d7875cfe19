"""What a folder of frames is: a rendered dataset, a real capture or a BOP scene, opened as such."""

from __future__ import annotations

import os
from pathlib import Path

from apose_studio.data.bop import BopScene, is_bop_scene
from apose_studio.data.dataset import CAPTURE_RGB, Dataset, DatasetError, load_capture


def open_frames(path: str | Path):
    """A Dataset for a rendered folder, a BopScene for a BOP scene folder, or a single Frame for a
    real-capture folder."""
    path = Path(path)
    if os.path.lexists(path / "dataset_info.json"):  # a FIFO or folder there too: Dataset says what it is
        return Dataset(path)
    if any(os.path.lexists(path / name) for name in CAPTURE_RGB):
        return load_capture(path)
    if is_bop_scene(path):
        return BopScene(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such folder")
    raise DatasetError(f"{path}: neither a dataset (dataset_info.json), a capture (rgb.png or rgb.jpg, depth.png, camera.json) "
                       "nor a BOP scene (scene_camera.json, rgb/, depth/)")
