"""Clustered means per cell (paper 2.4, Algorithm 1) and voxel down-sampling (paper 2.3.3).

Everything runs on one sorted int64 key per point: (cell, height bin, height within the bin).
Sorting it puts every cell's points together in height order, so 1-D density clustering is a
segment reduction with no loop over cells; the key carries all the sorted data.
numpy's SIMD sort orders it in place where the CPU has a fast one (`SIMD_SORT`), its stable
sort (timsort, which finds the runs a camera's pixel order leaves in the key) elsewhere; the
results are the same either way.

A refinement over the paper, measured in bench/accuracy.py: voxel down-sampling is optional
(off by default): equal weight per voxel quantises heights on a global bin phase and biased
flat floors by up to half a voxel.

A cluster's centroid is the mean height of its points, each point counted once whatever its
camera: the same statistic at every grid step. A mean over cameras of each camera's mean
(kept until 2026-12) weighed the cameras alike in a coarse cell, where each has points, but by
their points in a fine one, which holds one camera's: with 0.1 deg / 3 mm calibration the
cameras' floors disagree by up to 8 mm, and the volume moved with the step (bay-cone, four
views: +4.57 % at 0.1 m, +3.62 % at 5 mm; bench/results/accuracy-steps.md). Counting points
moved no mean error of the accuracy bench up by more than 0.05 pp and most down.

A bin's cells counted the cameras alike too until 2026-12, on the argument that cameras on
opposite sides cancel the shift depth noise gives each camera's points along its own rays at
8-18 m. Over ten seeds of hopper-low (the bin where it mattered most) that held at no step:
mean |volume error| 2.01 / 1.28 / 1.39 % with 2 / 3 / 4 cameras at 5 cm against 1.72 / 1.07 /
1.04 % counting points, as good or better at 2 and 1 cm, while the volume moved up to 0.92 pp
between grid steps (0.63 counting points; bench/results/accuracy-hopper-steps.md).
"""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from silo_agent.grid.grid import Grid
from silo_agent.reconstruct.fuse import CellMoments, run_starts
from silo_agent.reconstruct.residual import median

Z_QUANTUM_M = 1e-4  # height resolution inside the sort key
CAMERA_BITS = 8  # voxel key: up to 256 cameras
RELATIVE_MIN_POINTS = 0.25  # default: a cluster needs 1/4 of the points of the cell's largest
EPS_NOISE_FACTOR = 3.0  # default eps: 3 x the typical spread of one surface in a cell
EPS_MIN_M, EPS_MAX_M = 0.01, 0.10
CORE_DENSITY = 0.2  # a height bin is core at 1/5 of its cell's densest bin (MinPts, relative)
DOUBLE_SURFACE_FACTOR, DOUBLE_SURFACE_MIN_M = 3.0, 0.10  # how far apart two views may disagree
# ... in a bin, at least this many times the RMS a point errs by in the cell (trust.py
# `point_spread`): a cluster of noise reaches from about 2 RMS under its mean to 3 over, and at
# 8-10 m 3 eps (~0.35 m) cut its high tail, one-sided (a 10 m bin's heap, three cameras, read
# 0.5-0.7 % low; the spike rule's tolerance, the same bound, likewise)
DOUBLE_SURFACE_SPREADS = 5.0


@dataclass(frozen=True)
class CellHeights:
    """Per-cell results of the clustered-means step (arrays shaped like the grid)."""

    height: np.ndarray  # float64, NaN where no points
    centroid_x: np.ndarray  # mean x of the cell's points (for the slope correction)
    centroid_y: np.ndarray
    points: np.ndarray  # int, points per cell
    clusters: np.ndarray  # int, clusters kept per cell (0, 1 .. max_clusters)
    eps_m: float
    min_points: int | None  # None: relative to each cell's largest cluster
    double_surface_m: float  # how far apart two views of one surface may be


