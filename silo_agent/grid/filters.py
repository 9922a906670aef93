"""The few grid filters the engine runs on every scan, in numpy: box means, square minimum and
maximum, and dilation by the 4-neighbour cross. Grids are 2-D (box means also take a stack).

scipy.ndimage has all of them, but a one-off `silo-agent process` would pay about 0.25 s to
import it (its array-API layer copies numpy's namespace and so loads numpy.f2py, numpy.testing
and more), far more than the filters take to run. Each function here gives what its ndimage
counterpart gives in the mode the engine uses, to the bit (tests/test_filters.py compares
them): box means by ndimage's own running sums, minimum and maximum by van Herk / Gil-Werman
block scans, so each costs O(cells) whatever the window. Every filter runs down the columns
(axis 0) of the grid, then of its transpose; the loops step through the rows of a window or a
grid, each step one operation on whole rows, never a loop over cells.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

BoxMode = Literal["constant", "nearest"]  # zeros, or the edge cell repeated, outside the grid


def box_mean(values: np.ndarray, size: int, mode: BoxMode = "constant") -> np.ndarray:
    """`ndimage.uniform_filter(values, size, mode=mode)` over the last two axes (`size` odd),
    to the bit: the same running sums added in the same order. Leading axes stack grids that
    are filtered together, each on its own, so the passes' loops run once for all of them.
    As in ndimage, a NaN spoils the rest of its row or column: callers pass finite values."""
    if size < 1 or size % 2 != 1:
        raise ValueError(f"window size must be odd and positive, got {size}")
    if size == 1:  # as ndimage: the values themselves
        return values.astype(np.float64)
    down = _uniform_down(values, size, mode)
    across = _uniform_down(np.ascontiguousarray(down.swapaxes(-1, -2)), size, mode)
    return across.swapaxes(-1, -2)


def _uniform_down(values: np.ndarray, size: int, mode: BoxMode) -> np.ndarray:
    """`ndimage.uniform_filter1d` along axis -2: a running sum of the padded rows (the first
    window added row by row, then each step adds the entering row minus the leaving one),
    each output that sum divided by `size`. The steps' differences are taken at once; only
    their sequential total is a loop, over rows, each step one operation on whole rows."""
    rows = values.shape[-2]
    half = size // 2
    padded = np.zeros((*values.shape[:-2], rows + size - 1, values.shape[-1]))
    padded[..., half : half + rows, :] = values
    if mode == "nearest":
        padded[..., :half, :] = values[..., :1, :]
        padded[..., half + rows :, :] = values[..., -1:, :]
    running = np.empty((*values.shape[:-2], rows, values.shape[-1]))
    first = running[..., 0, :]
    first[...] = padded[..., 0, :]
    for row in range(1, size):
        first += padded[..., row, :]
    np.subtract(padded[..., size:, :], padded[..., : rows - 1, :], out=running[..., 1:, :])
    for row in range(1, rows):
        np.add(running[..., row - 1, :], running[..., row, :], out=running[..., row, :])
    running /= size
    return running


def minimum_filter(values: np.ndarray, size: int) -> np.ndarray:
    """`ndimage.minimum_filter(values, size)`: square window, mode 'reflect'."""
    return _extreme_down(_extreme_down(values, size, np.minimum).T, size, np.minimum).T


def maximum_filter(values: np.ndarray, size: int) -> np.ndarray:
    """`ndimage.maximum_filter(values, size)`: square window, mode 'reflect'."""
    return _extreme_down(_extreme_down(values, size, np.maximum).T, size, np.maximum).T


def _extreme_down(values: np.ndarray, size: int, pick: np.ufunc) -> np.ndarray:
    """Van Herk / Gil-Werman along axis 0: in blocks of `size` rows, running extremes forwards
    and backwards; a window spans the end of one block and the start of the next, so its
    extreme is the pick of one backward and one forward value. The loops run over the rows of
    a block (the window), each step a whole-row operation."""
    if size < 1:
        raise ValueError(f"window size must be positive, got {size}")
    if size == 1:
        return values.copy()
    rows = values.shape[0]
    before, after = size // 2, size - 1 - size // 2  # ndimage's centring, even sizes too
    blocks = -(-(rows + size - 1) // size)
    identity = np.inf if pick is np.minimum else -np.inf
    padded = np.full((blocks * size, *values.shape[1:]), identity)
    padded[before : before + rows] = values
    # mode 'reflect' (d c b a | a b c d | d c b a): one reflected copy each side is enough,
    # since a window reaching past it holds the whole grid already
    lead = min(before, rows)
    padded[before - lead : before] = values[:lead][::-1]
    tail = min(after, rows)
    padded[before + rows : before + rows + tail] = values[rows - tail :][::-1]
    forward = padded.reshape(blocks, size, -1)
    backward = forward.copy()
    for k in range(1, size):
        pick(forward[:, k], forward[:, k - 1], out=forward[:, k])
        j = size - 1 - k
        pick(backward[:, j], backward[:, j + 1], out=backward[:, j])
    forward_rows = forward.reshape(padded.shape)
    backward_rows = backward.reshape(padded.shape)
    return pick(backward_rows[:rows], forward_rows[size - 1 : size - 1 + rows])


def dilate_cross(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """`ndimage.binary_dilation(mask, iterations=iterations)`: each pass adds the 4-neighbours
    of every set cell (nothing is set beyond the grid)."""
    out = mask.astype(bool)
    for _ in range(iterations):
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        out = grown
    return out
