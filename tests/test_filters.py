"""The engine's own cross dilation against scipy.ndimage's binary dilation, the library it is
faster than (silo_agent/grid/filters.py says by how much), on random masks of awkward
shapes: single rows and columns, more passes than the grid is wide."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from silo_agent.grid import filters

SHAPES = [(1, 1), (1, 7), (6, 1), (13, 9), (37, 120), (200, 173)]


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("iterations", [1, 2, 10])
def test_dilate_cross_is_ndimage_binary_dilation(shape, iterations) -> None:
    mask = np.random.default_rng(iterations).random(shape) < 0.05
    expected = ndimage.binary_dilation(mask, iterations=iterations)
    assert np.array_equal(filters.dilate_cross(mask, iterations), expected)


def _numpy_block_sums(values: np.ndarray, k: int) -> np.ndarray:
    rows, cols = values.shape
    padded = np.pad(values, ((0, -rows % k), (0, -cols % k)))
    return padded.reshape(padded.shape[0] // k, k, padded.shape[1] // k, k).sum(axis=(1, 3))


@pytest.mark.parametrize("seed", range(40))
def test_block_sums_are_numpys_blocked_sum_to_the_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 10))
    shape = (int(rng.integers(1, 60)), int(rng.integers(1, 60)))
    if seed % 10 == 0:
        shape = (241, 1201)
    values = rng.normal(size=shape) * 10 ** rng.uniform(-3, 3, size=shape)
    values[rng.random(shape) < 0.2] = -0.0  # zeros keep their sign through the sums
    for grid in (
        values,
        (values * 5).astype(np.int64),
        np.asfortranarray(values),
        np.hstack([values, values])[:, ::2],
        values.astype(np.float32),
    ):
        got, expected = filters.block_sums(grid, k), _numpy_block_sums(grid, k)
        assert got.dtype == expected.dtype
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(expected))