def _sorts_with_simd() -> bool:
    """Whether numpy sorts int64 with fast SIMD kernels on this CPU (numpy >= 2.0: x86-simd-sort
    on AVX2 and AVX-512, Highway's VQSort on ARM): then its quicksort, else its stable sort
    (docs/development.md, performance notes)."""
    try:  # what numpy.show_runtime() reads; it has no stub
        features = importlib.import_module("numpy._core._multiarray_umath").__cpu_features__
    except (ImportError, AttributeError):  # numpy 1.x
        return False
    if features.get("AVX512_SKX", False) and _zen4():
        return False
    return any(features.get(name, False) for name in ("AVX2", "AVX512_SKX", "ASIMD", "SVE"))


def _zen4() -> bool:
    """An AMD Zen 4 (family 25 with AVX-512): numpy dispatches x86-simd-sort's AVX-512 kernels
    there, whose compress-stores to memory are microcoded (numpy/x86-simd-sort#6): the bench
    VM's EPYC sorts the 12 m silo's 3.3 M keys in 0.21 s with them, 0.08 s with the stable
    sort. Linux only (/proc/cpuinfo); elsewhere False."""
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    first = text.split("\n\n", 1)[0]
    vendor = re.search(r"^vendor_id\s*:\s*(\S+)", first, re.MULTILINE)
    family = re.search(r"^cpu family\s*:\s*(\d+)", first, re.MULTILINE)
    flags = re.search(r"^flags\s*:(.*)$", first, re.MULTILINE)
    return (
        vendor is not None
        and vendor.group(1) == "AuthenticAMD"
        and family is not None
        and int(family.group(1)) == 25
        and flags is not None
        and "avx512f" in flags.group(1).split()
    )


SIMD_SORT = _sorts_with_simd()


def voxel_downsample(
    points: np.ndarray, camera: np.ndarray, size: float
) -> tuple[np.ndarray, np.ndarray]:
    """Paper 2.3.3: one point per occupied voxel (per camera), at the centroid of its points."""
    voxel = np.floor(points / size).astype(np.int64)
    voxel -= voxel.min(axis=0)
    span = voxel.max(axis=0) + 1
    key = ((voxel[:, 0] * span[1] + voxel[:, 1]) * span[2] + voxel[:, 2]) << CAMERA_BITS
    key |= camera.astype(np.int64)
    order = np.argsort(key, kind="stable")
    key = key[order]
    starts = run_starts(key)
    counts = np.diff(np.append(starts, len(key)))
    sums = np.add.reduceat(points[order].astype(np.float64), starts, axis=0)
    return (sums / counts[:, None]).astype(np.float32), camera[order][starts]


@dataclass(frozen=True)
class _Segments:
    """The runs of the sorted key, one per (cell, height bin) holding points."""

    count: np.ndarray  # points in the segment
    bin: np.ndarray  # (cell, height bin) key, ascending
    z_sum: np.ndarray  # the points' heights above `z0`, summed (metres)
    z0: float
    height_bits: int  # bits of the height bin in `bin`
    bin_width_m: float


