"""Volume, base plane and levels from a filled height map (paper 2.4, cut cells weighted)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from silo_agent.grid.filters import block_sums
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


CLIP_BLOCK_M = 0.05  # the noise model's blocks for the clip's correction (`smooth_sigma`)
CLIP_MIN_DENSITY = 1e-3  # ... a block with less than this x the densest's information: fill


def counted_heights(
    grid: Grid,
    heights: np.ndarray,
    base: np.ndarray,
    scale_m: float,
    information: np.ndarray | None = None,
) -> np.ndarray:
    """Per cell, the height above `base` that the volume counts; NaN where there is no surface.

    Clipping each noisy cell at the base turns zero-mean sensor noise on a bare floor into a
    positive volume (about 0.4 sigma per cell). Here the surface is split into a smooth part
    (about Gaussian, `scale_m`) and the detail; only the smooth part is clipped, the detail is
    summed signed: counted = max(smooth, 0) + (height - base - smooth). Real areas below the
    base survive smoothing and are still excluded; noise cancels.

    The smooth part keeps some noise, and its clip still counts some: with X ~ N(mu, sigma),
    E[max(X, 0)] - max(mu, 0) = sigma (phi(z) - |z| Phi(-|z|)), z = mu / sigma (0.4 sigma a
    cell on a floor at the base, nothing a few sigmas off it). With `information` (the cameras'
    noise model) that expected excess, read at mu = the smooth part and sigma = its noise
    (`smooth_sigma`), is taken off the clipped value; but never below min(smooth, 0): a cell
    above the base is taken down to the base at most, one under it to its own signed value.
    The noise model's scale is the configured depth noise factor, rarely measured on a site;
    that bound keeps a wrong one's damage within the clip's own bias: on a bare floor at the
    base a cell counts between E[min(smooth, 0)] = -0.4 sigma (the factor far too high) and
    the clip's +0.4 sigma (far too low). Ground well under the base (a pit, a floor set a
    few sigmas too high) is still counted nothing, a smooth part made only of fill (no noise)
    is clipped as before.

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
    information : ndarray, shape grid.shape, optional
        Per measured cell, the information density of its height (1 / (m^2 x m^2),
        reconstruct/trust.py `cell_information`), 0 on filled cells; None: no noise model, the
        smooth part is clipped at the base.

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
    kept = np.maximum(smooth, 0.0)
    if information is not None:
        sigma = smooth_sigma(grid, information, region, scale_m)
        kept = np.maximum(kept - clip_excess(smooth, sigma), np.minimum(smooth, 0.0))
    counted = kept + (relative - smooth)
    return np.where(region, counted, np.nan)


CLIP_EXCESS_MAX_Z = 8.0  # beyond this many sigmas of 0 the clip adds under 1e-16 sigma


def clip_excess(mu: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """E[max(X, 0)] - max(mu, 0) for X ~ N(mu, sigma): what clipping a noisy value at 0 adds
    on average, sigma (phi(z) - |z| Phi(-|z|)) with z = mu / sigma; 0 where sigma is 0 or
    z beyond CLIP_EXCESS_MAX_Z (most of a silo: grain metres above the base)."""
    mu, sigma = np.asarray(mu, dtype=np.float64), np.asarray(sigma, dtype=np.float64)
    near = np.flatnonzero(np.abs(mu) < CLIP_EXCESS_MAX_Z * sigma)
    z = np.abs(mu.ravel()[near]) / sigma.ravel()[near]
    excess = np.zeros(mu.shape)
    excess.ravel()[near] = sigma.ravel()[near] * (
        np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi) - z * ndtr(-z)
    )
    return excess


