"""Registration residual: how far two cameras disagree on the height of the cells both observe.

Misplaced cameras show up as two surfaces in one cell (paper fig. 4). For every pair of cameras
and every cell both observe with enough points, the difference of their mean heights is taken,
corrected to first order for the local slope (the two cameras' points do not sit at the same
place in the cell, and on a slope that alone is a height difference). The pair's residual is
the median of those differences (robust to edges and shadows) with their MAD. Cells where a
camera's points spread over more than MAX_SPREAD_M in height, or where the surface is steeper
than MAX_SLOPE, are walls and edges, not a surface two cameras can agree on, and are left out
(opposite wall cameras otherwise shared only wall cells and read 0.6 m of "disagreement").

Pure numpy on the sparse (cell, camera) moments, no loop over cells and nothing cameras x cells:
it runs on every scan. The cameras of a cell sit side by side in those moments, so the pairs of
cameras in a cell are the moments one, two, ... places apart within the cell.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from silo_agent.grid.grid import Grid
from silo_agent.reconstruct.fuse import FusedCloud, run_starts

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
    # in place, and each array dropped once read: this runs while the fused cloud and its
    # moments are held, at the second pass's peak (2.8 M pairs of 8 cameras at 1 cm)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_z = moments.sum_z / count
        spread = moments.sum_zz / count
        spread -= np.square(mean_z)
        np.maximum(spread, 0.0, out=spread)
        np.sqrt(spread, out=spread)
    # a camera's cell is a surface seen from above, not a wall or post standing in it
    seen = np.flatnonzero((count >= min_points) & (spread <= MAX_SPREAD_M))
    del spread
    # in (cell, camera) order: the moments' pairs come camera by camera, and a stable sort by
    # cell merges the cameras' ascending runs with each cell's cameras kept in order
    seen = seen[np.argsort(moments.cell[seen], kind="stable")]
    cell = moments.cell[seen]
    cameras_seeing = np.bincount(cell, minlength=rows * cols)
    most = int(cameras_seeing.max()) if len(cameras_seeing) else 0
    if most < 2:
        return {}
    # slope from the cameras' mean surface (cells any camera sees; NaN elsewhere)
    mz = mean_z[seen]
    del mean_z
    with np.errstate(invalid="ignore", divide="ignore"):  # a bincount adds them in order
        surface = np.bincount(cell, mz, rows * cols) / cameras_seeing
    grad_y_grid, grad_x_grid = np.gradient(surface.reshape(rows, cols), grid.step)
    del surface
    grad_x, grad_y = grad_x_grid.ravel(), grad_y_grid.ravel()
    usable = (cameras_seeing >= 2) & np.isfinite(grad_x) & np.isfinite(grad_y)
    del cameras_seeing
    usable &= np.hypot(grad_x, grad_y) <= MAX_SLOPE  # steeper than grain stands: walls, edges
    kept = usable[cell]
    del usable
    seen, cell, mz = seen[kept], cell[kept], mz[kept]
    del kept
    gx, gy = grad_x[cell], grad_y[cell]
    del grad_x, grad_y, grad_x_grid, grad_y_grid
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = moments.sum_x[seen] / count[seen]
        my = moments.sum_y[seen] / count[seen]
    camera = moments.camera[seen].astype(np.int32)  # camera x n_cams + camera fits
    del seen
    keys, diffs = [], []
    for apart in range(1, most):
        a = np.flatnonzero(cell[:-apart] == cell[apart:])  # a camera and one `apart` later
        if len(a) == 0:
            continue
        b = a + apart
        keys.append((camera[a] * n_cams + camera[b]).astype(np.uint16))  # cameras <= 256
        diffs.append((mz[a] - mz[b]) - gx[a] * (mx[a] - mx[b]) - gy[a] * (my[a] - my[b]))
    if not keys:
        return {}
    key, diff = np.concatenate(keys), np.concatenate(diffs)
    order = np.argsort(key, kind="stable")  # a counting sort for 16-bit keys
    key, diff = key[order], diff[order]
    bounds = [*run_starts(key), len(key)]
    out: dict[str, PairResidual] = {}
    for first, last in itertools.pairwise(bounds):
        n = int(last - first)
        if n < min_cells:
            continue
        i, j = divmod(int(key[first]), n_cams)
        middle = median(diff[first:last])
        mad = median(np.abs(diff[first:last] - middle))
        residual = PairResidual(serials[i], serials[j], middle, mad, n)
        out[residual.key] = residual
    return out