def _segments(points: np.ndarray, cell: np.ndarray, n_cells: int, eps_m: float) -> _Segments:
    """One sort: key = (cell, height bin of eps/2, height within the bin), each field as
    narrow as the data allows; each (cell, bin) is then a run of the sorted key, a
    "segment", and the rest works on segments. The key and its sort die here: a fresh process
    pays for every page it touches, so a stage's scratch arrays go when it ends."""
    z = points[:, 2]
    z0 = float(z.min())
    scaled = z - z0
    scaled *= 1.0 / Z_QUANTUM_M
    z_q = np.round(scaled, out=scaled).astype(np.int64)
    del scaled
    bin_bits = max(0, int(np.floor(np.log2(max(eps_m / 2 / Z_QUANTUM_M, 1.0)))))
    height_bits = max(1, (int(z_q.max()) >> bin_bits).bit_length())  # bins above z0
    sorted_bits = max(1, (n_cells - 1).bit_length()) + height_bits
    if sorted_bits + bin_bits > 63:
        raise ValueError(
            f"height span {float(z.max()) - z0:.1f} m over {n_cells} cells does not fit the "
            "sort key; crop the cloud (ceiling_z) or use a coarser grid"
        )
    fine_mask = (1 << bin_bits) - 1
    key = cell.astype(np.int64)
    key <<= height_bits + bin_bits
    key |= (z_q >> bin_bits) << bin_bits
    z_q &= fine_mask
    key |= z_q
    del z_q
    # the bits below `bin_bits` get sorted too: only the segments' sums read them. The stable
    # sort (timsort) finds the runs each camera's pixel order leaves in the key: 0.08-0.12 s
    # for the 12 m silo's 3.1-3.3 M keys on the bench VM, where a radix sort of 16-bit digits
    # took 0.14-0.18 s and introsort 0.20 s
    key.sort(kind=None if SIMD_SORT else "stable")
    segment_key = key >> bin_bits
    s_start = run_starts(segment_key)
    s_bin = segment_key[s_start]  # (cell, height bin)
    del segment_key
    s_n = np.empty(len(s_start), np.int32)  # the runs' lengths, written as int32 at once
    np.subtract(s_start[1:], s_start[:-1], out=s_n[:-1], casting="unsafe")
    s_n[-1:] = len(key) - s_start[-1:]
    # the heights within the bin, summed per segment: differences of their running total at
    # the segments' ends (integers: exact, the sums reduceat gave), in place in the key and
    # the starts, so no array more than reduceat's made; 2-3x faster than reduceat, which pays
    # per run (the 12 m silo at 1 cm: 2.9 M segments of 3.3 M points)
    key &= fine_mask
    np.cumsum(key, out=key)
    s_start[:-1] = s_start[1:]  # each segment's last point: the next one's start, less one
    s_start[-1:] = len(key)
    s_start -= 1
    s_end_total = key[s_start]
    del key, s_start
    s_quanta = s_n * ((s_bin & ((1 << height_bits) - 1)) << bin_bits)  # whole bins, then fine
    s_quanta += s_end_total
    s_quanta[1:] -= s_end_total[:-1]
    del s_end_total
    s_z_sum = s_quanta * Z_QUANTUM_M
    return _Segments(s_n, s_bin, s_z_sum, z0, height_bits, Z_QUANTUM_M * (1 << bin_bits))


@dataclass(frozen=True)
class _Clusters:
    """Density clusters of the cells' heights, in cell order."""

    count: np.ndarray  # points
    cell: np.ndarray
    z: np.ndarray  # mean height of the cluster's points, silo frame


