"""Masked smoothing of grids in O(cells) whatever the radius (two box passes ~ a Gaussian)."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage


def masked_smooth(values: np.ndarray, mask: np.ndarray, sigma_cells: float) -> np.ndarray:
    """Weighted local mean of `values` over `mask` cells, about Gaussian with `sigma_cells`.

    Two passes of a box filter (sigma = size / sqrt(6)); cost independent of the radius, where a
    Gaussian's grows with it. NaN outside `mask`. The grids are filtered in float32 (scipy sums
    each window in float64 and rounds once a pass): a height off by ~1e-7 of itself, 0.2 um on
    grain 2 m up, at 0.6-0.8x the time (a 1200 x 1200 grid at sigma 40: 150-230 against
    190-400 ms) and half the memory of float64.
    """
    size = max(3, 2 * round(sigma_cells * math.sqrt(6) / 2) + 1)
    both = np.zeros((2, *mask.shape), np.float32)
    weight, total = both  # views
    weight[...] = mask
    np.copyto(total, values, where=mask)  # rounded to float32 as np.where's float64 would be
    # in place: scipy runs each axis a line at a time through its own buffer, so the values
    # are those of a new array, without two fresh 2 x 4 bytes a cell (a 1201 x 1201 grid: the
    # call 58 -> 47 ms)
    for _ in range(2):
        ndimage.uniform_filter(both, size, mode="constant", axes=(-2, -1), output=both)
    keep = weight > 1e-12
    keep &= mask
    out = np.full(mask.shape, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.divide(total, weight, out=out, where=keep, dtype=np.float64)
