"""The grid over a site's region: cells of one step, row = y, col = x, and the fraction of
each cell inside the region polygon."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from silo_agent.base.limits import MAX_GRID_CELLS, LimitExceeded
from silo_agent.grid.geometry import cell_fractions, grid_shape


@dataclass(frozen=True)
class Grid:
    """Cells of `step` metres covering the region's bounding box; row = y, col = x."""

    origin: tuple[float, float]  # outer corner of cell [0, 0] (minimum x and y)
    step: float
    shape: tuple[int, int]  # (rows, cols)
    inside: np.ndarray  # fraction of each cell inside the region polygon

    @classmethod
    def over(cls, region: np.ndarray, step: float) -> Grid:
        """The grid of `step` over `region`; remembered, since a silo's region never changes."""
        region = np.asarray(region, dtype=float)
        return _grid_over(region.tobytes(), region.shape, step)

    @property
    def cell_area(self) -> float:
        return self.step * self.step

    def cell_index(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of points; callers keep only those inside `valid_cells`."""
        inverse_step = 1.0 / self.step  # a multiply: cheaper than a divide over millions of points
        col = np.floor((x - self.origin[0]) * inverse_step).astype(np.int64)
        row = np.floor((y - self.origin[1]) * inverse_step).astype(np.int64)
        return row, col

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        rows, cols = self.shape
        xs = self.origin[0] + (np.arange(cols) + 0.5) * self.step
        ys = self.origin[1] + (np.arange(rows) + 0.5) * self.step
        return np.meshgrid(xs, ys)


@functools.lru_cache(maxsize=16)
def _grid_over(region_bytes: bytes, region_shape: tuple[int, ...], step: float) -> Grid:
    """`Grid.over`, cached: a daemon asks for the same grid every scan (docs/development.md,
    performance notes). The shared `inside` is read-only."""
    region = np.frombuffer(region_bytes).reshape(region_shape)
    low = region.min(axis=0)
    rows, cols = grid_shape(region, step)
    if rows * cols > MAX_GRID_CELLS:  # refused before numpy is asked for the arrays
        raise LimitExceeded(
            f"the region at grid step {step} m is {rows * cols:,} cells, more "
            f"than the limit of {MAX_GRID_CELLS:,}; use a coarser grid step"
        )
    origin = (float(low[0]), float(low[1]))
    inside = cell_fractions(region, origin, step, (rows, cols))
    inside.flags.writeable = False
    return Grid(origin, step, (rows, cols), inside)
