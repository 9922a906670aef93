"""Volume, base plane and levels from a filled height map (paper 2.4, cut cells weighted)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from silo_agent.grid.grid import Grid
from silo_agent.grid.smooth import masked_smooth

DENOISE_SCALE_M = 0.20  # smoothing under the base clip (integrate_denoised, denoised_columns)


@dataclass(frozen=True)
class Levels:
    min: float
    mean: float
    max: float


def boundary_cells(inside: np.ndarray) -> np.ndarray:
    """Cells of the region touching its edge: cut by the polygon or next to an outside cell."""
    region = inside > 0
    padded = np.pad(region, 1, constant_values=False)
    all_neighbours_in = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    return region & ((inside < 1.0) | ~all_neighbours_in)


def base_plane(
    grid: Grid, heights: np.ndarray, base: str, floor_z: float
) -> tuple[float, float, float]:
    """(a, b, c) of the base under the grain, z = a*x + b*y + c: the floor, or a plane fitted
    along the boundary. Published in the height map so a robot measures from the same base.

    Parameters
    ----------
    grid : Grid
        The grid over the region (`inside` marks the region's cells).
    heights : ndarray, shape grid.shape
        Filled surface heights, silo frame; NaN where unknown.
    base : {"floor", "boundary"}
        The flat floor at `floor_z`, or the least-squares plane through the boundary cells.
    floor_z : float
        Silo-frame z of the floor.

    Returns
    -------
    tuple of float
        (a, b, c).

    Raises
    ------
    ValueError
        `base = "boundary"` with fewer than 3 boundary cells that have a height.
    """
    if base == "floor":
        return 0.0, 0.0, float(floor_z)
    ring = boundary_cells(grid.inside) & np.isfinite(heights)
    if ring.sum() < 3:
        raise ValueError("base = 'boundary' needs at least 3 boundary cells with a height")
    xs, ys = grid.centres()
    design = np.column_stack([xs[ring], ys[ring], np.ones(int(ring.sum()))])
    (a, b, c), *_ = np.linalg.lstsq(design, heights[ring], rcond=None)
    return float(a), float(b), float(c)


def base_surface(grid: Grid, heights: np.ndarray, base: str, floor_z: float) -> np.ndarray:
    """Height of the base under every cell (`base_plane` evaluated at the cell centres).

    Parameters
    ----------
    grid, heights, base, floor_z
        As for `base_plane`.

    Returns
    -------
    ndarray, shape grid.shape
        Silo-frame z of the base at each cell centre.
    """
    if base == "floor":
        return np.full(grid.shape, floor_z)
    a, b, c = base_plane(grid, heights, base, floor_z)
    xs, ys = grid.centres()
    return a * xs + b * ys + c


def integrate(grid: Grid, heights: np.ndarray, base: np.ndarray) -> float:
    """Sum over cells of max(height - base, 0) x cell area x fraction of the cell inside.

    Parameters
    ----------
    grid : Grid
        The grid; `inside` weighs the region's cut cells.
    heights : ndarray, shape grid.shape
        Surface heights; NaN cells count nothing.
    base : ndarray, shape grid.shape
        Height of the base under each cell (`base_surface`).

    Returns
    -------
    float
        Volume in cubic metres.
    """
    above = np.where(np.isfinite(heights), np.maximum(heights - base, 0.0), 0.0)
    return float(np.sum(above * grid.inside) * grid.cell_area)


def integrate_counted(grid: Grid, counted: np.ndarray) -> float:
    """The volume: the heights the volume counts (`counted_heights`), weighted by the fraction
    of each cell inside the region, times the cell area.

    Parameters
    ----------
    grid : Grid
        The grid the heights are on.
    counted : ndarray, shape grid.shape
        `counted_heights`; NaN cells count nothing.

    Returns
    -------
    float
        Volume in cubic metres.
    """
    return float(np.sum(counted_columns(grid, counted)) * grid.cell_area)


def counted_columns(grid: Grid, counted: np.ndarray) -> np.ndarray:
    """Per cell, the counted height times the fraction inside (0 where there is no surface).

    Summed over any set of cells (a pile, the whole region) and multiplied by the cell area it
    gives that set's volume, so per-pile volumes add up to the engine's total."""
    return np.where(np.isfinite(counted), counted, 0.0) * grid.inside


def denoised_columns(
    grid: Grid, heights: np.ndarray, base: np.ndarray, scale_m: float
) -> np.ndarray:
    """`counted_columns` of a height map over `base`."""
    return counted_columns(grid, counted_heights(grid, heights, base, scale_m))


def counted_heights(
    grid: Grid, heights: np.ndarray, base: np.ndarray, scale_m: float
) -> np.ndarray:
    """Per cell, the height above `base` that the volume counts; NaN where there is no surface.

    Clipping each noisy cell at the base turns zero-mean sensor noise on a bare floor into a
    positive volume (about 0.4 sigma per cell). Here the surface is split into a smooth part
    (about Gaussian, `scale_m`) and the detail; only the smooth part is clipped, the detail is
    summed signed: counted = max(smooth, 0) + (height - base - smooth). Real areas below the
    base survive smoothing and are still excluded; noise cancels.

    Parameters
    ----------
    grid : Grid
        The grid over the region.
    heights : ndarray, shape grid.shape
        Filled surface heights, silo frame; NaN where unknown.
    base : ndarray, shape grid.shape
        Height of the base under each cell (`base_surface`).
    scale_m : float
        Scale of the smooth part (the smoothing's sigma, metres; at least one cell).

    Returns
    -------
    ndarray, shape grid.shape
        Counted height per cell (may be negative in a cell); NaN outside the region or
        where `heights` is NaN.
    """
    region = (grid.inside > 0) & np.isfinite(heights)
    relative = np.where(region, heights - base, 0.0)
    smooth = masked_smooth(relative, region, max(scale_m / grid.step, 1.0))
    smooth = np.where(region, smooth, 0.0)
    counted = np.maximum(smooth, 0.0) + (relative - smooth)
    return np.where(region, counted, np.nan)


def surface_levels(grid: Grid, heights: np.ndarray) -> Levels:
    """Min, area-weighted mean and max of the surface over the region.

    Parameters
    ----------
    grid : Grid
        The grid; `inside` weighs the mean.
    heights : ndarray, shape grid.shape
        Surface heights; at least one finite cell inside the region.

    Returns
    -------
    Levels
        Silo-frame z (not above the floor).
    """
    region = (grid.inside > 0) & np.isfinite(heights)
    values = heights[region]
    weights = grid.inside[region]
    return Levels(
        float(values.min()), float(np.sum(values * weights) / np.sum(weights)), float(values.max())
    )


LEVEL_SCALE_M = 0.4  # where a bin's highest and lowest grain are looked for ...
LEVEL_FIT_RADIUS_M = 1.0  # ... and the radius of the cone fitted there
LEVEL_WALL_BAND_M = 0.3  # ... but not this close to a bin's wall
LEVEL_CONE_MIN_SLOPE = 0.15  # a fitted slope under this (8.5 deg) is a flat surface's noise
GRAIN_MIN_DEPTH_M = 0.10  # grain, for a bin's levels: this deep, smoothed at LEVEL_SCALE_M


def _fitted_peak(
    grid: Grid, heights: np.ndarray, cells: np.ndarray, at: tuple[int, int], radius_m: float
) -> float:
    """Height at cell `at` of the cone h = a + b * distance fitted (least squares) to the
    `cells` within `radius_m` of it: exact on a heap's apex or a crater's bottom, the local
    mean on a flat surface (there the plain mean: extrapolating a noisy slope to the centre
    would read the very dip or bump that made the cell an extreme)."""
    xs, ys = grid.centres()
    distance = np.hypot(xs - xs[at], ys - ys[at])
    near = cells & (distance <= radius_m)
    design = np.column_stack([np.ones(int(near.sum())), distance[near]])
    (peak, slope), *_ = np.linalg.lstsq(design, heights[near], rcond=None)
    if abs(slope) < LEVEL_CONE_MIN_SLOPE:  # no cone: the local mean, not an extrapolation
        return float(np.mean(heights[near]))
    return float(peak)


def grain_levels(
    grid: Grid,
    heights: np.ndarray,
    counted: np.ndarray,
    observed: np.ndarray,
    off_wall: np.ndarray,
) -> Levels:
    """A bin's min, mean and max grain level, over the cells where grain stands (bare floor or
    hopper steel is not grain).

    At 8-10 m one cell's height is off by centimetres; the highest of thousands of cells is
    then the highest noise, not the highest grain, and a surface smoothed enough to hide the
    noise has a heap's apex rounded off. So the extremes are located on the measured grain
    smoothed at LEVEL_SCALE_M, and read from a cone fitted to the unsmoothed cells around
    them (LEVEL_FIT_RADIUS_M): a heap's apex and a crater's bottom are cones. They are looked
    for `off_wall` only: the grain at the foot of the wall is seen from across the bin, at the
    longest range, where the wall's noise was cut away; it reads ~0.1 m off."""
    region = (grid.inside > 0) & np.isfinite(heights)
    scale = max(LEVEL_SCALE_M / grid.step, 1.0)
    depth = masked_smooth(np.nan_to_num(counted), region, scale)
    grain = region & (np.nan_to_num(depth) > GRAIN_MIN_DEPTH_M)
    if not np.any(grain):
        grain = region
    measured = grain & observed & off_wall
    if not np.any(measured):
        measured = grain
    smooth = masked_smooth(heights, region, scale)
    ranked = np.where(measured & np.isfinite(smooth), smooth, np.nan)
    top = np.unravel_index(int(np.nanargmax(ranked)), ranked.shape)
    low = np.unravel_index(int(np.nanargmin(ranked)), ranked.shape)
    weights = grid.inside[grain]
    mean = float(np.sum(heights[grain] * weights) / np.sum(weights))
    return Levels(
        _fitted_peak(grid, heights, measured, (int(low[0]), int(low[1])), LEVEL_FIT_RADIUS_M),
        mean,
        _fitted_peak(grid, heights, measured, (int(top[0]), int(top[1])), LEVEL_FIT_RADIUS_M),
    )
