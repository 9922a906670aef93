"""Registration residual: how far two cameras disagree on the height of the cells both observe.

Misplaced cameras show up as two surfaces in one cell (paper fig. 4). For every pair of cameras
and every cell both observe with enough points, the difference of their mean heights is taken,
corrected to first order for the local slope (the two cameras' points do not sit at the same
place in the cell, and on a slope that alone is a height difference). The pair's residual is
the median of those differences (robust to edges and shadows) with their MAD. Cells where a
camera's points spread over more than MAX_SPREAD_M in height, or where the surface is steeper
than MAX_SLOPE, are walls and edges, not a surface two cameras can agree on, and are left out
(opposite wall cameras otherwise shared only wall cells and read 0.6 m of "disagreement").

Pure numpy, one bincount per quantity, no loop over cells: it runs on every scan.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from silo_agent.grid.grid import Grid
from silo_agent.reconstruct.fuse import FusedCloud

MAX_SPREAD_M = 0.05  # a camera's points in a cell spread more in height: a wall, not a surface
MAX_SLOPE = 1.0  # 45 deg; grain stands at 23-40 deg, walls and pile edges seen edge-on do not


@dataclass(frozen=True)
class PairResidual:
    """Height of camera `a` minus camera `b` over the cells both observe (metres)."""

    a: str
    b: str
    median_m: float  # signed: positive when `a` sees the surface higher than `b`
    mad_m: float  # median absolute deviation of the per-cell differences (not scaled)
    cells: int  # cells compared

    @property
    def key(self) -> str:
        return pair_key(self.a, self.b)

    def to_json(self) -> dict[str, float | int | str]:
        return {"median_m": self.median_m, "mad_m": self.mad_m, "cells": self.cells}

    @classmethod
    def from_json(cls, key: str, data: Mapping[str, Any]) -> PairResidual:
        """One of a published result's pairs (`key` as `pair_key` makes it)."""
        a, b = key.split("|", 1)
        return cls(a, b, float(data["median_m"]), float(data["mad_m"]), int(data["cells"]))


def median(values: np.ndarray) -> float:
    """`np.median` of a 1-D array, as it computes it (a partition; the mean of the two middle
    values for an even count), without the numpy.ma import np.median makes on its first call."""
    count = len(values)
    if count == 0:
        raise ValueError("median of no values")
    middle = count // 2
    if count % 2:
        return float(np.partition(values, middle)[middle])
    low, high = np.partition(values, [middle - 1, middle])[middle - 1 : middle + 1]
    return float((low + high) / 2.0)


def pair_key(a: str, b: str) -> str:
    """The published name of a camera pair: `"<serial a>|<serial b>"`."""
    return f"{a}|{b}"


def registration_residuals(
    fused: FusedCloud,
    grid: Grid,
    serials: Sequence[str],
    min_points: int = 5,
    min_cells: int = 50,
) -> dict[str, PairResidual]:
    """Residual of every camera pair that shares at least `min_cells` cells.

    A cell counts for a camera when it holds at least `min_points` of its points. Pairs are
    ordered as the cameras are in the scan (`a` before `b`).
    """
    n_cams = len(serials)
    if n_cams < 2 or len(fused.points) == 0:
        return {}
    rows, cols = grid.shape
    moments = fused.moments
    count = moments.count
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_z = moments.sum_z / count
        spread = np.sqrt(np.maximum(moments.sum_zz / count - mean_z**2, 0.0))
    # a camera's cell is a surface seen from above, not a wall or post standing in it
    seen = (count >= min_points) & (spread <= MAX_SPREAD_M)
    shared = seen.sum(axis=0) >= 2
    if not np.any(shared):
        return {}
    # slope from the cameras' mean surface (cells any camera sees; NaN elsewhere)
    with np.errstate(invalid="ignore", divide="ignore"):
        surface = np.where(seen, mean_z, 0.0).sum(axis=0) / seen.sum(axis=0)
    grad_y, grad_x = np.gradient(surface.reshape(rows, cols), grid.step)
    grad_x, grad_y = grad_x.ravel(), grad_y.ravel()
    usable = shared & np.isfinite(grad_x) & np.isfinite(grad_y)
    usable &= np.hypot(grad_x, grad_y) <= MAX_SLOPE  # steeper than grain stands: walls, edges
    cells = np.flatnonzero(usable)
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN where a camera has no point
        mx = moments.sum_x[:, cells] / count[:, cells]
        my = moments.sum_y[:, cells] / count[:, cells]
    mz = mean_z[:, cells]
    gx, gy, ok = grad_x[cells], grad_y[cells], seen[:, cells]
    out: dict[str, PairResidual] = {}
    for i in range(n_cams):
        for j in range(i + 1, n_cams):
            both = ok[i] & ok[j]
            n = int(both.sum())
            if n < min_cells:
                continue
            diff = (
                (mz[i, both] - mz[j, both])
                - gx[both] * (mx[i, both] - mx[j, both])
                - gy[both] * (my[i, both] - my[j, both])
            )
            middle = median(diff)
            mad = median(np.abs(diff - middle))
            residual = PairResidual(serials[i], serials[j], middle, mad, n)
            out[residual.key] = residual
    return out
