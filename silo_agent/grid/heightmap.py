"""The height map: a grid in the silo frame, explicit about origin, order and unknown cells."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from silo_agent.grid.filters import block_sums


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

    def coarsened(self, k: int, inside: np.ndarray | None = None) -> HeightMap:
        """This map on cells k times as wide (same origin), `inside` their fractions in the
        region (default the mean of their k x k cells', which is that fraction: areas add):
        a cell's height is the mean of its finite cells' (weighted by their fraction
        inside), it is observed where most of its area inside was, and its counted height
        keeps the volume: step'^2 x sum(counted' x inside') = step^2 x sum(counted x inside)."""
        area = block_sums(self.inside.astype(np.float64), k)
        if inside is None:
            inside = area / (k * k)
        rows, cols = inside.shape
        area = area[:rows, :cols]
        known = np.isfinite(self.heights)
        weight = np.where(known, self.inside, 0.0)
        total = block_sums(weight, k)[:rows, :cols]
        with np.errstate(invalid="ignore", divide="ignore"):
            heights = block_sums(np.where(known, self.heights * weight, 0.0), k)[:rows, :cols]
            heights = np.where((total > 0) & (inside > 0), heights / total, np.nan)
            seen = block_sums(np.where(self.observed, self.inside, 0.0), k)[:rows, :cols]
            counted = None
            if self.counted is not None:
                finite = np.isfinite(self.counted)
                column = block_sums(np.where(finite, self.counted * self.inside, 0.0), k)
                any_finite = block_sums(finite.astype(np.float64), k)[:rows, :cols] > 0
                counted = np.where(
                    any_finite & (inside > 0), column[:rows, :cols] / (k * k * inside), np.nan
                )
        return HeightMap(
            self.origin,
            self.step * k,
            heights.astype(self.heights.dtype),
            (seen >= 0.5 * area) & (area > 0),
            inside,
            floor_z=self.floor_z,
            base=self.base,
            counted=counted,
            captured_at=self.captured_at,
        )
