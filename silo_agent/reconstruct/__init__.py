"""BICM reconstruction: scan -> height map -> volume, mass, levels, coverage. Pure: no I/O.

fuse + crop -> voxel down-sample (optional) -> clustered means per cell -> fill of empty cells
(`reconstruction.fill`: by default the membrane held to the grain's angle of repose, and the
plain membrane in a bin; or the paper's B-spline, on request) -> slope
correction -> integration over the region (cut cells weighted).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from silo_agent.base.limits import MAX_GRID_CELLS
from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.grid.bin_shape import BinShape
from silo_agent.grid.filters import block_means, block_sums, dilate_cross
from silo_agent.grid.geometry import points_outside
from silo_agent.grid.grid import Grid
from silo_agent.grid.heightmap import HeightMap
from silo_agent.grid.smooth import masked_smooth
from silo_agent.grid.volume import (
    DENOISE_SCALE_M,
    LEVEL_WALL_BAND_M,
    Levels,
    base_plane,
    base_surface,
    counted_heights,
    grain_levels,
    integrate_counted,
    surface_levels,
)
from silo_agent.reconstruct.cells import (
    DOUBLE_SURFACE_SPREADS,
    EPS_MAX_M,
    CellTotals,
    clustered_means,
    height_segments,
    voxel_downsample,
)
from silo_agent.reconstruct.fill import bspline_fill, membrane_fill, repose_fill
from silo_agent.reconstruct.fuse import CellMoments, FusedCloud, fuse_and_crop
from silo_agent.reconstruct.residual import PairResidual, median, registration_residuals
from silo_agent.reconstruct.trust import blob_scale, cell_information, point_spread
from silo_agent.reconstruct.walls import (
    FirstSurface,
    WallCrossing,
    bare_bottom,
    reseat_level,
    reseated,
    wall_free,
    with_points,
)
from silo_agent.scan import CameraCloud, Scan, Site

if TYPE_CHECKING:  # the whole config's models: only `site_from_config` reads one
    from silo_agent.config import Config

__all__ = ["Reconstruction", "reconstruct", "site_from_config"]

EDGE_BAND_M = 0.10  # how far from a hole a sparse cell is suspect (see _trusted_cells)
EDGE_DENSITY_RATIO = 0.5
TRUST_BLOCK_M = 0.05  # ... judged on blocks this wide on the ground, at every grid step
TRUST_POINTS = 16  # ... or wider where a typical block holds fewer points than this
SPIKE_WIDTH_M = 0.10  # narrower raised features are not grain (see _without_spikes)
BIN_DENOISE_SCALE_M = 0.5  # bins: noise blobs of ~0.2 m at 8-10 m must not be clipped
BIN_EPS_MAX_M = 1.0  # a bin's grain is seen at up to ~10 m, with up to ~0.5 m of noise
WALL_PASS_STEP_M = 0.10  # grid of the first pass that finds the grain height at the wall
WALL_PASS_POINTS_PER_CELL = 64  # ... on about this many points a cell (_thinned)
WALL_BAND_M = 0.3  # a bin's cells this close to the wall are filled, not measured (_wall_band)
SAMPLING_GAP_SHARE = 1 / 3  # ... of the cells its points would fill measured (_sampling_gaps)
BIN_ANALYSIS_STEP_M = 0.05  # a bin is reconstructed on cells no wider (_analysis_blocks)
UNDER_BASE_M = 0.10  # a measured surface this far under its floor (median): a setup error


@dataclass
class Reconstruction:
    """Everything a scan's reconstruction says; `analysis.scan_analysis` adds detection's finds
    and `analysis.summary` makes the published summary of both."""

    scan_id: str
    method: str
    grid_step_m: float
    volume_m3: float | None
    mass_t: float | None
    coverage: float
    surface: Levels | None  # silo-frame z
    floor_z: float
    valid: bool
    invalid_reason: str | None
    heightmap: HeightMap | None
    cameras: list[str]
    points: dict[str, int] = field(default_factory=dict)
    parameters: dict[str, Any] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    registration: dict[str, PairResidual] = field(default_factory=dict)  # reconstruct/residual
    capacity_m3: float | None = None  # a bin's: bottom to eave over the region
    reference_z: float | None = None  # a bin's headspace reference: eave or roof peak
    # a bin's first pass only: the level its points are reseated on (walls.reseat_level)
    reseat_level: np.ndarray | None = field(default=None, repr=False)
    # how well each measured cell's height is known (reconstruct/trust.py, 1 / m^4; 0 where
    # filled), float32: pile detection and the collapse alarm read the map's noise from it
    information: np.ndarray | None = field(default=None, repr=False)

    def bin_figures(self) -> dict[str, float | None]:
        """Fill ratio and headspace (to the highest grain, to the mean surface) of a bin."""
        full = self.capacity_m3
        fill = self.volume_m3 / full if self.volume_m3 is not None and full else None
        top = mean = None
        if self.reference_z is not None and self.surface is not None:
            top, mean = self.reference_z - self.surface.max, self.reference_z - self.surface.mean
        return {
            "capacity_m3": full,
            "fill_ratio": fill,
            "headspace_m": top,
            "headspace_mean_m": mean,
        }

    def describe(self, findings: Sequence[str] = ()) -> str:
        """A few human-readable lines; `findings` (what detection found) go before the time."""
        lines = [f"scan      {self.scan_id}  ({self.method}, grid {self.grid_step_m * 100:g} cm)"]
        if self.volume_m3 is None:
            lines.append("volume    unknown")
        else:
            mass = f"   mass {self.mass_t:.3f} t" if self.mass_t is not None else ""
            lines.append(f"volume    {self.volume_m3:.4f} m³{mass}")
        lines.append(f"coverage  {self.coverage * 100:.1f} % of the region observed")
        if self.surface is not None:
            s, f = self.surface, self.floor_z
            lines.append(
                f"level     min {s.min - f:.3f}  mean {s.mean - f:.3f}  max {s.max - f:.3f}"
                " m above floor"
            )
        figures = self.bin_figures()
        if figures["capacity_m3"] is not None:
            fill, top = figures["fill_ratio"], figures["headspace_m"]
            lines.append(
                f"bin       capacity {figures['capacity_m3']:.1f} m³"
                + (f"   fill {fill * 100:.1f} %" if fill is not None else "")
                + (f"   headspace {top:.2f} m" if top is not None else "")
            )
        lines.append("valid     yes" if self.valid else f"valid     NO: {self.invalid_reason}")
        lines.extend(findings)
        total = sum(self.timings_s.values())
        lines.append(f"time      {total * 1000:.0f} ms  ({len(self.cameras)} camera(s))")
        return "\n".join(lines)


def site_from_config(config: Config) -> Site:
    s = config.silo
    return Site(
        region=s.region_polygon(),
        floor_z=s.floor_z,
        ceiling_z=s.ceiling_z,
        base=s.base,
        bulk_density_t_m3=s.bulk_density_t_m3,
        bin=s.bin_shape(),
    )


class _Clock:
    def __init__(self) -> None:
        self.laps: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self._last
        self._last = now


def _slope_corrected(
    grid: Grid, filled: np.ndarray, cells_x: np.ndarray, cells_y: np.ndarray, observed: np.ndarray
) -> np.ndarray:
    """Move each observed cell's mean from its points' centroid to the cell centre.

    A cell's points rarely sit evenly over it (cameras see the near part of a slope more
    densely); along the local slope that offset is a height bias, removed here. The slope is
    read on the 3 x 3 mean of the cells with a surface (the grid's edge cells repeated beyond
    it): outside a round region there is none, and a plain mean would carry that NaN along.
    """
    surface = np.isfinite(filled)
    stacked = np.empty((2, *filled.shape))
    stacked[0] = filled
    stacked[0][~surface] = 0.0
    stacked[1] = surface
    # in place, and the cell centres as a row and a column, not two grids: a 20 m bin at 1 cm
    # has 4 M cells, 32 MB a float64 grid, and this ran at the second pass's peak
    ndimage.uniform_filter(stacked, 3, output=stacked, mode="nearest", axes=(-2, -1))
    total, count = stacked
    rows, cols = grid.shape
    xs = grid.origin[0] + (np.arange(cols) + 0.5) * grid.step  # as grid.centres() has them
    ys = grid.origin[1] + (np.arange(rows) + 0.5) * grid.step
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN where no cell has a surface
        np.divide(total, count, out=total)
        grad_y, grad_x = np.gradient(total, grid.step)
        del stacked, total, count
        shift = np.subtract(xs[None, :], cells_x)
        shift *= grad_x
        del grad_x
        across = np.subtract(ys[:, None], cells_y)
        across *= grad_y
        shift += across
    del across, grad_y
    np.nan_to_num(shift, copy=False)
    shift += filled
    return np.where(observed, shift, filled)


def _trusted_cells(
    grid: Grid, observed: np.ndarray, counts: np.ndarray, sub_counts: np.ndarray | None = None
) -> np.ndarray:
    """Observed cells whose height can be trusted as a boundary value for the fill.

    At the edge of a camera's view or of a shadow, depth noise along the ray carries points
    past the edge into cells that see nothing else; those cells hold only the points pushed
    towards the camera and read high. They show as ground near a hole with far fewer points
    than the ground around it, and are left to the fill instead.

    How many points a place holds is judged on blocks of a fixed size on the ground, not on
    the grid's cells, so that the rule means the same at every grid step: TRUST_BLOCK_M, or
    wider if the scan's typical block of that size holds fewer than TRUST_POINTS points. On
    a fine grid a cell holds about one point and its count says nothing (a cell with none
    is no hole, one with fewer than its neighbours no edge: at 1 cm the rule dropped 15 % of
    bay-cone's cells by chance). A cell wider than a block (`sub_counts`: the points counted
    on cells 1/m as wide, `_sub_counts`) is dropped only when none of its sub-cells with
    points is trusted: a cell at the edge of a view that is partly seen holds real ground
    (at 10 cm dropping those cells grew cone A1A5's holes, +3.87 % against +2.9 % finer).
    """
    inside = grid.inside > 0
    m, seen = 1, observed
    if sub_counts is not None and sub_counts.shape[0] > grid.shape[0]:
        m = sub_counts.shape[0] // grid.shape[0]
        seen = np.repeat(np.repeat(observed, m, axis=0), m, axis=1) & (sub_counts > 0)
        inside = np.repeat(np.repeat(inside, m, axis=0), m, axis=1)
        counts = sub_counts
    step = grid.step / m

    def blocks(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points, area (cells inside) and whether seen, per block of k x k cells."""
        points = block_sums(counts.astype(np.float64), k)
        area = block_sums(inside.astype(np.float64), k)
        return points, area, block_sums(seen.astype(np.float64), k) > 0

    k = max(1, round(TRUST_BLOCK_M / step))
    points, area, seen_blocks = blocks(k)
    if np.any(seen_blocks):  # wider blocks if the typical one holds too few points to judge
        typical = median(points[seen_blocks] / area[seen_blocks])  # points a cell
        wide = round(np.sqrt(TRUST_POINTS / max(typical, 1e-12)))
        if wide > k:
            k = wide
            points, area, seen_blocks = blocks(k)
    band = max(1, round(EDGE_BAND_M / (k * step)))
    near_hole = dilate_cross(~seen_blocks & (area > 0), band)
    with np.errstate(invalid="ignore", divide="ignore"):
        density = points / area
    local = masked_smooth(density, seen_blocks, band / 2)
    suspect = near_hole & (density < EDGE_DENSITY_RATIO * np.nan_to_num(local))
    rows, cols = seen.shape
    suspect = np.repeat(np.repeat(suspect, k, axis=0), k, axis=1)[:rows, :cols]
    if m == 1:
        return observed & ~suspect
    return observed & (block_sums((seen & ~suspect).astype(np.int64), m) > 0)


def _sub_counts(grid: Grid, points: np.ndarray) -> np.ndarray | None:
    """Points counted on cells 1/m as wide as `grid`'s, m the smallest with cells no wider
    than TRUST_BLOCK_M (None if the grid's own are): what `_trusted_cells` judges a wide
    cell's points on."""
    m = int(np.ceil(grid.step / TRUST_BLOCK_M - 1e-9))
    if m <= 1:
        return None
    rows, cols = grid.shape[0] * m, grid.shape[1] * m
    inverse = m / grid.step
    col = np.clip(np.floor((points[:, 0] - grid.origin[0]) * inverse).astype(np.int64), 0, cols - 1)
    row = np.clip(np.floor((points[:, 1] - grid.origin[1]) * inverse).astype(np.int64), 0, rows - 1)
    return np.bincount(row * cols + col, minlength=rows * cols).reshape(rows, cols)


def _sampling_gaps(
    grid: Grid, observed: np.ndarray, points: np.ndarray, excluded: np.ndarray
) -> np.ndarray:
    """The empty cells of a surface the cameras sample more sparsely than the grid's cells, not
    holes they did not see: in the TRUST_BLOCK_M block round the cell at least
    SAMPLING_GAP_SHARE of the cells measured that its `points` (per measured cell) would
    fill if they fell at random (1 - exp(-points a cell)), and none `excluded` (the wall band,
    a hopper's bare cone). At 1 cm a crater seen from 9-10 m holds a point in half its cells,
    at 5 mm in one in three: a third of the cells, asked of every block, called those gaps
    holes at 5 mm (hopper-low, two cameras, 0.1 deg / 3 mm: +3.0 % against 0.0 % at 1 cm).
    By the bare cone an empty cell is its steel's (the fill there runs level with the grain
    below it)."""
    size = max(3, 2 * round(TRUST_BLOCK_M / grid.step / 2) + 1)
    share = ndimage.uniform_filter(observed.astype(np.float64), size, mode="constant")
    density = np.where(observed, points, 0).astype(np.float64)
    density = ndimage.uniform_filter(density, size, mode="constant")  # points a cell
    sampled = (share > 0) & (share >= SAMPLING_GAP_SHARE * -np.expm1(-density))
    beside = ndimage.maximum_filter(excluded, size, mode="constant")  # by the band or bare
    return ~observed & ~beside & (grid.inside > 0) & sampled


def _without_spikes(
    grid: Grid, filled: np.ndarray, observed: np.ndarray, tolerance: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Replace cells standing above a morphological opening of the surface by the opening.

    Grain cannot stand in a column narrower than SPIKE_WIDTH_M; cells that do are points of a
    wall or post carried into the region by depth noise, with no grain point beside them.
    """
    size = max(3, 2 * round(SPIKE_WIDTH_M / grid.step / 2) + 1)
    region = grid.inside > 0
    eroded = ndimage.minimum_filter(np.where(region, filled, np.inf), size)
    opened = ndimage.maximum_filter(np.where(region, eroded, -np.inf), size)
    spikes = region & (filled - opened > tolerance)
    return np.where(spikes, opened, filled), observed & ~spikes


class _BinCells:
    """A bin's wall distance and bottom height at the grid's cell centres, each computed at most
    once a reconstruction: the wall band, the base, the levels and the capacity read them, and
    each is a pass over the centres (4 M cells for a 20 m bin at 1 cm)."""

    def __init__(self, grid: Grid, shape: BinShape) -> None:
        self.grid, self.shape = grid, shape

    @functools.cached_property
    def wall_distance(self) -> np.ndarray:
        return self.shape.wall_distance(*self.grid.centres())

    @functools.cached_property
    def bottom(self) -> np.ndarray:
        return self.shape.bottom(*self.grid.centres())


def _wall_band(grid: Grid, bin_cells: _BinCells | None, observed: np.ndarray) -> np.ndarray:
    """A bin's cells within WALL_BAND_M of its wall (none without a bin, or if nothing else
    was measured): they are filled from the grain inside, not measured.

    Depth noise moves a point along its ray: at 8-10 m from an eave camera, 0.1-0.3 m across
    the floor. Away from the wall a cell loses as many points to its neighbours as it gains;
    by the far wall it gains the points noise pushed outward and down from nearer grain but
    none pushed inward from beyond the wall (those rays met the wall): the band reads low,
    by 5-15 cm at 9 m (bench/results/accuracy-round-bins.md), more than its share of the
    volume. The grain inside continues to the wall (the fill), held above a hopper's steel.
    """
    if bin_cells is None:
        return np.zeros(grid.shape, dtype=bool)
    band = (bin_cells.wall_distance < WALL_BAND_M) & (grid.inside > 0)
    return band if np.any(observed & ~band) else np.zeros(grid.shape, dtype=bool)


def _excluding(fused: FusedCloud, discs: Sequence[tuple[float, float, float]]) -> FusedCloud:
    """`fused` without the points inside any of the (x, y, radius) discs."""
    keep = points_outside(fused.points, discs)
    points, camera, cell = fused.points[keep], fused.camera[keep], fused.cell[keep]
    moments = CellMoments.of(points, camera, cell, fused.moments.n_cells, fused.moments.n_cams)
    return FusedCloud(points, camera, cell, fused.raw_count, moments)


def reconstruct(
    scan: Scan,
    settings: ReconstructionConfig,
    site: Site | None = None,
    exclude: Sequence[tuple[float, float, float]] = (),
    calibration: CalibrationConfig | None = None,
    release_points: bool = False,
) -> Reconstruction:
    """Run the configured method on `scan`; `site` overrides the scan's own site.

    `exclude` lists silo-frame discs (x, y, radius) whose points are not grain (a leveling
    robot found by the detector): they are dropped after fusing and the fill covers the hole.
    `calibration` sets how the cameras' height disagreement is measured (reconstruct/residual).
    A site with a known bin (`site.bin`) first loses its wall points (reconstruct/walls.py).

    Parameters
    ----------
    scan : Scan
        The cameras' clouds, their extrinsics and the scan's own site.
    settings : ReconstructionConfig
        Method (`bicm` or a baseline), grid step, fill, clustering.
    site : Site, optional
        Region, floor, base and bulk density; default the scan's.
    exclude : sequence of (x, y, radius)
        Silo-frame discs whose points are dropped.
    calibration : CalibrationConfig, optional
        Residual thresholds; default `CalibrationConfig()`.
    release_points : bool
        Let go of the raw clouds' points once they are read (`released`): `scan.cameras` then
        holds the same cameras without points, for a caller that reads no more of them than
        their serials and poses. The raw clouds otherwise live through the reconstruction's
        peak (8 full-resolution cameras: 86 MB).

    Returns
    -------
    Reconstruction
        Volume, mass, coverage, levels, the height map, validity with its reason, stage
        timings and the camera pairs' residuals. An empty region is an invalid result, not an
        error.

    Raises
    ------
    LimitExceeded
        The region at this grid step is past the grid's cell limit.
    """
    site = site or scan.site
    blocks = _analysis_blocks(settings, site)
    if blocks > 1:
        fine_step = settings.grid_step_m / blocks
        fine = reconstruct(
            scan,
            settings.model_copy(update={"grid_step_m": fine_step}),
            site,
            exclude,
            calibration,
            release_points,
        )
        return _coarsened(fine, Grid.over(site.region, settings.grid_step_m), blocks)
    raw = sum(len(c.points) for c in scan.cameras)
    if site.bin is None:
        clouds = list(scan.cameras) if release_points else None
        if release_points:
            released(scan)
        result = _reconstruct(scan, settings, site, exclude, calibration, clouds=clouds)
        result.points["raw"] = raw
        return result
    started = time.perf_counter()
    grid, crossings, clear, rough = _wall_pass(scan, settings, site, exclude, calibration)
    # what only the wall step needs goes before the second pass (a fresh process pays for every
    # page it touches), and each camera's steadied cloud as soon as it is reseated
    if rough.heightmap is None:  # nothing certainly off the wall: judge by the clear points
        cameras = [with_points(c, k) for c, k in zip(scan.cameras, clear, strict=True)]
        dropped = raw - sum(len(c.points) for c in cameras)
        del crossings
    else:
        del clear
        first = rough.heightmap.heights.astype(np.float64)
        cameras, dropped = wall_free(
            scan.cameras, crossings, site.bin, first, settings.depth_noise_factor
        )
        del crossings
    if release_points:
        released(scan)
    if rough.heightmap is not None:
        # once: it is the same for every camera
        surface = FirstSurface.of(grid, first, rough.reseat_level)
        del rough
        for index in range(len(cameras)):
            cameras[index] = reseated(cameras[index], surface, settings.depth_noise_factor)
    walls_s = time.perf_counter() - started
    result = _reconstruct(scan, settings, site, exclude, calibration, clouds=cameras)
    del cameras
    result.timings_s = {"walls": walls_s, **result.timings_s}
    result.points["raw"] = raw
    result.points["wall"] = dropped
    return result


def _analysis_blocks(settings: ReconstructionConfig, site: Site) -> int:
    """k: a bin asked for a grid coarser than BIN_ANALYSIS_STEP_M is reconstructed on cells k
    times finer (within the cell limit) and its map given in blocks of k x k (`_coarsened`);
    1 otherwise.

    A 10 cm cell where a drawn-down hopper's grain meets the steel holds points unevenly
    across the crease, its mean 2-3 cm under the cell's (hopper-low, two cameras: the cells
    of grain under 5 cm deep read 26 mm low at 10 cm, 15 mm at 5 cm), and its volume moved with
    the step: -0.46 % at 10 cm against -0.16 % at 5 cm. On 5 cm cells a 10 cm map is the 5 cm
    one, in blocks. Cost: a 10 cm map is as dear as a 5 cm one, and that is its points' work
    (12 m bin, 8 full-resolution cameras, `process` at 10 cm on one core: 2.3 s before, 2.0 s
    now, the same as at 5 cm; hopper-low, two cameras: 0.3-0.5 s at either step)."""
    step = settings.grid_step_m
    k = math.ceil(step / BIN_ANALYSIS_STEP_M - 1e-9)
    if site.bin is None or settings.method != "bicm" or k < 2:
        return 1
    rows, cols = Grid.over(site.region, step).shape  # the grid asked for: its limit first
    return max(1, min(k, math.isqrt(MAX_GRID_CELLS // (rows * cols))))


def _coarsened(fine: Reconstruction, grid: Grid, k: int) -> Reconstruction:
    """`fine`, reconstructed on cells k times finer than `grid`'s, given on `grid`: its map in
    k x k blocks (`HeightMap.coarsened`: the same volume), its volume, levels and coverage
    as they are (read on the finer cells)."""
    parameters = fine.parameters | {"analysis_step_m": fine.grid_step_m}
    result = replace(fine, grid_step_m=grid.step, parameters=parameters)
    if fine.heightmap is not None:
        result.heightmap = fine.heightmap.coarsened(k, grid.inside)
    if fine.information is not None:  # a density: a block's is its cells' mean
        information = block_means(fine.information.astype(np.float64), k, grid.shape)
        result.information = information.astype(np.float32)
    return result


def released(scan: Scan) -> None:
    """`scan`'s cameras, in place (every holder of the scan sees it), without their points and
    colours: serials, poses, intrinsics and counts of dropped non-measurements stay."""
    empty = np.empty((0, 3), np.float32)
    scan.cameras[:] = [replace(c, points=empty, colors=None) for c in scan.cameras]


def _wall_crossings(
    cameras: Sequence[CameraCloud], shape: BinShape, grid: Grid, noise_factor: float
) -> tuple[list[WallCrossing], list[np.ndarray]]:
    """Each camera's wall crossings on the first pass's `grid` and which of its points are
    certainly clear of the wall (a mask, not a copy of them: the first pass reads a few of
    them, `_thinned`), a camera at a time (`WallCrossing.of_cloud`: and a chunk of its points
    at a time)."""
    crossings, clear = [], []
    for cloud in cameras:
        crossing, clear_of_wall = WallCrossing.of_cloud(cloud, shape, grid, noise_factor)
        crossings.append(crossing)
        clear.append(clear_of_wall)
    return crossings, clear


def _wall_pass(
    scan: Scan,
    settings: ReconstructionConfig,
    site: Site,
    exclude: Sequence[tuple[float, float, float]],
    calibration: CalibrationConfig | None,
) -> tuple[Grid, list[WallCrossing], list[np.ndarray], Reconstruction]:
    """A bin's coarse first pass (WALL_PASS_STEP_M at least), made again (`_refined`): its
    grid, each camera's wall crossings and points certainly clear of the wall, and the pass."""
    if site.bin is None:
        raise ValueError("a wall pass needs the bin's geometry (site.bin)")
    rough_settings = settings.model_copy(
        update={"method": "bicm", "grid_step_m": max(settings.grid_step_m, WALL_PASS_STEP_M)}
    )
    grid = Grid.over(site.region, rough_settings.grid_step_m)
    crossings, clear = _wall_crossings(scan.cameras, site.bin, grid, settings.depth_noise_factor)
    rough = _reconstruct(
        replace(scan, cameras=_thinned(scan.cameras, clear, grid)),
        rough_settings,
        site,
        exclude,
        calibration,
        first_pass=True,
    )
    rough = _refined(scan, crossings, grid, rough, rough_settings, site, exclude, calibration)
    return grid, crossings, clear, rough