def smooth_sigma(
    grid: Grid, information: np.ndarray, region: np.ndarray, scale_m: float
) -> np.ndarray:
    """Per cell, the noise sigma of `masked_smooth`'s mean at `scale_m` over `region`, from the
    cameras' information density I (0 on filled cells).

    On a grid finer than CLIP_BLOCK_M most cells hold no point (at 1 cm a pixel seen from 3 m
    covers several), so the density is read on blocks of about that side b (a sliding mean
    over the block's cells in the region): a block's mean height has variance v = 1 / (b^2 I),
    and the filled cells of a measured block carry it; blocks under CLIP_MIN_DENSITY of the
    densest are fill, v = 0. The mean's
    variance is then share x (kernel-weighted mean of v) / (kernel weight on the region)^2,
    share (`_kernel_share`) the kernel's sum of squared weights at scale_m / b: exact for v
    even over the kernel, and where the region cuts it symmetrically (half a kernel at an edge
    doubles it). The same figure at every grid step."""
    factor = max(1, round(CLIP_BLOCK_M / grid.step))
    side = factor * grid.step
    inside = region.astype(np.float64)
    density = np.where(region, information, 0.0)
    if factor > 1:  # over the block's cells in the region
        both = np.stack([density, inside])
        density, share = ndimage.uniform_filter(both, factor, mode="constant", axes=(-2, -1))
        density = np.divide(density, share, out=np.zeros_like(density), where=share > 0)
    measured = region & (density > CLIP_MIN_DENSITY * float(density.max(initial=0.0)))
    variance = np.divide(1.0 / (side * side), density, out=np.zeros(region.shape), where=measured)
    sigma_cells = max(scale_m / grid.step, 1.0)
    weight, total = _block_smooth([inside, variance], sigma_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = _kernel_share(scale_m / side) * total / np.square(weight)
    sigma = np.where(weight > 1e-12, np.sqrt(np.maximum(spread, 0.0)), 0.0)
    return np.where(region, _block_cells(sigma, _smooth_block(sigma_cells), region.shape), 0.0)


def _smooth_block(sigma_cells: float) -> int:
    """`_block_smooth`'s block side in cells: a quarter of the scale."""
    return max(1, int(sigma_cells // 4))


def _block_smooth(layers: list[np.ndarray], sigma_cells: float) -> list[np.ndarray]:
    """Each layer's kernel-weighted mean: `masked_smooth`'s two box passes (about a Gaussian of
    `sigma_cells`), zero outside the grid. On blocks of a quarter of the scale (the kernel
    still 4+ blocks wide; noise levels change over it): the blocks' means (in float64), which
    `_block_cells` gives back to their cells once whatever is computed from them is (on a
    1 cm grid they cost a 25th or less)."""
    block = _smooth_block(sigma_cells)
    coarse = np.stack([block_sums(layer, block) for layer in layers]).astype(np.float32)
    size = max(3, 2 * round(sigma_cells / block * np.sqrt(6) / 2) + 1)
    for _ in range(2):
        coarse = ndimage.uniform_filter(coarse, size, mode="constant", axes=(-2, -1))
    return list((coarse / block**2).astype(np.float64))


def _block_cells(values: np.ndarray, block: int, shape: tuple[int, ...]) -> np.ndarray:
    """Each block's value at each of its cells, on a grid of `shape`."""
    blocks_r, blocks_c = values.shape
    cells = np.broadcast_to(values[:, None, :, None], (blocks_r, block, blocks_c, block))
    return cells.reshape(blocks_r * block, blocks_c * block)[: shape[0], : shape[1]]


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


LEVEL_SCALE_M = 0.4  # without a noise model: where a bin's highest and lowest grain are looked for
LEVEL_FIT_RADIUS_M = 1.0  # ... and the radius of the cone fitted there
LEVEL_WALL_BAND_M = 0.3  # ... but not this close to a bin's wall
LEVEL_CONE_MIN_SLOPE = 0.3  # a fitted slope under this (17 deg) is no heap or crater (below)
GRAIN_MIN_DEPTH_M = 0.10  # grain, for a bin's levels: this deep, smoothed at LEVEL_SCALE_M
LEVEL_SIGMA_M = 0.015  # a level is read where the surface is known to this (1 sigma) ...
LEVEL_SCALES_M = (0.15, 0.3, 0.6, 1.2, 2.4)  # ... averaged over the widest of these that
LEVEL_AGREE_SIGMAS = 3.0  # agrees with every finer one within this many of its sigmas
LEVEL_CONE_SIGMAS = 3.0  # a fitted cone's slope must stand this many sigmas clear of flat
LEVEL_CONE_MIN_SHARE = 0.7  # ... on a disc of which this share holds measured grain
LEVEL_CONE_MAX_TILT = 0.5  # ... and fall all round: a one-sided tilt under half the slope
LEVEL_CONE_RADIUS_M = 1.5  # with a noise model, a cone's tip is fitted this far round it
LEVEL_CONE_MAX_RADIUS_M = 6.0  # ... or on discs twice, four times as wide while they agree
LEVEL_CELL_GAP_M = 0.05  # ... a disc's share counting cells this close between measured ones
LEVEL_MIN_KNOWN_SHARE = 0.5  # read so if this share of the grain is known to LEVEL_SIGMA_M
LEVEL_GRID_M = 0.05  # on a finer grid levels are read on blocks of about this size
LEVEL_CONTACT_SIGMA_M = 0.025  # grain meeting bare steel: its height there read if known to this
LEVEL_CONTACT_ITERATIONS = 10  # ... the cells its fitted plane stands over, settled this often


def _kernel_share(sigma_cells: float) -> float:
    """Sum of the squared weights of `masked_smooth`'s kernel (two box passes) at this sigma,
    in 2-D: a mean over it of independent cells keeps this share of their variance."""
    size = max(3, 2 * round(sigma_cells * np.sqrt(6) / 2) + 1)
    line = np.convolve(np.ones(size), np.ones(size)) / size**2
    return float(np.sum(line**2)) ** 2


def level_surface(
    grid: Grid, heights: np.ndarray, measured: np.ndarray, information: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measured surface averaged, per cell, over the widest of LEVEL_SCALES_M that still
    agrees with every finer one (Lepski's rule: each finer mean, within LEVEL_AGREE_SIGMAS of
    its own noise), and that mean's sigma (inf where not measured).

    `information` (reconstruct/trust.py) weighs the cells: a camera's points count by the
    inverse of their noise, so a cell seen from 5 m and from 10 m reads mostly the near one.
    Filled cells count nothing: a level is read on what the cameras measured. A wider mean
    has less noise but rounds a heap's apex or a crater's bottom off; the rule stops widening
    where that rounding starts to show over the noise. On flat grain across a 10 m bin it
    reaches 1.2-2.4 m; on a heap's flank under 5 m of range it stays at 0.15-0.3 m. Third,
    the cells known to LEVEL_SIGMA_M at some scale: where a level may be read at all."""
    region = grid.inside > 0
    weight = np.where(measured & np.isfinite(heights), information, 0.0)
    weighted = np.where(weight > 0, weight * np.nan_to_num(heights), 0.0)
    surface = np.full(grid.shape, np.nan)
    sigma = np.full(grid.shape, np.inf)
    agrees = measured.copy()
    known = np.zeros(grid.shape, dtype=bool)
    # every finer mean's band (mean -+ LEVEL_AGREE_SIGMAS sigma), intersected
    lower = np.full(grid.shape, -np.inf)
    upper = np.full(grid.shape, np.inf)
    for scale_m in LEVEL_SCALES_M:
        cells = max(scale_m / grid.step, 1.0)
        mean_weight = masked_smooth(weight, region, cells)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = masked_smooth(weighted, region, cells) / mean_weight
            spread = np.sqrt(_kernel_share(cells) / (grid.cell_area * mean_weight))
        mean = np.where(measured, mean, np.nan)
        spread = np.where(np.isfinite(mean) & (mean_weight > 0), spread, np.inf)
        with np.errstate(invalid="ignore"):
            agrees &= np.isfinite(mean) & (mean >= lower) & (mean <= upper)
            lower = np.maximum(lower, mean - LEVEL_AGREE_SIGMAS * spread)
            upper = np.minimum(upper, mean + LEVEL_AGREE_SIGMAS * spread)
        surface = np.where(agrees, mean, surface)
        sigma = np.where(agrees, spread, sigma)
        known |= measured & (spread <= LEVEL_SIGMA_M)
    return surface, sigma, known


def _weighted_fit(
    design: np.ndarray, weight: np.ndarray, heights: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """Weighted least squares of `heights` on `design` (`weight` each cell's inverse
    variance): the coefficients and their covariance; None if the fit is singular."""
    try:
        covariance = np.linalg.inv(design.T @ (design * weight[:, None]))
    except np.linalg.LinAlgError:
        return None
    return covariance @ (design.T @ (weight * heights)), covariance


def _cone_fit(
    design: np.ndarray, weight: np.ndarray, heights: np.ndarray
) -> tuple[np.ndarray, float, float] | None:
    """`_weighted_fit` of a cone (`design`'s second column the distance from the tip): the
    coefficients, and how steep the fitted slope must be to stand clear of flat
    (LEVEL_CONE_MIN_SLOPE, and LEVEL_CONE_SIGMAS of its own noise), and the sigma of the tip
    (the first coefficient); None if the fit is singular.

    Grain heaps and craters stand at the angle of repose (23-35 deg, REPOSE_DEG): a slope under
    17 deg is a rounded crease where a heap meets flat grain, or a dip of noise blobs, and its
    tip no level (at 8.5 deg an 18 m bin's ring 1 m outside its heap read a 0.19 m deep
    "crater", the averaged surface there -0.03 m)."""
    fit = _weighted_fit(design, weight, heights)
    if fit is None:
        return None
    coefficients, covariance = fit
    clear = max(LEVEL_CONE_MIN_SLOPE, LEVEL_CONE_SIGMAS * float(np.sqrt(covariance[1, 1])))
    return coefficients, clear, float(np.sqrt(covariance[0, 0]))


def _cone_or_mean(
    grid: Grid,
    heights: np.ndarray,
    cells: np.ndarray,
    information: np.ndarray,
    at: tuple[int, int],
    mean: float,
    rises: bool,
) -> float:
    """The height at cell `at` of a cone h = a + b * distance fitted to the `cells` round it
    (weighted by their information), if it is one: its slope rises away from `at` (a
    crater's bottom, `rises`) or falls (a heap's apex) by more than LEVEL_CONE_SIGMAS of its
    own noise and LEVEL_CONE_MIN_SLOPE, on a disc mostly measured (not cut by the wall band
    or the edge of what was seen), and its tip lies beyond `mean`, the surface averaged there
    (averaging rounds a tip off, never sharpens it); else `mean`.

    The disc is LEVEL_CONE_RADIUS_M, widened (doubling) while the wider cone is still one
    and its tip agrees with every narrower tip within LEVEL_AGREE_SIGMAS of that tip's own
    noise (Lepski's rule, as `level_surface`'s): a tip is an extrapolation, and from 10-13 m
    (an 18 m bin's apex seen from the eaves) a 1.5 m disc's tip is known to ~6 cm, a 6 m
    disc's to ~2 cm; where the flank stops being a cone the wider tip departs and the rule
    stops."""
    tip = _widened_tip(
        lambda radius: _cone_tip(grid, heights, cells, information, at, radius, rises)
    )
    if tip is None:
        return mean
    beyond = tip <= mean if rises else tip >= mean
    return float(tip) if beyond else mean


def _widened_tip(tip_at: Callable[[float], tuple[float, float] | None]) -> float | None:
    """The tip of the widest disc (LEVEL_CONE_RADIUS_M, doubling to LEVEL_CONE_MAX_RADIUS_M)
    whose fit `tip_at(radius)` (tip and sigma, None if no cone) is still a cone and agrees
    with every narrower tip within LEVEL_AGREE_SIGMAS of that tip's sigma (Lepski's rule);
    None if the first disc's is no cone."""
    tip = None
    lower, upper = -np.inf, np.inf  # every narrower tip's band, intersected
    radius = LEVEL_CONE_RADIUS_M
    while radius <= LEVEL_CONE_MAX_RADIUS_M:
        fitted = tip_at(radius)
        if fitted is None or not lower <= fitted[0] <= upper:
            break
        tip = fitted[0]
        lower = max(lower, tip - LEVEL_AGREE_SIGMAS * fitted[1])
        upper = min(upper, tip + LEVEL_AGREE_SIGMAS * fitted[1])
        radius *= 2
    return tip


def _cone_tip(
    grid: Grid,
    heights: np.ndarray,
    cells: np.ndarray,
    information: np.ndarray,
    at: tuple[int, int],
    radius_m: float,
    rises: bool,
) -> tuple[float, float] | None:
    """The tip at cell `at` of the cone fitted to the `cells` within `radius_m`, and its
    sigma, if it is a cone (`_cone_or_mean`'s tests); else None."""
    rows, cols, (row, col) = _window(grid, at, radius_m)
    xs, ys = _centres(grid, rows, cols)
    heights, cells, information = heights[rows, cols], cells[rows, cols], information[rows, cols]
    distance = np.hypot(xs - xs[row, col], ys - ys[row, col])
    disc = (grid.inside[rows, cols] > 0) & (distance <= radius_m)
    near = cells & disc & (information > 0)
    # on a fine grid at long range a pixel covers several cells: cells between measured ones
    # count as measured for the share (not for the fit)
    gap = max(0, round(LEVEL_CELL_GAP_M / grid.step) - 1)
    covered = ndimage.maximum_filter(cells, size=2 * gap + 1) if gap else cells
    if near.sum() < 3 or (covered & disc).sum() < LEVEL_CONE_MIN_SHARE * disc.sum():
        return None
    weight = information[near] * grid.cell_area  # inverse variance of each cell
    bearing = np.arctan2(ys - ys[row, col], xs - xs[row, col])[near]
    d = distance[near]
    design = np.column_stack([np.ones(len(d)), d, d * np.cos(bearing), d * np.sin(bearing)])
    fit = _cone_fit(design, weight, heights[near])
    if fit is None:
        return None
    (tip, slope, tilt_x, tilt_y), clear, tip_sigma = fit
    # a cone falls (or rises) alike all round: a rim or a slope falls on one side only
    round_ = np.hypot(tilt_x, tilt_y) < LEVEL_CONE_MAX_TILT * abs(slope)
    cone = (slope > clear if rises else slope < -clear) and round_
    return (float(tip), tip_sigma) if cone else None


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
    information: np.ndarray | None = None,
    wall_distance: np.ndarray | None = None,
    bottom: np.ndarray | None = None,
) -> Levels:
    """A bin's min, mean and max grain level, over the cells where grain stands (bare floor or
    hopper steel is not grain); `bottom`, the bin's steel under each cell, lets a highest point
    where the grain meets bare steel be read on that contact (`_to_contact`).

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
    weights = grid.inside[grain]
    mean = float(np.sum(heights[grain] * weights) / np.sum(weights))
    if information is not None:
        level_grid, level_heights, level_measured, level_information, level_wall = _level_grid(
            grid, heights, measured, information, wall_distance
        )
        steel = None
        if bottom is not None:
            # every measured cell off the wall, grain or bare steel, on the same blocks
            _, all_heights, all_measured, all_information, _ = _level_grid(
                grid, heights, region & observed & off_wall, information, None
            )
            factor = _level_factor(grid)
            steel = _Steel(
                all_heights,
                all_measured,
                all_information,
                _block_mean(bottom, factor) if factor >= 2 else bottom,
            )
        levels = _trusted_levels(
            level_grid, level_heights, level_measured, level_information, mean, level_wall, steel
        )
        if levels is not None:
            return levels
    smooth = masked_smooth(heights, region, scale)
    ranked = np.where(measured & np.isfinite(smooth), smooth, np.nan)
    top = np.unravel_index(int(np.nanargmax(ranked)), ranked.shape)
    low = np.unravel_index(int(np.nanargmin(ranked)), ranked.shape)
    return Levels(
        _fitted_peak(grid, heights, measured, (int(low[0]), int(low[1])), LEVEL_FIT_RADIUS_M),
        mean,
        _fitted_peak(grid, heights, measured, (int(top[0]), int(top[1])), LEVEL_FIT_RADIUS_M),
    )


def _trusted_levels(
    grid: Grid,
    heights: np.ndarray,
    measured: np.ndarray,
    information: np.ndarray,
    mean: float,
    wall_distance: np.ndarray | None,
    steel: _Steel | None = None,
) -> Levels | None:
    """`grain_levels` with a noise model: the extremes of `level_surface` over the cells where
    it is known to LEVEL_SIGMA_M, each read as a cone if one is there (`_cone_or_mean`) or
    carried on to the wall if it lies by the wall band on a slope down to it (`_to_wall`),
    the highest on to where the grain meets bare steel if it lies by some (`_to_contact`);
    None if less than LEVEL_MIN_KNOWN_SHARE of the measured grain is known that well."""
    surface, sigma, known = level_surface(grid, heights, measured, information)
    trusted = known & np.isfinite(surface)
    if trusted.sum() < LEVEL_MIN_KNOWN_SHARE * measured.sum():
        return None  # a sparse view (one camera, a small image): the cameras pin down little
    # located on one smoothing for all cells (an adaptive one would rank a crater's bottom,
    # averaged wider, above its flanks), read on the adaptive one
    located = masked_smooth(heights, measured, max(LEVEL_SCALE_M / grid.step, 1.0))
    ranked = np.where(trusted & np.isfinite(located), located, np.nan)
    if not np.any(np.isfinite(ranked)):
        return None
    top = np.unravel_index(int(np.nanargmax(ranked)), ranked.shape)
    low = np.unravel_index(int(np.nanargmin(ranked)), ranked.shape)
    top_at, low_at = (int(top[0]), int(top[1])), (int(low[0]), int(low[1]))
    lowest = _cone_or_mean(grid, heights, measured, information, low_at, float(surface[low]), True)
    highest = _cone_or_mean(
        grid, heights, measured, information, top_at, float(surface[top]), False
    )
    if wall_distance is not None:
        lowest = _to_wall(grid, heights, measured, information, low_at, lowest, True, wall_distance)
        highest = _to_wall(
            grid, heights, measured, information, top_at, highest, False, wall_distance
        )
    if lowest == float(surface[low]):  # no crater's tip, no cone at the wall: flat grain
        lowest = _flat_level(heights, measured, information, trusted, surface, sigma, low_at)
    if steel is not None:
        highest = _to_contact(grid, steel, measured, top_at, highest)
    return Levels(lowest, mean, highest)


def _flat_level(
    heights: np.ndarray,
    measured: np.ndarray,
    information: np.ndarray,
    trusted: np.ndarray,
    surface: np.ndarray,
    sigma: np.ndarray,
    at: tuple[int, int],
) -> float:
    """The level of the flat grain an extreme was found on (no cone's tip, no cone at the
    wall): the information-weighted mean of the measured heights of every trusted cell whose
    averaged surface agrees with the one at `at` within LEVEL_AGREE_SIGMAS of their
    difference's sigma.

    Read at `at` alone the level is one averaged mean, and a biased one there: the extreme is
    located where the 0.4 m surface dips or bumps most, the noisiest grain (an 18 m bin's
    corners between its eave cameras, seen from 15-18 m), where the mean widens to 1.2 m and
    its weights lean toward the better-seen grain, up the heap's foot (the flat ring of an
    18 m bin read +6 cm on average). Over all the grain at that level each cell counts only
    its own height, cells a heap or a crater's flank lifts off it by more than the noise are
    left out, and the noise of thousands of cells averages out."""
    with np.errstate(invalid="ignore"):
        spread = np.hypot(sigma, sigma[at])
        level = trusted & measured & (information > 0)
        level &= np.abs(surface - surface[at]) <= LEVEL_AGREE_SIGMAS * spread
    if not np.any(level):
        return float(surface[at])
    weight = information[level]
    return float(np.sum(weight * heights[level]) / np.sum(weight))


@dataclass(frozen=True)
class _Steel:
    """On the grid levels are read on: every measured cell off the wall band, grain or bare
    steel (heights, mask, information), and the bin's steel (floor or hopper) under each."""

    heights: np.ndarray
    measured: np.ndarray
    information: np.ndarray
    bottom: np.ndarray


def _to_contact(
    grid: Grid, steel: _Steel, grain: np.ndarray, at: tuple[int, int], value: float
) -> float:
    """The highest grain of a hopper drawn down into its cone lies where the grain meets the
    bare steel rising above it. Read there it reads low: the grain's edge ends short of the
    contact (where it is thinner than noise), and averaged there only the grain side counts
    (8-12 cm at 1280x720). So if the measured cells within LEVEL_CONE_RADIUS_M of `at` hold
    bare steel (not `grain`), a plane h = a + p n + q t is fitted (information-weighted) to those
    it stands above the steel on (the grain's cells to start, settled a few times: cells are
    not picked by their own noise), n running across the steel's contour lines (the steel's
    height over its slope: from the axis of a conical hopper, so a crater's cone is a plane
    in it) and t along them; where it meets the steel, if the steel rises faster than the
    grain and that height is known to LEVEL_CONTACT_SIGMA_M (the lever to the contact doubles
    the plane's noise), is the level if above `value`."""
    rows, cols, (row, col) = _window(grid, at, LEVEL_CONE_RADIUS_M)
    bottom = steel.bottom[rows, cols]
    if min(bottom.shape) < 2:
        return value
    slope_y, slope_x = (float(g[row, col]) for g in np.gradient(bottom, grid.step))
    rise = float(np.hypot(slope_x, slope_y))
    if not rise > LEVEL_CONE_MIN_SLOPE:  # a flat floor: no contour to cross
        return value
    xs, ys = _centres(grid, rows, cols)
    heights, information = steel.heights[rows, cols], steel.information[rows, cols]
    dx, dy = xs - xs[row, col], ys - ys[row, col]
    disc = steel.measured[rows, cols] & (np.hypot(dx, dy) <= LEVEL_CONE_RADIUS_M)
    disc &= information > 0
    grain = grain[rows, cols] & disc
    if not np.any(disc & ~grain):
        return value  # grain all round: no contact here
    across = (bottom - bottom[row, col]) / rise
    along = (dy * slope_x - dx * slope_y) / rise
    on = grain
    for _ in range(LEVEL_CONTACT_ITERATIONS):
        if on.sum() < 3:
            return value
        design = np.column_stack([np.ones(int(on.sum())), across[on], along[on]])
        fit = _weighted_fit(design, information[on] * grid.cell_area, heights[on])
        if fit is None:
            return value
        (a, p, q), covariance = fit
        above = disc & (a + p * across + q * along > bottom)
        if np.array_equal(above, on):
            break
        on = above
    if not p < rise:
        return value  # the grain rises as fast as the steel: they do not meet outward
    reach = (a - bottom[row, col]) / (rise - p)  # across, from `at` to the contact
    if abs(reach) > LEVEL_CONE_RADIUS_M:
        return value
    lever = rise / (rise - p)
    variance = covariance[0, 0] + reach * reach * covariance[1, 1] + 2 * reach * covariance[0, 1]
    if not lever * np.sqrt(max(variance, 0.0)) <= LEVEL_CONTACT_SIGMA_M:
        return value
    return max(value, float(a + p * reach))


def _to_wall(
    grid: Grid,
    heights: np.ndarray,
    cells: np.ndarray,
    information: np.ndarray,
    at: tuple[int, int],
    value: float,
    rises: bool,
    wall_distance: np.ndarray,
) -> float:
    """An extreme found by the wall band may lie at the wall itself: a side-draw's cone is
    drawn down to its outlet in the wall, grain blown against the wall stands highest there.
    The band's own cells are not read (from 8-10 m the far wall's grain reads 3-5 cm low
    there), so a cone h = a + b * distance is fitted (weighted by information) to the `cells`
    within LEVEL_CONE_RADIUS_M of the wall point nearest `at`, its tip on the wall; if it rises
    away from the wall (a lowest point, `rises`) or falls (a highest) by LEVEL_CONE_SIGMAS of
    its own noise and LEVEL_CONE_MIN_SLOPE, its tip is the level, if beyond `value`.

    The disc is widened (doubling, to LEVEL_CONE_MAX_RADIUS_M) while the wider cone is still
    one and its tip agrees with every narrower tip, as `_cone_or_mean`'s: half a 1.5 m disc,
    seen from 8-10 m, knows the tip to 5-10 cm (a side-draw's outlet in a 10 m bin, four eave
    cameras, read -0.10 to +0.05 m off over seeds 2-9)."""
    reach = float(wall_distance[at])
    if not np.isfinite(reach) or reach > LEVEL_WALL_BAND_M + 2 * grid.step:
        return value
    tip = _widened_tip(
        lambda radius: _wall_tip(
            grid, heights, cells, information, at, radius, rises, wall_distance
        )
    )
    if tip is None:
        return value
    return min(value, tip) if rises else max(value, tip)


def _wall_tip(
    grid: Grid,
    heights: np.ndarray,
    cells: np.ndarray,
    information: np.ndarray,
    at: tuple[int, int],
    radius_m: float,
    rises: bool,
    wall_distance: np.ndarray,
) -> tuple[float, float] | None:
    """The tip on the wall of the cone fitted to the `cells` within `radius_m` of the wall
    point nearest `at`, and its sigma, if it is a cone (`_to_wall`'s test); else None."""
    reach = float(wall_distance[at])
    rows, cols, (row, col) = _window(grid, at, radius_m + reach)
    local = wall_distance[rows, cols]
    if min(local.shape) < 2:
        return None
    inward_y, inward_x = (float(g[row, col]) for g in np.gradient(local, grid.step))
    norm = float(np.hypot(inward_x, inward_y))
    if not norm > 0:
        return None
    xs, ys = _centres(grid, rows, cols)
    heights, cells, information = heights[rows, cols], cells[rows, cols], information[rows, cols]
    foot_x = xs[row, col] - inward_x / norm * reach
    foot_y = ys[row, col] - inward_y / norm * reach
    distance = np.hypot(xs - foot_x, ys - foot_y)
    near = cells & (distance <= radius_m) & (information > 0)
    if near.sum() < 3:
        return None
    weight = information[near] * grid.cell_area
    design = np.column_stack([np.ones(int(near.sum())), distance[near]])
    fit = _cone_fit(design, weight, heights[near])
    if fit is None:
        return None
    (tip, slope), clear, tip_sigma = fit
    cone = slope > clear if rises else slope < -clear
    return (float(tip), tip_sigma) if cone else None


def _window(
    grid: Grid, at: tuple[int, int], radius_m: float
) -> tuple[slice, slice, tuple[int, int]]:
    """The rows and columns of the grid within `radius_m` of cell `at` (a square), and `at`
    inside them: a cone's fit reads a few thousand cells, not the grid's millions."""
    reach = int(np.ceil(radius_m / grid.step)) + 1
    row, col = at
    top, left = max(row - reach, 0), max(col - reach, 0)
    return slice(top, row + reach + 1), slice(left, col + reach + 1), (row - top, col - left)


def _centres(grid: Grid, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray]:
    """`grid.centres()` of a window."""
    n_rows, n_cols = grid.shape
    xs = grid.origin[0] + (np.arange(n_cols)[cols] + 0.5) * grid.step
    ys = grid.origin[1] + (np.arange(n_rows)[rows] + 0.5) * grid.step
    return np.meshgrid(xs, ys)


def _level_grid(
    grid: Grid,
    heights: np.ndarray,
    measured: np.ndarray,
    information: np.ndarray,
    wall_distance: np.ndarray | None,
) -> tuple[Grid, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The grid, heights, measured cells, information and wall distance levels are read on:
    a grid finer than LEVEL_GRID_M in blocks of about that size (heights information-weighted,
    information and wall distance averaged, a block measured if a cell of it is). Levels
    average over 0.15 m and more anyway; at 1 cm a pixel seen from 10 m covers several cells,
    most cells hold no point, and ten smoothings of millions of cells cost seconds."""
    factor = _level_factor(grid)
    if factor < 2:
        return grid, heights, measured, information, wall_distance

    weight = np.where(measured & np.isfinite(heights), information, 0.0)
    block_weight = _block_mean(weight, factor)
    with np.errstate(invalid="ignore", divide="ignore"):
        block_heights = _block_mean(weight * np.nan_to_num(heights), factor) / block_weight
    inside = _block_mean(grid.inside, factor)
    coarse = Grid(grid.origin, grid.step * factor, inside.shape, inside)
    block_wall = None
    if wall_distance is not None:
        block_wall = _block_mean(np.nan_to_num(wall_distance, nan=np.inf, posinf=1e9), factor)
    return coarse, block_heights, block_weight > 0, block_weight, block_wall


def _level_factor(grid: Grid) -> int:
    """How many of the grid's cells a side make a block of about LEVEL_GRID_M (under 2: the
    grid itself is read)."""
    return round(LEVEL_GRID_M / grid.step)


def _block_mean(values: np.ndarray, factor: int) -> np.ndarray:
    """`values` averaged over blocks of `factor` x `factor` cells (`_level_grid`'s blocks)."""
    return block_sums(values, factor) / (factor * factor)
