"""Exact nearest neighbours (tasks/occupancy/nearest.py) against a brute-force answer."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.occupancy.nearest import nearest_indices


def _brute(src: np.ndarray, qry: np.ndarray) -> np.ndarray:
    d = ((qry[:, None, :] - src[None, :, :]) ** 2).sum(axis=2)
    return np.argmin(d, axis=1)  # the first (lowest index) of equal minima


@pytest.mark.parametrize("leaf_size", [1, 4, 32])
def test_matches_brute_force_on_a_sweep_like_cloud(leaf_size):
    """Sources in a camera-like wedge, queries all around (many far from every source), in scan
    order and shuffled: the same answers as an exhaustive search."""
    rng = np.random.default_rng(3)
    az = rng.uniform(-np.pi, np.pi, 3000)
    r = rng.uniform(1.0, 40.0, 3000)
    pts = np.stack([r * np.cos(az), r * np.sin(az), rng.uniform(-1.0, 3.0, 3000)], 1)
    in_view = np.abs(az) < 0.6
    src, qry = pts[in_view], pts[~in_view]
    expected = _brute(src, qry)
    np.testing.assert_array_equal(nearest_indices(src, qry, leaf_size=leaf_size), expected)
    order = rng.permutation(len(qry))
    np.testing.assert_array_equal(
        nearest_indices(src, qry[order], leaf_size=leaf_size), expected[order]
    )


def test_ties_take_the_lowest_index_and_threads_do_not_matter():
    # a lattice: many queries are equidistant from several sources, and sources repeat
    g = np.stack(
        np.meshgrid(np.arange(6.0), np.arange(6.0), np.arange(3.0), indexing="ij"), -1
    ).reshape(-1, 3)
    src = np.concatenate([g, g[::7]])  # duplicates come after their first copy
    qry = np.concatenate([g + 0.5, g[::-1] + [0.5, 0.0, 0.0], g])
    qry = np.tile(qry, (40, 1))  # enough rows to be split over threads
    expected = _brute(src, qry)
    for threads in (1, 2, 3):
        np.testing.assert_array_equal(
            nearest_indices(src, qry, threads=threads, leaf_size=4), expected
        )


def test_single_source_and_empty_queries():
    assert nearest_indices(np.zeros((1, 3)), np.ones((5, 3))).tolist() == [0] * 5
    assert nearest_indices(np.zeros((4, 3)), np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match="at least one source"):
        nearest_indices(np.zeros((0, 3)), np.ones((2, 3)))