def _refined(
    scan: Scan,
    crossings: list[WallCrossing],
    grid: Grid,
    rough: Reconstruction,
    settings: ReconstructionConfig,
    site: Site,
    exclude: Sequence[tuple[float, float, float]],
    calibration: CalibrationConfig | None,
) -> Reconstruction:
    """The first pass made again, of every camera's points (thinned) that `rough`'s level
    judges wall-free, reseated on it; `rough` itself if that finds no surface.

    The first pass is made of the points certainly clear of the wall: their smoothed depth is
    short of the wall's by 1.5 depth RMS (0.7 m along the ray at 17 m). So the grain within
    that of the far wall is left out ray by ray, and a cell near the wall gets only the points
    noise pushed outward from nearer grain, none pushed inward from beyond: an 18 m bin's ring
    seen from the far eaves read 0.27-0.37 m low in the first pass, and the wall test and the
    reseating built on it took grain near the wall for wall and levelled it low. The points
    the first pass's level calls wall-free reach the wall, and noise moves them both ways.
    Cost: the wall test, smoothing and reseating of a thinned cloud, and a coarse pass."""
    if site.bin is None or rough.heightmap is None:
        return rough
    first = rough.heightmap.heights.astype(np.float64)
    stride = _stride(sum(len(c.points) for c in scan.cameras), grid)
    every = [
        cloud if stride < 2 else with_points(cloud, np.arange(0, len(cloud.points), stride))
        for cloud in scan.cameras
    ]
    crossed = [c.every(stride) for c in crossings]
    clouds, _ = wall_free(every, crossed, site.bin, first, settings.depth_noise_factor)
    surface = FirstSurface.of(grid, first, rough.reseat_level)
    clouds = [reseated(cloud, surface, settings.depth_noise_factor) for cloud in clouds]
    again = _reconstruct(
        replace(scan, cameras=clouds), settings, site, exclude, calibration, first_pass=True
    )
    return rough if again.heightmap is None else again


