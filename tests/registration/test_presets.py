"""Parameters: presets, the file's registration section, the caller."""

from dataclasses import replace

import pytest

from apose_studio.errors import AposeError
from apose_studio.params import RegistrationConfig
from apose_studio.registration import resolve_params


def test_params_from_file_and_caller():
    p = resolve_params("default", RegistrationConfig(voxel_size_m=0.002, seed=7))
    assert p.voxel_size_m == 0.002 and p.seed == 7 and p.preset == "default"
    assert p.voxel(1.0) == 0.002
    assert resolve_params("default").voxel(0.05) == pytest.approx(0.001)  # diameter / 50
    paper = resolve_params("paper")
    assert (paper.voxel(1.0), paper.ransac_max_iterations, paper.ransac_confidence) == (0.008, 100000, 0.899)
    assert resolve_params("default", RegistrationConfig(preset="paper")).preset == "paper"
    assert replace(paper, seed=3).seed == 3
    with pytest.raises(AposeError, match="unknown preset 'fast'"):
        resolve_params("fast")

