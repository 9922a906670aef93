"""`counted_heights`' clip at the base, corrected for the noise the smooth part keeps.

A flat bare floor at the base with known noise holds no volume: the clip at the base counts
about 0.4 of the smooth part's sigma a cell there, and the correction (the clip's expected
excess, from the cameras' information) takes part of that off, never more than down to
min(smooth, 0) a cell, whatever the information claims. The truths here come from the noise
itself (its measured scatter after smoothing) and from quadrature over the normal density, not
from the code under test."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, ndimage
from scipy.stats import norm

from silo_agent.grid.grid import Grid
from silo_agent.grid.smooth import masked_smooth
from silo_agent.grid.volume import (
    _block_smooth,
    _kernel_share,
    clip_excess,
    counted_heights,
    integrate_counted,
    smooth_sigma,
)

STEP = 0.04  # a 20 m square floor at 4 cm: 250 000 cells
CELLS = 500
SCALE_M = 0.2
SIGMA_CELL_M = 0.01  # each cell's height noise, independent cell to cell
FLOOR_Z = 1.0


def _grid(step: float = STEP, cells: int = CELLS) -> Grid:
    return Grid((0.0, 0.0), step, (cells, cells), np.ones((cells, cells)))


def _noisy(surface: np.ndarray, seed: int = 0) -> np.ndarray:
    return surface + np.random.default_rng(seed).normal(0.0, SIGMA_CELL_M, surface.shape)


def _information(grid: Grid, scale: float = 1.0) -> np.ndarray:
    """Each cell's information density for noise of SIGMA_CELL_M a cell, 1 / (area x var),
    times `scale` (a depth noise factor k off by 1 / sqrt(scale))."""
    return np.full(grid.shape, scale / (grid.cell_area * SIGMA_CELL_M**2))


def _counted(grid: Grid, heights: np.ndarray, information: np.ndarray | None) -> np.ndarray:
    return counted_heights(grid, heights, np.full(grid.shape, FLOOR_Z), SCALE_M, information)


def _smooth_noise(grid: Grid, noise: np.ndarray) -> np.ndarray:
    return masked_smooth(noise, np.ones(grid.shape, bool), SCALE_M / grid.step)


def _measured_sigma(grid: Grid, noise: np.ndarray) -> float:
    """The smooth part's noise sigma, measured: the scatter of the smoothed noise itself, away
    from the edges (1 m), where the kernel is whole."""
    margin = round(1.0 / grid.step)
    return float(np.std(_smooth_noise(grid, noise)[margin:-margin, margin:-margin]))


def _expected_excess(mu: float, sigma: float) -> float:
    """E[max(X, 0)] - max(mu, 0), X ~ N(mu, sigma), by quadrature."""
    mean, _ = integrate.quad(lambda x: x * norm.pdf(x, mu, sigma), 0.0, mu + 12 * sigma)
    return mean - max(mu, 0.0)


@pytest.mark.parametrize("mu", [-0.03, -0.01, 0.0, 0.004, 0.01, 0.05])
def test_the_clip_excess_is_the_normal_expectation(mu: float) -> None:
    sigma = 0.01
    got = clip_excess(np.array([mu]), np.array([sigma]))[0]
    assert got == pytest.approx(_expected_excess(mu, sigma), rel=1e-6, abs=1e-12)
    assert clip_excess(np.array([mu]), np.array([0.0]))[0] == 0.0  # no noise: nothing added


@pytest.mark.parametrize(("step", "cells"), [(0.1, 100), (0.04, 250), (0.02, 300), (0.01, 600)])
def test_the_smooth_sigma_is_the_smoothings_own_at_every_step(step: float, cells: int) -> None:
    """The same information density (noise per unit area) at every grid step gives the same
    sigma of the smooth part, and it is what the smoothing leaves of white noise of that
    density: its impulse response's squared weights times the cell's variance (within 15 %:
    the noise model reads it on 5 cm blocks, the kernel's width rounds to whole cells)."""
    grid = _grid(step, cells)
    density = 1.0 / (STEP**2 * SIGMA_CELL_M**2)  # 1 cm of noise a 4 cm cell
    per_cell = 1.0 / math.sqrt(grid.cell_area * density)
    impulse = np.zeros(grid.shape)
    impulse[cells // 2, cells // 2] = 1.0
    weights = _smooth_noise(grid, impulse)
    truth = per_cell * math.sqrt(float(np.sum(weights**2)))
    model = smooth_sigma(grid, np.full(grid.shape, density), np.ones(grid.shape, bool), SCALE_M)
    assert model[cells // 2, cells // 2] == pytest.approx(truth, rel=0.15)
    assert model[cells // 2, cells // 2] == pytest.approx(0.5e-3, rel=0.15)  # any step
    # at the region's edge the kernel is cut in half: the half's squared weights over the
    # square of its sum, about twice the variance
    half = weights[cells // 2 :]
    truth = per_cell * math.sqrt(float(np.sum(half**2)) / float(np.sum(half)) ** 2)
    assert model[0, cells // 2] == pytest.approx(truth, rel=0.15)


def _lmin_mean(ratio: float) -> float:
    """E[max(max(s, 0) - excess(s), min(s, 0))] for s ~ N(0, 1): what the corrected clip
    counts a cell on a floor at the base, the excess E[max(X, 0)] - max(s, 0) read with
    X ~ N(s, ratio) (a sigma `ratio` x the truth); both expectations as sums over a fine grid
    of the normal density."""
    s = np.linspace(-8.0, 8.0, 1601)[:, None]
    x = s + ratio * np.linspace(-10.0, 10.0, 2001)[None, :]
    weight = norm.pdf(x, s, ratio)
    excess = np.trapezoid(np.maximum(x, 0.0) * weight, x, axis=1) - np.maximum(s[:, 0], 0.0)
    counted = np.maximum(np.maximum(s[:, 0], 0.0) - excess, np.minimum(s[:, 0], 0.0))
    return float(np.trapezoid(counted * norm.pdf(s[:, 0]), s[:, 0]))


@pytest.mark.parametrize(("scale", "ratio"), [(1.0, 1.0), (0.16, 2.5), (1e-4, 100.0), (1e4, 0.01)])
def test_a_noisy_bare_floor_at_the_base(scale: float, ratio: float) -> None:
    """The volume of a flat floor at the base with noise: the clip at the base counts
    0.4 sigma a cell; corrected with the right information, 0.28 sigma; with information
    claiming noise 2.5x the truth (a depth noise factor 2.5x too high), ~0; 100x, down to the
    bound -0.4 sigma (every cell at min(smooth, 0)); far too little noise, the clip itself."""
    grid = _grid()
    heights = _noisy(np.full(grid.shape, FLOOR_Z))
    area = CELLS * CELLS * grid.cell_area
    sigma = _measured_sigma(grid, heights - FLOOR_Z)
    bias = sigma / math.sqrt(2 * math.pi) * area  # the clip's: E[max(s, 0)], s ~ N(0, sigma)
    # the signed sum's own noise (sigma_cell x sqrt(N) x cell area: 0.008 m^3) is common to
    # every estimate: each is compared with it
    signed = float(np.sum(heights - FLOOR_Z) * grid.cell_area)
    clipped = integrate_counted(grid, _counted(grid, heights, None))
    assert clipped - signed == pytest.approx(bias, rel=0.1)

    counted = _counted(grid, heights, _information(grid, scale))
    volume = integrate_counted(grid, counted)
    expected = _lmin_mean(ratio) * sigma * area
    assert volume - signed == pytest.approx(expected, abs=0.1 * bias)
    # never above the clip, never under min(smooth, 0) a cell, whatever the information says
    relative = heights - FLOOR_Z
    smooth = _smooth_noise(grid, relative)
    assert np.all(counted - (relative - smooth) >= np.minimum(smooth, 0.0) - 1e-12)
    assert volume <= clipped + 1e-9


def test_ground_truly_under_the_base_is_still_not_counted() -> None:
    """Half the floor 5 cm under the base (a pit, or a floor set 5 cm too high there): that half
    counts nothing, as the clip at the base counted; summed signed it would be -5 cm a cell."""
    grid = _grid()
    true = np.full(grid.shape, FLOOR_Z)
    true[:, CELLS // 2 :] -= 0.05
    heights = _noisy(true)
    counted = _counted(grid, heights, _information(grid))
    clipped = _counted(grid, heights, None)
    # off the step (1 m), the pit's cells count what the clip counts there: the detail only
    pit = np.s_[:, CELLS // 2 + 25 :]
    assert np.allclose(counted[pit], clipped[pit], atol=1e-9)
    signed = float(np.sum(heights - FLOOR_Z) * grid.cell_area)
    assert signed < -0.045 * CELLS * CELLS // 2 * grid.cell_area
    assert integrate_counted(grid, counted) == pytest.approx(
        integrate_counted(grid, clipped), abs=0.5 * abs(integrate_counted(grid, clipped))
    )


def test_a_fill_under_the_base_counts_nothing() -> None:
    """Filled cells carry no noise (information 0): a fill under the base, far from any
    measured cell, is clipped at the base as before."""
    grid = _grid()
    heights = _noisy(np.full(grid.shape, FLOOR_Z))
    information = _information(grid)
    filled = np.zeros(grid.shape, bool)
    filled[:, CELLS // 2 :] = True
    heights[filled] = FLOOR_Z - 0.002  # a membrane sagging 2 mm under the floor
    information[filled] = 0.0
    counted = _counted(grid, heights, information)
    far = np.s_[:, CELLS // 2 + 25 :]  # 1 m into the fill: the kernel reads fill only
    assert np.allclose(counted[far], 0.0, atol=1e-9)


def test_the_smooth_sigma_is_its_blocks_given_to_their_cells() -> None:
    """Computed on `_block_smooth`'s blocks and given back to the cells, the sigma is the same
    to the bit as the same arithmetic on every cell, on a grid that is no whole number of
    blocks and a region with holes."""
    rng = np.random.default_rng(5)
    grid = Grid(origin=(0.0, 0.0), step=0.01, shape=(233, 187), inside=np.ones((233, 187)))
    region = rng.random(grid.shape) < 0.8
    information = np.where(rng.random(grid.shape) < 0.5, rng.random(grid.shape) * 1e8, 0.0)
    got = smooth_sigma(grid, information, region, SCALE_M)
    # the former per-cell arithmetic: the blocks' means on every cell, then the sigma
    density = np.where(region, information, 0.0)
    both = np.stack([density, region.astype(np.float64)])
    density, share = ndimage.uniform_filter(both, 5, mode="constant", axes=(-2, -1))
    density = np.divide(density, share, out=np.zeros_like(density), where=share > 0)
    measured = region & (density > 1e-3 * float(density.max()))
    variance = np.divide(1.0 / 0.05**2, density, out=np.zeros(grid.shape), where=measured)
    coarse = _block_smooth([region.astype(np.float64), variance], SCALE_M / 0.01)
    weight, total = (np.repeat(np.repeat(c, 5, axis=0), 5, axis=1)[:233, :187] for c in coarse)
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = _kernel_share(SCALE_M / 0.05) * total / np.square(weight)
    expected = np.where(region & (weight > 1e-12), np.sqrt(np.maximum(spread, 0.0)), 0.0)
    np.testing.assert_array_equal(got, expected)
    assert np.all(got[~region] == 0.0) and np.any(got > 0)