def _stride(points: int, grid: Grid) -> int:
    """k such that every k-th of `points` gives the first pass's `grid` about
    WALL_PASS_POINTS_PER_CELL points a cell (1: all of them).

    The first pass gives the grain height at the wall (a ray that met the wall 5 cm above it
    saw wall) and the slope the points are reseated along: 64 points of 10 cm cells know
    both to ~1 cm at 10 m. Eight full-resolution cameras over a 12 m bin bring 250 a cell,
    and the first pass's sort and sums cost by the point."""
    budget = WALL_PASS_POINTS_PER_CELL * int(np.count_nonzero(grid.inside > 0))
    return max(1, points // max(budget, 1))


def _thinned(
    clouds: Sequence[CameraCloud], clear: Sequence[np.ndarray], grid: Grid
) -> list[CameraCloud]:
    """Every k-th of each cloud's points in `clear` (a mask per cloud), k by `_stride`."""
    stride = _stride(sum(int(np.count_nonzero(k)) for k in clear), grid)
    if stride < 2:
        return [with_points(c, k) for c, k in zip(clouds, clear, strict=True)]
    return [with_points(c, np.flatnonzero(k)[::stride]) for c, k in zip(clouds, clear, strict=True)]


def _reconstruct(
    scan: Scan,
    settings: ReconstructionConfig,
    site: Site,
    exclude: Sequence[tuple[float, float, float]],
    calibration: CalibrationConfig | None,
    first_pass: bool = False,
    clouds: list[CameraCloud] | None = None,
) -> Reconstruction:
    """`reconstruct` on clouds that hold no wall. A bin's `first_pass` skips the cameras'
    registration residuals and the surface levels, and adds the level its points are reseated
    on (only its heights and that level are read). `clouds`, one per camera of `scan` in its
    order, are fused in place of the scan's own (a bin's second pass: its clouds without
    their wall points) and the list is emptied once they are: the fused cloud holds their
    points, and the clouds would otherwise live through the clustering's peak (8
    full-resolution cameras: 66 MB)."""
    clock = _Clock()
    grid = Grid.over(site.region, settings.grid_step_m)
    fused = fuse_and_crop(
        scan.cameras if clouds is None else clouds, site, grid, consume=clouds is not None
    )
    if exclude:
        fused = _excluding(fused, exclude)
    clock.lap("fuse_crop")
    calibration = calibration or CalibrationConfig()
    registration: dict[str, PairResidual] = {}
    if not first_pass:
        registration = registration_residuals(
            fused,
            grid,
            [c.serial for c in scan.cameras],
            calibration.residual_min_points,
            calibration.residual_min_cells,
        )
        clock.lap("registration_residual")
    if settings.method != "bicm":
        from silo_agent.reconstruct.baselines import baseline_heights

        heights, observed, volume = baseline_heights(settings, fused, grid, site)
        clock.lap(settings.method)
        counts = _PointCounts(fused.raw_count, len(fused.points), len(fused.points))
        result = _result(scan, site, settings, grid, counts, heights, observed, volume, {}, clock)
        result.registration = registration
        return result

    # each stage drops what the next does not read: a fresh process pays for every page it
    # touches, and the moments (~45 bytes a (cell, camera) pair) need not outlive their totals
    # nor the cloud the clustering (the grid stages after it allocate tens of grid arrays)
    points, camera, cell, moments = fused.points, fused.camera, fused.cell, fused.moments
    raw_count, in_region = fused.raw_count, len(fused.points)
    del fused
    if settings.voxel_size_m is not None:
        points, camera = voxel_downsample(points, camera, settings.voxel_size_m)
        row, col = grid.cell_index(points[:, 0], points[:, 1])
        cell = row * grid.shape[1] + col
        moments = CellMoments.of(points, camera, cell, moments.n_cells, moments.n_cams)
        clock.lap("voxel_downsample")
    # how well each cell is known, from the moments: for a bin's levels, and outside a bin for
    # the volume's clip correction (`counted_heights`); before the totals: its per-pair
    # temporaries are the larger peak
    information = blob = None
    if site.bin is not None or all(cloud.intrinsics for cloud in scan.cameras):
        information = cell_information(grid, moments, scan.cameras, settings.depth_noise_factor)
    if site.bin is not None and first_pass:  # how wide its cameras' noise blobs are, for the
        blob = blob_scale(grid, moments, scan.cameras)  # reseat level
    spread = None
    if site.bin is not None and all(cloud.intrinsics for cloud in scan.cameras):
        spread = point_spread(grid, moments, scan.cameras, settings.depth_noise_factor)
    eps_max = BIN_EPS_MAX_M if site.bin is not None else EPS_MAX_M
    totals = CellTotals.of(moments, settings.cluster_eps_m, eps_max)
    del moments
    segments = height_segments(points, cell, grid, totals)
    counts = _PointCounts(raw_count, in_region, len(points))
    sub_counts = _sub_counts(grid, points)
    del points, camera, cell
    cells = clustered_means(
        segments,
        grid,
        totals,
        settings.cluster_min_points,
        settings.max_clusters,
        point_spread=spread,
    )
    clock.lap("clustered_means")
    del segments, totals
    observed = np.isfinite(cells.height) & (grid.inside > 0)
    observed = _trusted_cells(grid, observed, cells.points, sub_counts)
    del sub_counts
    bin_cells = _BinCells(grid, site.bin) if site.bin is not None else None
    band = _wall_band(grid, bin_cells, observed)
    if bin_cells is not None and information is not None and site.base == "floor":
        # a hopper's bare cone: filled, held up by the steel below (site.base "floor")
        bare = bare_bottom(
            grid,
            bin_cells.shape,
            cells.height,
            observed,
            bin_cells.bottom,
            information,
            settings.repose_slope,
        )
        if np.any(observed & ~band & ~bare):  # an empty hopper keeps its measured steel
            band |= bare
    seen = observed & band  # measured cells of the band or bare steel: covered, though filled
    observed &= ~band
    fill = settings.fill_for(site.bin is not None)
    parameters = {
        "voxel_size_m": settings.voxel_size_m,
        "cluster_eps_m": cells.eps_m,
        "cluster_min_points": cells.min_points,
        "max_clusters": settings.max_clusters,
        "slope_correction": settings.slope_correction,
        "fill": fill,
    }
    if fill == "repose":
        parameters["repose_deg"] = round(float(np.degrees(np.arctan(settings.repose_slope))), 3)
    if not np.any(observed):
        result = _result(
            scan, site, settings, grid, counts, None, observed, None, parameters, clock
        )
        result.registration = registration
        return result
    if fill == "bspline":
        filled = bspline_fill(cells.height, observed)
    elif fill == "repose":
        filled = repose_fill(
            cells.height,
            observed,
            grid.inside > 0,
            cells.points,
            settings.repose_slope,
            grid.step,
            level_floor=site.base == "floor",
        )
    else:
        filled = membrane_fill(cells.height, observed, grid.inside > 0)
    tolerance: float | np.ndarray = cells.double_surface_m
    if spread is not None:  # a bin's: each cell's noise (cells.py, DOUBLE_SURFACE_SPREADS)
        tolerance = np.maximum(tolerance, DOUBLE_SURFACE_SPREADS * spread.reshape(grid.shape))
    filled, observed = _without_spikes(grid, filled, observed, tolerance)
    clock.lap("fill")
    if settings.slope_correction:
        filled = _slope_corrected(grid, filled, cells.centroid_x, cells.centroid_y, observed)
        clock.lap("slope_correction")
    heights = np.where(grid.inside > 0, filled, np.nan)
    if bin_cells is not None and site.base == "floor":
        base = bin_cells.bottom  # a hopper's cone counts, a sloped floor too
        # a fill is no surface under the bin's steel (the membrane runs flat into the wall,
        # where a hopper's cone rises); measured cells keep their noise for `counted_heights`,
        # and so do the gaps between them, filled from their noise: held at the steel, those of
        # a thin wedge of grain where a crater meets the cone counted only their high half
        # (+41 mm on 1.7 m² of hopper-low at 1 cm, +0.8 % on the volume; none at 2 cm)
        hole = ~observed & ~_sampling_gaps(grid, observed, cells.points, band)
        heights = np.where(hole & (heights < base), base, heights)
    else:
        base = base_surface(grid, heights, site.base, site.floor_z)
    under = _under_base(heights, base, observed) if site.base == "floor" else None
    scale_m = BIN_DENOISE_SCALE_M if site.bin is not None else DENOISE_SCALE_M
    # a bin keeps the plain clip: its bare steel reads ~0.5 cm low from 8-10 m, an offset
    measured = None if information is None else np.where(observed, information, 0.0)
    noise = None
    if site.bin is None and information is not None:  # filled cells measured nothing
        noise, information = measured, None
    counted = counted_heights(grid, heights, base, scale_m, noise)
    del noise
    volume = integrate_counted(grid, counted)
    clock.lap("volume")
    result = _result(
        scan,
        site,
        settings,
        grid,
        counts,
        heights,
        observed,
        volume,
        parameters,
        clock,
        counted=counted,
        base=base_plane(grid, heights, site.base, site.floor_z),
        seen=observed | seen if site.bin is not None else None,
        bin_cells=bin_cells,
        information=information,
        levels=not first_pass,
        under_base_m=under,
    )
    result.points["after_downsampling"] = counts.after_downsampling
    result.registration = registration
    if measured is not None and not first_pass:
        result.information = measured.astype(np.float32)
    del measured
    if information is not None and blob is not None:
        result.reseat_level = reseat_level(grid, heights, observed, information, blob)
    return result


def _under_base(heights: np.ndarray, base: np.ndarray, observed: np.ndarray) -> float | None:
    """How far the measured surface lies under the floor (the median over its measured cells),
    if by more than UNDER_BASE_M; else None. Grain cannot lie under the floor: a surface that
    does says the floor's height (`floor_z`) or the cameras' poses are wrong, and its volume
    (near nothing, every cell clipped at the floor) is no measurement."""
    with np.errstate(invalid="ignore"):  # NaN heights: not under
        deep = np.count_nonzero(observed & (heights < base - UNDER_BASE_M))
    if 2 * deep <= np.count_nonzero(observed):  # the median is not that deep (a count: cheap)
        return None
    return float(np.median((base - heights)[observed]))


@dataclass(frozen=True)
class _PointCounts:
    """What a result says of the points: read, in the region, after down-sampling."""

    raw: int
    in_region: int
    after_downsampling: int


def _result(
    scan: Scan,
    site: Site,
    settings: ReconstructionConfig,
    grid: Grid,
    counts: _PointCounts,
    heights: np.ndarray | None,
    observed: np.ndarray,
    volume: float | None,
    parameters: dict[str, Any],
    clock: _Clock,
    counted: np.ndarray | None = None,
    base: tuple[float, float, float] | None = None,
    seen: np.ndarray | None = None,
    bin_cells: _BinCells | None = None,
    information: np.ndarray | None = None,
    levels: bool = True,
    under_base_m: float | None = None,
) -> Reconstruction:
    """`counted` and `base` (bicm only: the volume is integrated from the map) go into the map;
    `seen` (default `observed`): the cells the cameras covered, for the coverage;
    `information` (reconstruct/trust.py): how well each measured cell is known, for a bin's
    levels; without `levels` the result has no surface levels (a bin's first pass: nothing
    reads them); `under_base_m` (`_under_base`): the surface lies that far under the floor,
    and the result is invalid."""
    if bin_cells is None and site.bin is not None:
        bin_cells = _BinCells(grid, site.bin)
    region_area = float(np.sum(grid.inside))
    covered = observed if seen is None else seen
    coverage = float(np.sum(grid.inside * covered) / region_area)
    valid, reason = True, None
    if volume is None:
        valid, reason = False, "no measured point inside the region"
    elif under_base_m is not None:
        valid = False
        reason = (
            f"the measured surface lies {under_base_m:.2f} m under the floor (median): "
            "the floor's height (floor_z) or the cameras' poses are wrong"
        )
    elif coverage < settings.min_coverage:
        valid = False
        reason = f"coverage {coverage:.3f} below the minimum {settings.min_coverage}"
    heightmap = surface = None
    if heights is not None:
        heightmap = HeightMap(
            grid.origin,
            grid.step,
            heights.astype(np.float32),
            observed,
            grid.inside,
            floor_z=site.floor_z,
            base=base,
            counted=counted,
            captured_at=scan.captured_at,
        )
        if levels and np.any(np.isfinite(heights)):
            if bin_cells is not None and counted is not None:
                wall = bin_cells.wall_distance
                surface = grain_levels(
                    grid,
                    heights,
                    counted,
                    observed,
                    wall > LEVEL_WALL_BAND_M,
                    information,
                    wall,
                    bin_cells.bottom,
                )
            else:
                surface = surface_levels(grid, heights)
    density = site.bulk_density_t_m3
    capacity = reference = None
    if site.bin is not None and bin_cells is not None:
        depth = site.bin.eave_z - bin_cells.bottom
        capacity = float(np.sum(depth * grid.inside) * grid.cell_area)
        reference = site.bin.reference_z
    return Reconstruction(
        scan_id=scan.scan_id,
        method=settings.method,
        grid_step_m=settings.grid_step_m,
        volume_m3=volume,
        mass_t=volume * density if volume is not None and density is not None else None,
        coverage=coverage,
        surface=surface,
        floor_z=site.floor_z,
        valid=valid,
        invalid_reason=reason,
        heightmap=heightmap,
        cameras=[c.serial for c in scan.cameras],
        points={
            "raw": counts.raw,
            "not_measurements": sum(c.not_measurements for c in scan.cameras),
            "in_region": counts.in_region,
        },
        parameters=parameters,
        timings_s=clock.laps,
        capacity_m3=capacity,
        reference_z=reference,
    )
