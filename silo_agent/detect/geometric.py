"""Geometric pile detector: segment the height map into piles by their peaks. Pure numpy/scipy.

Works from depth alone, so it needs neither light (the paper's YOLO drops to 26-45 % mAP below
50 lux) nor a trained model. Steps:

1. relief = height above the base the engine integrates over (floor or boundary plane), or
   above a local background (a wide morphological opening) when `background_m` is set;
2. basins = watershed of the (lightly smoothed) relief over the cells standing `EDGE_M` above
   it: every cell follows its steepest ascent to a peak, so basin boundaries fall on the
   valley lines between piles (where one cone meets the next);
3. a basin whose peak rises less than `min_prominence_m` above the saddle to a higher basin, or
   lies closer than `min_separation_m` to its peak, is merged into it (peaks and saddles read on
   a smoother relief, so noise bumps do not count);
4. piles lower than `min_height_m` or with a footprint under `min_area_m2` are dropped.

A pile's volume is the sum of the engine's own per-cell columns over its basin (the height
map's `counted` layer, or `volume.denoised_columns` over a local background), so pile volumes
add up to (at most) the scan's volume.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from silo_agent.config import DetectionConfig
from silo_agent.detect.piles import Pile
from silo_agent.grid.filters import block_means
from silo_agent.grid.grid import Grid
from silo_agent.grid.heightmap import HeightMap
from silo_agent.grid.smooth import masked_smooth
from silo_agent.grid.volume import (
    DENOISE_SCALE_M,
    base_surface,
    counted_columns,
    denoised_columns,
    smooth_sigma,
)

__all__ = ["Surface", "detect_piles", "detection_map", "grid_of", "relief"]

EDGE_M = 0.01  # a cell belongs to a pile's footprint when it stands this far above the base
BASIN_SMOOTHING_M = 0.04  # Gaussian sigma of the surface the basins are traced on
PEAK_SMOOTHING_M = 0.10  # sigma of the surface peaks and saddles are read on: D455 noise at
# 3-5 m leaves bumps of several cm a few decimetres wide, which must not count as piles
DETECTION_STEP_M = 0.02  # piles are found on blocks of cells up to this wide (`detection_map`)
# a peak is its own pile only if it stands above the saddle by this many standard deviations of
# the difference of two heights of the surface peaks are read on (the cameras' noise model,
# `volume.smooth_sigma`): 1.5 left a noise peak on the far ring of the simulator's 18 m bin
# from eight full-resolution eave cameras, 2 none on bin-18, bin-heap, hopper-heap, bin-side
# (seeds 0-2); near the cameras min_prominence_m rules (docs/detection.md)
NOISE_SIGMAS = 2.0


def grid_of(heightmap: HeightMap) -> Grid:
    return Grid(heightmap.origin, heightmap.step, heightmap.shape, heightmap.inside)


def relief(heightmap: HeightMap, base: np.ndarray, background_m: float | None) -> np.ndarray:
    """Height above `base`, or above a local background when `background_m` is given.

    The background is a grey opening with a square `background_m` wide: it removes every
    feature narrower than that (the piles) and keeps the wide level they stand on. It opens the
    smoothed surface: the opening's minimum would otherwise sit on the noise's troughs.
    """
    heights = heightmap.heights.astype(float)
    region = np.isfinite(heights) & (heightmap.inside > 0)
    floor = base
    if background_m is not None:
        size = max(3, 2 * round(background_m / heightmap.step / 2) + 1)
        smooth = masked_smooth(heights, region, max(PEAK_SMOOTHING_M / heightmap.step, 1.0))
        eroded = ndimage.minimum_filter(np.where(region, smooth, np.inf), size)
        opened = ndimage.maximum_filter(np.where(region, eroded, -np.inf), size)
        floor = np.maximum(base, np.where(region, opened, base))
    return np.where(region, heights - floor, np.nan)


def detection_map(heightmap: HeightMap) -> HeightMap:
    """The map piles are found on: `heightmap` in blocks of k x k cells, k the most whose
    block is no wider than DETECTION_STEP_M (2 at 1 cm, 4 at 5 mm; 1, the map itself, on cells
    wider than 1 cm), made by `HeightMap.coarsened` (the same volume, so pile volumes still
    add up to the scan's).

    The basins are traced on a surface smoothed over BASIN_SMOOTHING_M, twice the blocks'
    width: a finer map finds the same piles at k^2 times the cells. Measured with the whole
    detection (`Surface.of` + `detect_piles`, one core): the 12 m bin of bench/silos.py at
    1 cm, 241 -> 96 ms, the bay scans of bench/floor.py (c) 46-59 -> 19-26 ms; pile volumes
    within 0.2 % where the same basins are found, peaks 1-2 cm lower (a block's mean, not its
    highest cell's height)."""
    k = int(DETECTION_STEP_M / heightmap.step + 1e-9)
    return heightmap.coarsened(k) if k >= 2 else heightmap


_OFFSETS = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
_DIAGONAL = float(np.hypot(1, 1))  # a diagonal neighbour's distance in cells
_BLOCK_ROWS = 32  # `_ascent_basins`' slopes a block of rows at a time: they stay in cache


def _ascent_basins(smooth: np.ndarray, domain: np.ndarray) -> np.ndarray:
    """Label every `domain` cell by the local maximum its steepest-ascent path ends on.

    Each cell points at its steepest uphill neighbour (8-connected); pointer jumping follows
    the paths to their tops in log(length) vectorised steps. Where two cones meet, the ascent
    goes up the cone the cell lies on, so basin boundaries fall on the valley lines. Labels
    number the tops in row-major order. A path never leaves the domain (cells outside it read
    -inf), so the tops are the domain's cells that point at themselves.

    The steepest neighbour is kept as its number in `_OFFSETS` (uint8), a block of rows at a
    time, and the best slope by `np.fmax` (a NaN slope, -inf - -inf, never wins, as it never
    compared greater): one masked copy of a byte an offset, not two of float64 and int64 over
    the whole map. The same pointers (a neighbour wins only where its slope is greater than
    every earlier one's): 12 m bin at 1 cm (1.44 M cells), the whole function 79 -> 53 ms
    (the pointers 47-50 -> 22 ms, the rest is the jumping).
    """
    rows, cols = smooth.shape
    values = np.pad(np.where(domain, smooth, -np.inf), 1, constant_values=-np.inf)
    choice = np.zeros(smooth.shape, dtype=np.uint8)  # 0: itself, k + 1: _OFFSETS[k]
    block = min(rows, _BLOCK_ROWS)
    best, slope = np.empty((block, cols)), np.empty((block, cols))
    better = np.empty((block, cols), dtype=bool)
    with np.errstate(invalid="ignore"):  # -inf - -inf outside the domain: never better
        for top in range(0, rows, block):
            n = min(block, rows - top)
            high, rise, up, pick = best[:n], slope[:n], better[:n], choice[top : top + n]
            high.fill(0.0)
            centre = values[1 + top : 1 + top + n, 1 : cols + 1]
            for k, (dr, dc) in enumerate(_OFFSETS):
                near = values[1 + top + dr : 1 + top + n + dr, 1 + dc : cols + 1 + dc]
                np.subtract(near, centre, out=rise)
                if dr and dc:
                    np.divide(rise, _DIAGONAL, out=rise)
                np.greater(rise, high, out=up)
                np.fmax(high, rise, out=high)
                np.copyto(pick, k + 1, where=up)
    # a neighbour is on the map: one outside it reads -inf, never uphill
    step = np.array([0] + [dr * cols + dc for dr, dc in _OFFSETS])
    pointer = np.arange(rows * cols)
    pointer += step[choice.ravel()]
    del choice
    while True:
        jumped = pointer[pointer]
        if np.array_equal(jumped, pointer):
            break
        pointer = jumped
    inside = domain.ravel()
    tops = np.flatnonzero(inside & (pointer == np.arange(rows * cols)))
    number = np.zeros(rows * cols, dtype=np.int64)
    number[tops] = np.arange(1, len(tops) + 1)
    return np.where(inside, number[pointer], 0).reshape(rows, cols)


def _saddles(labels: np.ndarray, smooth: np.ndarray) -> dict[tuple[int, int], float]:
    """Highest pass between every pair of touching basins: max over their shared edges of the
    lower of the two cells.

    The pairs of neighbours that differ found once a direction on the flat map (a row's last
    cell has no right neighbour), then gathered by index: not six boolean selections a
    direction over the whole map. The same pairs in the same order: 12 m bin at 1 cm (1.44 M
    cells), 21-23 -> 7-8 ms."""
    cols = labels.shape[1]
    flat, height = labels.ravel(), smooth.ravel()
    pairs = []
    for shift in (1, cols):  # right, down
        differ = flat[:-shift] != flat[shift:]
        if shift == 1:
            differ[cols - 1 :: cols] = False  # a row's last cell and the next row's first
        first = np.flatnonzero(differ)
        del differ
        la, lb = flat[first], flat[first + shift]
        touch = (la > 0) & (lb > 0)
        first, la, lb = first[touch], la[touch], lb[touch]
        low, high = np.minimum(la, lb), np.maximum(la, lb)
        pairs.append(np.column_stack([low, high, np.minimum(height[first], height[first + shift])]))
    edges = np.concatenate(pairs)
    if len(edges) == 0:
        return {}
    keys = edges[:, 0].astype(np.int64) * (int(labels.max()) + 1) + edges[:, 1].astype(np.int64)
    unique, inverse = np.unique(keys, return_inverse=True)
    best = np.full(len(unique), -np.inf)
    np.maximum.at(best, inverse, edges[:, 2])
    n = int(labels.max()) + 1
    return {(int(k // n), int(k % n)): float(v) for k, v in zip(unique, best, strict=True)}


def _run_maxima(values: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(where each run of equal labels starts in the map's row-major order, its largest value);
    `labels` not empty."""
    flat = labels.ravel()
    starts = np.empty(len(flat), dtype=bool)
    starts[0] = True
    np.not_equal(flat[1:], flat[:-1], out=starts[1:])
    runs = np.flatnonzero(starts)
    with np.errstate(invalid="ignore"):  # the unlabelled cells' runs may be NaN
        return runs, np.maximum.reduceat(values.ravel(), runs)


def _highest(
    values: np.ndarray,
    labels: np.ndarray,
    count: int,
    run_maxima: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Each label's (0..count) highest value, -inf for label 0 and for labels with no cell
    (`values` finite where labelled); `run_maxima` the labels' `_run_maxima` when known.

    A basin is a patch of cells, so in row-major order its cells come in runs: the maximum of
    each run (one reduceat over the map), then a scatter-maximum over the runs, not over the
    cells. The same maxima (a maximum does not round); 16 piles' 3 M labelled cells on a 20 m
    bin at 1 cm: 155-173 -> 13-15 ms, where `np.maximum.at` spent ~50 ns a cell."""
    flat = labels.ravel()
    highest = np.full(count + 1, -np.inf)
    if len(flat) == 0:
        return highest
    runs, maxima = _run_maxima(values, labels) if run_maxima is None else run_maxima
    with np.errstate(invalid="ignore"):  # the unlabelled cells' runs may be NaN: dropped next
        np.maximum.at(highest, flat[runs], maxima)
    highest[0] = -np.inf
    return highest


def _basin_peaks(
    values: np.ndarray, labels: np.ndarray, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Each basin's (1..count) highest value and the (row, col) of that cell (of several
    equal highest cells, the first in row-major order). `values` is finite where labels > 0.

    A scatter-maximum over the cells and one comparison, not a sort of all the values (what
    `ndimage.maximum_position` does; docs/development.md, performance notes). The comparison
    over the cells of the runs whose maximum is their basin's peak only (`_highest`'s runs),
    not over every labelled cell: 12 m bin at 1 cm (1.44 M cells), 13-16 -> 10 ms.
    """
    if labels.size == 0:
        return np.full(count, -np.inf), np.zeros((count, 2), dtype=np.int64)
    runs, maxima = _run_maxima(values, labels)
    peaks = _highest(values, labels, count, (runs, maxima))
    flat_labels, flat_values = labels.ravel(), values.ravel()
    ends = np.append(runs[1:], len(flat_labels))
    run_label = flat_labels[runs]
    with np.errstate(invalid="ignore"):  # NaN outside the basins: never a peak
        top = maxima == peaks[run_label]
    top &= run_label > 0
    runs, ends = runs[top], ends[top]
    length = ends - runs
    cells = np.arange(int(length.sum())) - np.repeat(np.cumsum(length) - length, length)
    cells += np.repeat(runs, length)  # ascending: the runs' cells in row-major order
    highest = cells[flat_values[cells] == peaks[flat_labels[cells]]]
    cell = np.zeros(count + 1, dtype=np.int64)
    cell[flat_labels[highest[::-1]]] = highest[::-1]  # the last assignment wins: the first cell
    return peaks[1:], np.column_stack(np.unravel_index(cell[1:], values.shape))


def _merge_low_peaks(
    labels: np.ndarray,
    smooth: np.ndarray,
    min_prominence: float,
    min_separation_cells: float,
    noise: np.ndarray | None = None,
) -> np.ndarray:
    """Merge each basin into its highest-saddle higher neighbour when its peak is less than
    `min_prominence` above that saddle (or NOISE_SIGMAS x sqrt(2) x `noise`, `smooth`'s noise
    sigma, at the peak, if more) or closer than `min_separation_cells` to that neighbour's
    peak; lowest peaks first (loops over basins, not cells)."""
    count = int(labels.max())
    if count < 2:
        return labels
    index = np.arange(1, count + 1)
    peaks, where = _basin_peaks(smooth, labels, count)
    need = np.full(count, min_prominence)
    if noise is not None:
        np.maximum(need, NOISE_SIGMAS * np.sqrt(2.0) * noise[where[:, 0], where[:, 1]], out=need)
    needed = dict(zip(index.tolist(), need.tolist(), strict=True))
    rank = {k: (float(p), k) for k, p in zip(index.tolist(), peaks, strict=True)}
    top = {k: w.astype(float) for k, w in zip(index.tolist(), where, strict=True)}
    neighbours: dict[int, dict[int, float]] = {k: {} for k in rank}
    for (a, b), s in _saddles(labels, smooth).items():
        neighbours[a][b] = s
        neighbours[b][a] = s
    owner = np.arange(count + 1)
    for k in sorted(rank, key=rank.__getitem__):
        higher = {n: s for n, s in neighbours[k].items() if rank[n] > rank[k]}
        if not higher:
            continue
        into, saddle = max(higher.items(), key=lambda item: item[1])
        prominent = rank[k][0] - saddle >= needed[k]
        apart = np.hypot(*(top[k] - top[into])) >= min_separation_cells
        if prominent and apart:
            continue
        owner[owner == k] = into
        for n, s in neighbours.pop(k).items():
            neighbours[n].pop(k, None)
            if n != into:
                neighbours[into][n] = max(s, neighbours[into].get(n, -np.inf))
                neighbours[n][into] = neighbours[into][n]
    return owner[labels]


@dataclass(frozen=True)
class Surface:
    """A height map prepared for measuring piles: relief, per-cell volume columns, cell
    centres. Computed once per scan, shared by both detectors."""

    heightmap: HeightMap
    floor_z: float
    smooth: np.ndarray  # relief (`relief`) lightly smoothed: basins and footprints
    coarse: np.ndarray  # relief smoothed more: peak heights and saddles without noise bumps
    surface: np.ndarray  # silo-frame z, NaN outside the region
    columns: (
        np.ndarray
    )  # m³ per cell: the volume's columns (`counted` layer) or over the background
    xs: np.ndarray
    ys: np.ndarray
    noise: np.ndarray | None = None  # `coarse`'s noise sigma per cell; None: not known

    @classmethod
    def of(
        cls,
        heightmap: HeightMap,
        base: np.ndarray,
        floor_z: float,
        background_m: float | None,
        information: np.ndarray | None = None,
    ) -> Surface:
        """`base` is the engine's base surface (`volume.base_surface`) on the map's grid;
        `information` the cameras' information density of each measured cell's height
        (`Reconstruction.information`, on the map's grid), which tells the noise of the
        surface peaks are read on (`coarse`)."""
        grid = grid_of(heightmap)
        rise = relief(heightmap, base, background_m)
        region = np.isfinite(rise)
        step = heightmap.step
        smooth = masked_smooth(rise, region, max(BASIN_SMOOTHING_M / step, 1.0))
        coarse = masked_smooth(rise, region, max(PEAK_SMOOTHING_M / step, 1.0))
        noise = None
        if information is not None:
            noise = smooth_sigma(grid, information, region, PEAK_SMOOTHING_M)
        surface = np.where(region, heightmap.heights.astype(float), np.nan)
        if background_m is None and heightmap.counted is not None:
            counted = counted_columns(grid, heightmap.counted)  # the volume's own columns
        else:
            volume_base = base if background_m is None else surface - rise
            counted = denoised_columns(grid, surface, volume_base, DENOISE_SCALE_M)
        columns = counted * grid.cell_area
        xs, ys = heightmap.cell_centres()
        return cls(heightmap, floor_z, smooth, coarse, surface, columns, xs, ys, noise)

    @classmethod
    def for_piles(
        cls,
        heightmap: HeightMap,
        base: str,
        floor_z: float,
        background_m: float | None,
        information: np.ndarray | None = None,
    ) -> Surface:
        """The surface piles are found on: `heightmap` in blocks up to DETECTION_STEP_M wide
        (`detection_map`) above its base (`base`, the site's: "floor" or "boundary");
        `information` on `heightmap`'s grid (a density: a block's is its cells' mean)."""
        blocks = detection_map(heightmap)
        grid = grid_of(blocks)
        under = base_surface(grid, blocks.heights.astype(float), base, floor_z)
        if information is not None and blocks is not heightmap:
            k = round(blocks.step / heightmap.step)
            information = block_means(information.astype(np.float64), k, blocks.shape)
        return cls.of(blocks, under, floor_z, background_m, information)

    def pile(
        self,
        cells: np.ndarray,
        detector: str,
        confidence: float | None = None,
        box: tuple[slice, ...] | None = None,
    ) -> Pile:
        """Measure the pile standing on `cells` (boolean, on the map's grid, or on its `box`
        when given: a pile's bounding box, `ndimage.find_objects`'); id 0. The same figures
        either way: the box holds all the pile's cells, in the map's row-major order."""

        def of(values: np.ndarray) -> np.ndarray:
            return values if box is None else values[box]

        columns, xs, ys, surface = of(self.columns), of(self.xs), of(self.ys), of(self.surface)
        weight = np.maximum(columns[cells], 0.0)
        total = float(np.sum(weight))
        if total > 0:
            centroid = (
                float(np.sum(weight * xs[cells]) / total),
                float(np.sum(weight * ys[cells]) / total),
            )
        else:
            centroid = (float(np.mean(xs[cells])), float(np.mean(ys[cells])))
        top = np.where(cells, np.nan_to_num(surface, nan=-np.inf), -np.inf)
        row, col = (int(i) for i in np.unravel_index(int(np.argmax(top)), top.shape))
        if box is not None:  # back on the map; no surface at all: its first cell, as unboxed
            found = np.max(top) > -np.inf
            row, col = (row + box[0].start, col + box[1].start) if found else (0, 0)
        peak = row, col
        area = of(self.heightmap.inside) * self.heightmap.step**2
        return Pile(
            id=0,
            detector=detector,
            centroid=centroid,
            peak=(float(self.xs[peak]), float(self.ys[peak])),
            peak_height_m=float(self.surface[peak] - self.floor_z),
            footprint_m2=float(np.sum(area[cells])),
            volume_m3=float(np.sum(columns[cells])),
            confidence=confidence,
        )


def detect_piles(surface: Surface, settings: DetectionConfig) -> list[Pile]:
    """Piles of a reconstructed height map, largest volume first, ids 1..n (see
    `piles.match_ids` for ids that last between scans).

    Parameters
    ----------
    surface : Surface
        The height map above its base, smoothed and coarse (`Surface.of`).
    settings : DetectionConfig
        Prominence, footprint and volume a pile needs.

    Returns
    -------
    list of Pile
        The geometric detector's piles; empty when nothing stands `EDGE_M` above the base.
    """
    smooth = surface.smooth
    domain = np.isfinite(smooth) & (smooth > EDGE_M)
    if not np.any(domain):
        return []
    labels = _ascent_basins(smooth, domain)
    coarse = surface.coarse
    labels = _merge_low_peaks(
        labels,
        coarse,
        settings.min_prominence_m,
        settings.min_separation_m / surface.heightmap.step,
        surface.noise,
    )
    tallest = _highest(coarse, labels, int(labels.max()))
    # each pile measured over its bounding box, not over the whole map (16 piles on a 20 m
    # bin's 4 M cells at 1 cm: 0.44 -> 0.08 s under cProfile)
    boxes = ndimage.find_objects(labels)
    piles = []
    for k in np.flatnonzero(tallest >= settings.min_height_m):  # basins high enough to be piles
        box = boxes[k - 1]  # a label with no cell is never high enough (_highest: -inf)
        pile = surface.pile(labels[box] == k, "geometric", box=box)
        if pile.footprint_m2 >= settings.min_area_m2:
            piles.append(pile)
    piles.sort(key=lambda p: -p.volume_m3)
    return [replace(p, id=i + 1) for i, p in enumerate(piles)]
