"""The height map: a grid in the silo frame, explicit about origin, order and unknown cells."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class HeightMap:
    """Surface heights on a regular grid (grid_map / OccupancyGrid conventions, made explicit).

    - `origin` is the silo-frame (x, y) of the *outer corner* of cell [0, 0] (minimum x and y).
    - Row r covers y in [origin_y + r*step, origin_y + (r+1)*step): row 0 is the southern-most
      (minimum y) row; column c likewise along +x. Arrays are indexed [row, col] = [y, x].
    - `heights` are silo-frame z in metres, NaN outside the region (the only unknown value).
    - `observed` marks cells that held measured points; the others were filled
      (`reconstruction.fill`: by default the repose fill, the membrane in a bin).
    - `inside` is the fraction (0..1) of each cell inside the region polygon.
    - `floor_z` is the silo-frame z of the floor (levels are heights above it).
    - `base` is (a, b, c) of the base the volume is measured from, z = a*x + b*y + c.
    - `counted` is, per cell, the height above the base that the published volume counts
      (NaN without a surface): volume = step**2 * sum(counted * inside). None when the volume
      does not come from the map (the baseline methods).
    """

    origin: tuple[float, float]
    step: float
    heights: np.ndarray
    observed: np.ndarray
    inside: np.ndarray
    floor_z: float | None = None
    base: tuple[float, float, float] | None = None
    counted: np.ndarray | None = None
    captured_at: str | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) of every cell centre, each shaped like `heights`."""
        rows, cols = self.shape
        xs = self.origin[0] + (np.arange(cols) + 0.5) * self.step
        ys = self.origin[1] + (np.arange(rows) + 0.5) * self.step
        return np.meshgrid(xs, ys)

    def height_at(self, x: float, y: float) -> float:
        """Height of the cell containing (x, y); NaN outside the grid or region."""
        col = int(np.floor((x - self.origin[0]) / self.step))
        row = int(np.floor((y - self.origin[1]) / self.step))
        rows, cols = self.shape
        if not (0 <= row < rows and 0 <= col < cols):
            return float("nan")
        return float(self.heights[row, col])