def _clusters(
    segments: _Segments,
    eps_m: float,
    double_surface: float | np.ndarray,
) -> _Clusters:
    """1-D density clustering (DBSCAN on a height histogram) of every cell at once: a bin is
    core when its 3-bin neighbourhood holds CORE_DENSITY x the cell's densest one; clusters
    are runs of core bins in a cell, split by a gap of more than eps."""
    b_n, b_key, height_bits = segments.count, segments.bin, segments.height_bits
    b_cell = (b_key >> height_bits).astype(np.int32)  # the grid's cells fit (base/limits.py)
    cell_of_bins = run_starts(b_cell)
    # bins i-1 and i are adjacent heights of one cell (consecutive keys: same cell, next bin)
    adjacent = b_key[1:] - b_key[:-1] == 1
    adjacent[cell_of_bins[1:] - 1] = False
    # each bin's count and its adjacent neighbours': the counts times the 0/1 adjacency added,
    # integers, so the very sums of a masked add (np.add's where=, whose masked loop was 5x
    # slower: the 12 m silo's 2.2 M bins at 1 cm, one core under load, 22-28 -> 4.5 ms)
    density = b_n.copy()
    density[1:] += b_n[:-1] * adjacent
    density[:-1] += b_n[1:] * adjacent
    del adjacent
    bins_per_cell = np.diff(np.append(cell_of_bins, len(b_key)))
    peak = np.repeat(np.maximum.reduceat(density, cell_of_bins), bins_per_cell)
    core = density >= CORE_DENSITY * peak
    del density, peak, bins_per_cell, cell_of_bins

    c_bin = np.flatnonzero(core)
    del core
    bin_width = segments.bin_width_m
    gap_bins = max(1, int(np.ceil(eps_m / bin_width)))
    core_key, core_cell = b_key[c_bin], b_cell[c_bin]  # gathered once, read three times
    del b_key
    new_cluster = np.ones(len(c_bin), dtype=bool)
    new_cluster[1:] = (core_cell[1:] != core_cell[:-1]) | (core_key[1:] - core_key[:-1] > gap_bins)
    cluster_of_core_bin = np.cumsum(new_cluster) - 1
    first = np.flatnonzero(new_cluster)  # each cluster's lowest bin, among the core bins
    del new_cluster
    n_clusters = len(first)
    # a surface is thin: a cluster taller than a double surface is something standing on the
    # grain (a wall seen through depth noise, a post) and only its lowest part is grain
    bottom = core_key[first][cluster_of_core_bin]
    bound = double_surface[core_cell] if isinstance(double_surface, np.ndarray) else double_surface
    thin = core_key - bottom <= bound / bin_width
    bin_cluster = np.full(len(b_cell), -1, dtype=np.int32)  # clusters <= points
    bin_cluster[c_bin[thin]] = cluster_of_core_bin[thin]
    c_cell = core_cell[first]
    # the clustering's peak: its scratch arrays go before the sums
    del b_cell, c_bin, thin, bottom, cluster_of_core_bin, first, core_key, core_cell
    member = bin_cluster >= 0  # a mask: most bins are members
    m_cluster = bin_cluster[member]
    del bin_cluster
    c_n = np.bincount(m_cluster, b_n[member], n_clusters)
    # the points' mean height: what a cell of any size means by it (the module docstring)
    c_z = segments.z0 + np.bincount(m_cluster, segments.z_sum[member], n_clusters) / c_n
    return _Clusters(c_n, c_cell, c_z)


@dataclass(frozen=True)
class CellTotals:
    """What the clustered means read of a cloud's (cell, camera) moments, dense over the
    grid's cells: points, centroids, and eps (the density radius: a gap larger than this in a
    cell splits clusters; given, or adapted to the cells' noise).

    Taken before the clustering so the moments can go first: they are ~45 bytes a (cell,
    camera) pair, these 24 bytes a cell (8 cameras at 1 cm over a 12 m silo: 125 MB against
    35 MB, held through the clustering's own peak)."""

    points: np.ndarray  # int64 per cell
    centroid_x: np.ndarray  # float64 mean x of the cell's points, NaN where none
    centroid_y: np.ndarray
    eps_m: float | None  # None: no points (and none asked for)

    @classmethod
    def of(cls, moments: CellMoments, eps_m: float | None, eps_max_m: float) -> CellTotals:
        """`eps_max_m` caps the adapted eps (a bin seen at 10 m needs more than a bay at 3 m)."""
        per_cell = moments.per_cell(moments.count)
        if eps_m is None and len(moments.count):
            crowded = per_cell >= 3
            count = per_cell[crowded]
            total = moments.per_cell(moments.sum_z)[crowded]
            squares = moments.per_cell(moments.sum_zz)[crowded]
            variance = np.maximum(squares - total * total / count, 0.0) / (count - 1)
            typical = float(np.sqrt(median(variance))) if np.any(crowded) else 0.0
            eps_m = float(np.clip(EPS_NOISE_FACTOR * typical, EPS_MIN_M, eps_max_m))
            del crowded, count, total, squares, variance
        with np.errstate(invalid="ignore", divide="ignore"):
            centroid_x = moments.per_cell(moments.sum_x) / per_cell
            centroid_y = moments.per_cell(moments.sum_y) / per_cell
        return cls(per_cell, centroid_x, centroid_y, eps_m)


