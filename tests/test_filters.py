"""The engine's numpy grid filters against scipy.ndimage, the library they stand in for on the
scan path (silo_agent/grid/filters.py says why), on random grids of awkward shapes:
single rows and columns, windows longer than the grid, even windows, infinities."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from silo_agent.grid import filters

SHAPES = [(1, 1), (1, 7), (6, 1), (13, 9), (37, 120), (200, 173)]


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("size", [1, 3, 5, 11, 49])
@pytest.mark.parametrize("mode", ["constant", "nearest"])
def test_box_mean_is_ndimage_uniform_filter_to_the_bit(shape, size, mode) -> None:
    """To the bit, not to a tolerance: the engine compares smoothed values with thresholds
    (a cell's count against half its neighbourhood's), and a last-bit difference flipped some
    of those decisions on exact ties."""
    values = np.random.default_rng(size).normal(1.5, 0.4, shape)
    expected = ndimage.uniform_filter(values, size, mode=mode)
    assert np.array_equal(filters.box_mean(values, size, mode), expected)
    counts = np.random.default_rng(size).integers(0, 9, shape).astype(float)  # ties aplenty
    assert np.array_equal(
        filters.box_mean(counts, size, mode), ndimage.uniform_filter(counts, size, mode=mode)
    )


def test_box_mean_filters_stacked_grids_each_on_its_own() -> None:
    rng = np.random.default_rng(7)
    first, second = rng.random((30, 40)), rng.random((30, 40))
    for mode in ("constant", "nearest"):
        stacked = filters.box_mean(np.stack([first, second]), 5, mode)
        assert np.array_equal(stacked[0], ndimage.uniform_filter(first, 5, mode=mode))
        assert np.array_equal(stacked[1], ndimage.uniform_filter(second, 5, mode=mode))


def test_box_filters_refuse_even_windows() -> None:
    with pytest.raises(ValueError, match="odd"):
        filters.box_mean(np.zeros((4, 4)), 4)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("size", [1, 2, 3, 4, 11, 12, 101])
def test_minimum_and_maximum_are_ndimage_filters(shape, size) -> None:
    rng = np.random.default_rng(sum(shape) + size)
    values = rng.normal(size=shape)
    values[rng.random(shape) < 0.1] = np.inf  # how the engine marks cells outside the region
    assert np.array_equal(
        filters.minimum_filter(values, size), ndimage.minimum_filter(values, size)
    )
    assert np.array_equal(
        filters.maximum_filter(-values, size), ndimage.maximum_filter(-values, size)
    )


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("iterations", [1, 2, 10])
def test_dilate_cross_is_ndimage_binary_dilation(shape, iterations) -> None:
    mask = np.random.default_rng(iterations).random(shape) < 0.05
    expected = ndimage.binary_dilation(mask, iterations=iterations)
    assert np.array_equal(filters.dilate_cross(mask, iterations), expected)
