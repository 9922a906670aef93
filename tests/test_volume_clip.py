"""`counted_heights`' clip at the base: unbiased for a bare floor's noise, still robust.

With the cameras' information the smooth part of the surface is summed signed where it is
noise: within NOISE_CLIP_SIGMAS of its own sigma of the base, on a floor whose mean over metres
is at the base. On a flat bare floor with noise the volume sums to ~0, where a clip at the base
counts about 0.4 of the smooth part's sigma a cell; ground truly under the base (a pit), a
floor set a little too high, and a fill under the base still count nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from silo_agent.grid.grid import Grid
from silo_agent.grid.smooth import masked_smooth
from silo_agent.grid.volume import NOISE_CLIP_SIGMAS, counted_heights, integrate_counted

STEP = 0.04  # a 20 m square floor at 4 cm: 250 000 cells
CELLS = 500
SCALE_M = 0.2
SIGMA_CELL_M = 0.01  # each cell's height noise, independent cell to cell
FLOOR_Z = 1.0


def _grid() -> Grid:
    return Grid((0.0, 0.0), STEP, (CELLS, CELLS), np.ones((CELLS, CELLS)))


def _noisy(surface: np.ndarray, seed: int = 0) -> np.ndarray:
    return surface + np.random.default_rng(seed).normal(0.0, SIGMA_CELL_M, surface.shape)


def _information(grid: Grid) -> np.ndarray:
    """Each cell's information density for noise of SIGMA_CELL_M a cell: 1 / (area x var)."""
    return np.full(grid.shape, 1.0 / (grid.cell_area * SIGMA_CELL_M**2))


def _volume(grid: Grid, heights: np.ndarray, information: np.ndarray | None) -> float:
    base = np.full(grid.shape, FLOOR_Z)
    return integrate_counted(grid, counted_heights(grid, heights, base, SCALE_M, information))


def _smooth_sigma(grid: Grid, noise: np.ndarray) -> float:
    """The smooth part's noise sigma, measured: the scatter of the smoothed noise itself
    (away from the edges, where the kernel is whole)."""
    smooth = masked_smooth(noise, np.ones(grid.shape, bool), SCALE_M / STEP)
    return float(np.std(smooth[50:-50, 50:-50]))


def test_a_noisy_bare_floor_sums_to_about_nothing() -> None:
    grid = _grid()
    heights = _noisy(np.full(grid.shape, FLOOR_Z))
    area = CELLS * CELLS * grid.cell_area
    sigma_smooth = _smooth_sigma(grid, heights - FLOOR_Z)
    # the signed sum of N independent cells: sigma_cell x sqrt(N) x cell area; allow 4
    noise_bound = 4 * SIGMA_CELL_M * CELLS * grid.cell_area
    clipped_at_base = _volume(grid, heights, None)
    volume = _volume(grid, heights, _information(grid))
    # the clip at the base: 0.4 sigma a cell, about ten times the signed sum's noise here
    expected_bias = sigma_smooth / math.sqrt(2 * math.pi) * area
    assert clipped_at_base == pytest.approx(expected_bias, rel=0.25)
    assert clipped_at_base > 2 * noise_bound
    # what is left of it: the noise's tail under -k sigma (phi(3), 1 % of it), and the floor
    # patches whose 2 m mean reads low by chance (1.5 of that mean's sigmas: 7 % of the floor,
    # 1-28 % over 20 seeds), clipped at the base as offsets
    signed = float(np.sum(heights - FLOOR_Z) * grid.cell_area)
    assert 0.0 <= volume - signed <= 0.4 * (clipped_at_base - signed)
    assert abs(volume) <= noise_bound + 0.4 * expected_bias


def test_a_floor_set_a_little_too_high_is_clipped_as_before() -> None:
    """The whole floor 1 mm under the base (2 sigma of the smooth part: noise, cell by cell):
    its 2 m mean says it is an offset, and it is clipped at the base as it was; summed signed
    it would count -1 mm a cell."""
    grid = _grid()
    heights = _noisy(np.full(grid.shape, FLOOR_Z - 0.001))
    area = CELLS * CELLS * grid.cell_area
    volume = _volume(grid, heights, _information(grid))
    clipped_at_base = _volume(grid, heights, None)
    signed = float(np.sum(heights - FLOOR_Z) * grid.cell_area)
    assert signed == pytest.approx(-0.001 * area, rel=0.1)
    noise_bound = 4 * SIGMA_CELL_M * CELLS * grid.cell_area
    assert abs(volume - clipped_at_base) <= 0.05 * abs(signed)
    assert volume >= -noise_bound


def test_ground_truly_under_the_base_is_still_not_counted() -> None:
    """Half the floor 5 cm under the base (a pit, or a floor set 5 cm too high there): that half
    counts nothing, as the clip at the base counted; summed signed it would be -5 cm a cell."""
    grid = _grid()
    true = np.full(grid.shape, FLOOR_Z)
    true[:, CELLS // 2 :] -= 0.05
    heights = _noisy(true)
    half = CELLS * CELLS // 2 * grid.cell_area
    noise_bound = 4 * SIGMA_CELL_M * CELLS * grid.cell_area

    volume = _volume(grid, heights, _information(grid))
    clipped_at_base = _volume(grid, heights, None)
    signed = float(np.sum(heights - FLOOR_Z) * grid.cell_area)
    assert signed < -0.045 * half
    # where the step is smoothed over (a few kernel widths along a 20 m edge), the smooth part
    # passes through -k sigma: at most k sigma a cell there
    sigma_smooth = _smooth_sigma(grid, heights - true)
    band = 6 * SCALE_M * CELLS * STEP
    assert volume >= -noise_bound - NOISE_CLIP_SIGMAS * sigma_smooth * band
    assert abs(volume - clipped_at_base) <= NOISE_CLIP_SIGMAS * sigma_smooth * (band + 0.1 * half)


def test_a_fill_under_the_base_counts_nothing() -> None:
    """Filled cells carry no noise (information 0): a fill under the base, far from any
    measured cell, is clipped at the base as before; without information everything is."""
    grid = _grid()
    heights = _noisy(np.full(grid.shape, FLOOR_Z))
    information = _information(grid)
    filled = np.zeros(grid.shape, bool)
    filled[:, CELLS // 2 :] = True
    heights[filled] = FLOOR_Z - 0.002  # a membrane sagging 2 mm under the floor
    information[filled] = 0.0
    base = np.full(grid.shape, FLOOR_Z)
    counted = counted_heights(grid, heights, base, SCALE_M, information)
    deep = filled.copy()
    deep[:, : CELLS // 2 + 4 * round(SCALE_M / STEP)] = False  # beyond the kernel's reach
    assert np.all(np.abs(counted[deep]) < 1e-6)  # the smooth part clipped, no detail left
    without = counted_heights(grid, heights, base, SCALE_M, None)
    assert np.array_equal(counted[deep], without[deep])
