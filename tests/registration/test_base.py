"""The prepared base object's near-surface grid."""

import numpy as np
import trimesh


def test_near_grid_answers_like_the_distance_to_the_cloud():
    """The screening's grid says 'near' for points well within the radius and 'far' for points well
    beyond it (it is exact up to a cell's half diagonal, 0.22 x radius); off the grid is far."""
    from scipy.spatial import cKDTree

    from apose_studio.registration import NearGrid

    rng = np.random.default_rng(3)
    cloud = trimesh.sample.sample_surface_even(trimesh.creation.box((0.04, 0.02, 0.01)), 3000, seed=1)[0]
    r = 0.002
    grid = NearGrid.around(cloud, r)
    q = cloud[rng.choice(len(cloud), 4000)] + rng.normal(scale=r, size=(4000, 3))
    q = np.concatenate([q, [[1.0, 1.0, 1.0], [-1.0, 0.0, 0.0]]])
    d = cKDTree(cloud).query(q)[0]
    got = grid.contains(q)
    assert got[d < 0.75 * r].all() and not got[d > 1.25 * r].any()
    assert (d < 0.75 * r).sum() > 500 and (d > 1.25 * r).sum() > 500  # both kinds were asked


def test_near_grid_stays_small_for_a_fine_radius_on_a_big_part():
    from apose_studio.registration import NearGrid

    cloud = trimesh.sample.sample_surface_even(trimesh.creation.box((1.0, 0.8, 0.5)), 20000, seed=1)[0]
    grid = NearGrid.around(cloud, 0.002)  # radius/4 cells would be 400 x 320 x 200 = 26 M
    assert grid.occupied.size <= 1.1 * NearGrid.MAX_CELLS
    assert grid.contains(cloud[:100]).all() and not grid.contains(np.array([[0.0, 0.0, 0.0]])).any()

