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
