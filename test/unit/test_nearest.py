"""nearest.NearestWithin answers as cKDTree.query(..., distance_upper_bound=gate) does."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rtabmap_ros2.core.nearest import NearestWithin


def _kdtree_answer(points, queries, gate):
    distances, index = cKDTree(points).query(queries, distance_upper_bound=gate)
    return np.where(np.isfinite(distances), index, -1)


@pytest.mark.parametrize("gate", [0.05, 0.3, 2.0])
def test_same_neighbours_as_cKDTree(gate):
    rng = np.random.default_rng(3)
    # A scan-like reference: points along walls, and queries near them, far from them and outside
    # the reference's bounding box.
    t = rng.uniform(0.0, 10.0, 800)
    walls = np.column_stack([t, np.where(t > 5.0, 4.0, 0.0)]) + rng.normal(0.0, 0.01, (800, 2))
    queries = np.concatenate([walls[::3] + rng.normal(0.0, gate, (267, 2)),
                              rng.uniform(-3.0, 13.0, (500, 2))])
    found = NearestWithin(walls, gate).query(queries)
    np.testing.assert_array_equal(found, _kdtree_answer(walls, queries, gate))
    assert (found >= 0).any() and (found < 0).any()


def test_no_reference_points_and_non_finite_queries():
    assert NearestWithin(np.zeros((0, 2)), 0.3).query(np.zeros((3, 2))).tolist() == [-1, -1, -1]
    points = np.array([[0.0, 0.0], [1.0, 0.0]])
    queries = np.array([[np.nan, 0.0], [np.inf, 0.0], [0.9, 0.1], [0.5, 0.0]])
    assert NearestWithin(points, 0.3).query(queries).tolist() == [-1, -1, 1, -1]


def test_k_nearest_as_cKDTree_within_the_gate():
    rng = np.random.default_rng(5)
    points = np.concatenate([rng.uniform(0.0, 6.0, (600, 2)), rng.uniform(20.0, 21.0, (3, 2))])
    gate = 0.4
    index, reach = NearestWithin(points, gate).k_nearest(3)
    distances, expected = cKDTree(points).query(points, k=3)
    within = distances[:, -1] <= gate
    assert within.any() and (~within).any()
    np.testing.assert_array_equal(index[within], expected[within])
    np.testing.assert_array_equal(reach[within], distances[within, -1])
    assert (reach[~within] > gate).all()   # beyond the gate: known to be beyond it
