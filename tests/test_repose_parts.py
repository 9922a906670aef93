"""The repose bounds' parts against the plain computations they stand for: the lattice means
against scipy's Gaussian filter read bilinearly, the near-distance against the exact
distance transform, the pruned envelopes and the local envelopes against every pair."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from silo_agent.reconstruct.fill import (
    _envelopes,
    _LatticeMeans,
    _local_envelopes,
    _near_distance,
    _pair_envelopes,
)


@pytest.mark.parametrize("spacing", [3.0, 0.03 / 0.01, 1.5, 5.0])
def test_the_lattice_means_are_the_filtered_grid_read_at_the_nodes(spacing: float) -> None:
    rng = np.random.default_rng(1)
    values = rng.normal(size=(61, 83)) * (rng.random((61, 83)) < 0.6)
    sigma = 3.0 if spacing > 2 else 1.5
    means = _LatticeMeans(values.shape, sigma, spacing)
    nodes = means.nodes()
    filtered = ndimage.gaussian_filter(values, sigma, mode="constant")
    expected = ndimage.map_coordinates(filtered, list(nodes), order=1, mode="nearest")
    np.testing.assert_allclose(means(values), expected, rtol=0, atol=1e-13)
    rows, cols = np.indices(values.shape, dtype=np.float64)
    moments = means.moments(values)
    for got, weight in zip(moments, (1.0, rows, cols), strict=True):
        plain = ndimage.gaussian_filter(values * weight, sigma, mode="constant")
        reference = ndimage.map_coordinates(plain, list(nodes), order=1, mode="nearest")
        np.testing.assert_allclose(got, reference, rtol=0, atol=1e-11)


def test_the_near_distance_is_the_exact_transform_up_to_its_limit() -> None:
    rng = np.random.default_rng(2)
    known = rng.random((70, 90)) < 0.02
    known[30:50, 40:80] = False  # a hole wider than the limit
    cells = np.nonzero(~known)
    exact = ndimage.distance_transform_edt(~known)[cells]
    for limit in (1, 4, 7):
        got = _near_distance(known, cells, limit)
        near = exact <= limit
        np.testing.assert_array_equal(got[near], exact[near])
        assert np.all(np.isinf(got[~near]))


def test_the_pruned_envelopes_are_those_of_every_pair() -> None:
    rng = np.random.default_rng(3)
    target = (rng.random(3000) * 400, rng.random(3000) * 600)
    source = (rng.random(900) * 400, rng.random(900) * 600)
    heights = rng.random(900) + np.where(rng.random(900) < 0.1, 2.0, 0.0)
    bounds = [(heights, 0.005, True), (heights - 0.1, 0.005, False), (heights, 0.0002, True)]
    pruned = _envelopes(target, source, bounds)
    every = _pair_envelopes(
        *(np.asarray(a, dtype=np.float32) for a in (*target, *source)),
        [np.asarray(h, dtype=np.float32) for h, _, _ in bounds],
        bounds,
    )
    for got, expected in zip(pruned, every, strict=True):
        np.testing.assert_array_equal(got, expected)


def test_no_sources_bound_no_target() -> None:
    """A hole's far bounds come from every other lattice node's sources; a few sources may
    have none there, and the envelope over no pairs is no bound (it was a zero-size reduction)."""
    target = (np.array([1.0, 5.0, 9.0]), np.array([2.0, 4.0, 6.0]))
    none = (np.empty(0), np.empty(0))
    upper, lower = _envelopes(target, none, [(np.empty(0), 0.01, True), (np.empty(0), 0.01, False)])
    np.testing.assert_array_equal(upper, np.full(3, np.inf))
    np.testing.assert_array_equal(lower, np.full(3, -np.inf))


def test_the_local_envelopes_are_those_of_the_sources_within_reach() -> None:
    rng = np.random.default_rng(4)
    where = rng.random((30, 40)) < 0.5
    count = int(where.sum())
    node_r, node_c = np.nonzero(where)
    position = (node_r * 3.0 + rng.random(count), node_c * 3.0 + rng.random(count))
    raised = rng.random(count)
    lowered = raised - 0.2
    slope, reach = 0.01, 3
    under, over = _local_envelopes(where, position, raised, lowered, slope, reach)
    dr = node_r[:, None] - node_r[None, :]
    dc = node_c[:, None] - node_c[None, :]
    within = dr * dr + dc * dc <= reach * reach
    distance = slope * np.hypot(
        position[0][None, :] - position[0][:, None], position[1][None, :] - position[1][:, None]
    )
    np.testing.assert_allclose(
        under, np.min(np.where(within, raised[None, :] + distance, np.inf), axis=1), atol=1e-15
    )
    np.testing.assert_allclose(
        over, np.max(np.where(within, lowered[None, :] - distance, -np.inf), axis=1), atol=1e-15
    )