def height_segments(
    points: np.ndarray, cell: np.ndarray, grid: Grid, totals: CellTotals
) -> _Segments | None:
    """The sorted (cell, height bin) runs of the points that `clustered_means`
    clusters (None without points); `totals` are those of (points, cell). All the
    clustering reads of the points: they can go before it runs."""
    if len(points) == 0 or totals.eps_m is None:
        return None
    rows, cols = grid.shape
    return _segments(points, cell, rows * cols, totals.eps_m)


def clustered_means(
    segments: _Segments | None,
    grid: Grid,
    totals: CellTotals,
    min_points: int | None,
    max_clusters: int,
    point_spread: np.ndarray | None = None,
) -> CellHeights:
    """`segments` and `totals` of one cloud (`height_segments`, `CellTotals.of`): heights from
    the one, centroids and eps from the other. `point_spread` (per cell, a bin's): the
    double-surface bound is at least DOUBLE_SURFACE_SPREADS times it."""
    rows, cols = grid.shape
    n_cells = rows * cols
    eps_m = totals.eps_m
    if segments is None or eps_m is None:
        nan = np.full(grid.shape, np.nan)
        zeros = np.zeros(grid.shape, dtype=int)
        return CellHeights(nan, nan, nan, zeros, zeros, eps_m or 0.0, min_points, 0.0)

    per_cell = totals.points
    double_surface = max(DOUBLE_SURFACE_FACTOR * eps_m, DOUBLE_SURFACE_MIN_M)
    threshold: float | np.ndarray = double_surface
    if point_spread is not None:
        threshold = np.maximum(np.float32(double_surface), DOUBLE_SURFACE_SPREADS * point_spread)
    found = _clusters(segments, eps_m, threshold)
    c_n, c_cell, c_z = found.count, found.cell, found.z
    n_clusters = len(c_n)

    # ---- noise: clusters too small, absolutely or relative to the cell's largest cluster
    cell_start = run_starts(c_cell)
    group_size = np.diff(np.append(cell_start, n_clusters))
    largest = np.repeat(np.maximum.reduceat(c_n, cell_start), group_size)
    if min_points is None:
        valid = c_n >= np.ceil(RELATIVE_MIN_POINTS * largest)
    else:
        # a cell whose clusters are all small keeps its largest: sparse cells still count
        valid = (c_n >= min_points) | ((c_n == largest) & (largest < min_points))
    # a second surface is a misaligned view of the first, not something standing on the
    # grain (a wall, a robot, a spout): it must lie close above the lowest valid cluster
    lowest = np.repeat(np.minimum.reduceat(np.where(valid, c_z, np.inf), cell_start), group_size)
    valid &= c_z - lowest <= (threshold[c_cell] if isinstance(threshold, np.ndarray) else threshold)

    # ---- keep the `max_clusters` largest valid clusters of each cell (ties: the lowest); only
    # the few cells with more valid clusters than that need ranking
    valid_per_cell = np.add.reduceat(valid.astype(np.int64), cell_start)
    crowded_cluster = np.repeat(valid_per_cell > max_clusters, group_size)
    keep = valid.copy()
    if np.any(crowded_cluster):
        idx = np.flatnonzero(crowded_cluster)
        order = idx[np.lexsort((c_z[idx], -c_n[idx], ~valid[idx], c_cell[idx]))]
        sorted_cell = c_cell[order]
        first = run_starts(sorted_cell)
        rank = np.arange(len(order)) - np.repeat(first, np.diff(np.append(first, len(order))))
        keep[order] &= rank < max_clusters

    kept = np.bincount(c_cell, keep.astype(float), n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        height = np.bincount(c_cell, c_z * keep, n_cells) / kept
    height[kept == 0] = np.nan
    return CellHeights(
        height=height.reshape(grid.shape),
        centroid_x=totals.centroid_x.reshape(grid.shape),
        centroid_y=totals.centroid_y.reshape(grid.shape),
        points=per_cell.reshape(grid.shape),
        clusters=kept.astype(int).reshape(grid.shape),
        eps_m=eps_m,
        min_points=min_points,
        double_surface_m=double_surface,
    )
