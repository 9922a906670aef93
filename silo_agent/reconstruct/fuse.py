"""Fusing the cameras' clouds onto the grid: transform, crop to the ceiling and the region,
and the per-camera cell moments the residual and the clustered means share."""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

from silo_agent.grid.grid import Grid
from silo_agent.scan import CameraCloud, Site


def run_starts(values: np.ndarray) -> np.ndarray:
    """Start offsets of the runs of equal values in a sorted array.

    A boolean mask of neighbour inequality: 7x faster than flatnonzero(diff(prepend=...)),
    which copies the array to prepend and subtracts in int64.
    """
    starts = np.empty(len(values), dtype=bool)
    starts[:1] = True
    np.not_equal(values[1:], values[:-1], out=starts[1:])
    return np.flatnonzero(starts)


def _sorted_pairs(
    camera: np.ndarray, cell: np.ndarray, n_cells: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points in any camera order: (the pair of each point as intp, each pair's cell, each
    pair's camera), the pairs numbered in (camera, cell) order through a sort of their keys."""
    key = camera.astype(np.int64) * n_cells + cell
    unique, index = np.unique(key, return_inverse=True)
    pair_camera, pair_cell = np.divmod(unique, n_cells)
    return index.astype(np.intp), pair_cell.astype(cell.dtype), pair_camera.astype(np.uint8)


def _pair_sums(
    points: np.ndarray, index: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(count, sum x, sum y, sum z, sum z^2) of the `n` pairs, the points numbered by `index`:
    one bincount each, adding each pair's points in their order."""
    count = np.bincount(index, None, n)
    sum_x = np.bincount(index, points[:, 0], n)
    sum_y = np.bincount(index, points[:, 1], n)
    z = points[:, 2].astype(np.float64)
    sum_z = np.bincount(index, z, n)
    z *= z  # squared in place
    return count, sum_x, sum_y, sum_z, np.bincount(index, z, n)


def _camera_cells(camera_bounds: list[int], cell: np.ndarray, n_cells: int) -> list[np.ndarray]:
    """Each camera's cells, ascending, of points that come camera by camera (`camera_bounds`:
    each camera's first point, then the end): marked on the grid, no sort and nothing
    cameras x cells."""
    seen = np.zeros(n_cells, bool)
    cells = []
    for lo, hi in itertools.pairwise(camera_bounds):
        seen[cell[lo:hi]] = True
        ascending = np.flatnonzero(seen)
        seen[ascending] = False
        cells.append(ascending.astype(cell.dtype, copy=False))
    return cells


@dataclass(frozen=True)
class CellMoments:
    """Per (camera, cell) pair holding points: point count and sums of x, y, z and z^2.

    Computed once per scan while fusing and shared by the registration residual (per-camera
    means and spreads) and the clustered means (cell centroids, the noise that sets eps).
    Sparse: only the pairs that occur, camera by camera and each camera's cells ascending, so
    the cost grows with the points and the cells, not with cameras x cells (8 cameras at 1 cm
    over a 12 m silo held five dense arrays of 8 x 1.44 M cells, 460 MB); a camera's pairs are
    one slice, and a cell's pairs still come in camera order. The sums stay float64: the spread
    is sum_zz / n - mean^2, a difference of two numbers ~ z^2 = 25 m^2 for a ~1e-6 m^2
    variance, which float32's 7 digits cannot carry.
    """

    cell: np.ndarray  # (pairs,) flat cell index (the points' dtype), ascending within a camera
    camera: np.ndarray  # (pairs,) uint8, ascending
    count: np.ndarray  # int64
    sum_x: np.ndarray  # float64, like the other sums
    sum_y: np.ndarray
    sum_z: np.ndarray
    sum_zz: np.ndarray
    n_cells: int
    n_cams: int

    @classmethod
    def of(
        cls, points: np.ndarray, camera: np.ndarray, cell: np.ndarray, n_cells: int, n_cams: int
    ) -> CellMoments:
        """Each pair's sums add its points in their order, as a bincount per camera would.

        Points that come camera by camera (a fused cloud) are summed a camera at a time into
        that camera's slice of the pairs: a pair's points are all its camera's, so each sum
        adds the same values in the same order as one bincount over all the points, to the
        bit, while the index, the float64 columns bincount reads and their temporaries are one
        camera's, not the cloud's (12 m silo at 1 cm, 5.2 M points of 8 cameras: three
        5.2 M-point float64 / intp arrays, 125 MB of fresh pages, no longer made; see the
        commit for the timings). Points in any other order: one bincount each over a sort of
        their (camera, cell) keys."""
        if len(camera) and np.any(camera[1:] < camera[:-1]):
            index, pair_cell, pair_camera = _sorted_pairs(camera, cell, n_cells)
            sums = _pair_sums(points, index, len(pair_cell))
            return cls(pair_cell, pair_camera, *sums, n_cells, n_cams)
        bounds = np.searchsorted(camera, np.arange(n_cams + 1)).tolist()
        cells = _camera_cells(bounds, cell, n_cells)
        sizes = [len(c) for c in cells]
        pair_cell = np.concatenate(cells) if cells else np.empty(0, cell.dtype)
        del cells
        pair_camera = np.repeat(np.arange(n_cams, dtype=np.uint8), sizes)
        n = len(pair_cell)
        count = np.empty(n, np.intp)  # bincount's own count type
        sum_x, sum_y, sum_z, sum_zz = (np.empty(n) for _ in range(4))
        number = np.empty(n_cells, np.intp)  # read only where written: a camera's own cells
        first = 0
        for (lo, hi), size in zip(itertools.pairwise(bounds), sizes, strict=True):
            pairs = slice(first, first + size)
            number[pair_cell[pairs]] = np.arange(size)
            local = np.take(number, cell[lo:hi])
            mine = _pair_sums(points[lo:hi], local, size)
            for whole, part in zip((count, sum_x, sum_y, sum_z, sum_zz), mine, strict=True):
                whole[pairs] = part
            first += size
        return cls(pair_cell, pair_camera, count, sum_x, sum_y, sum_z, sum_zz, n_cells, n_cams)

    def camera_slices(self) -> list[slice]:
        """Each camera's pairs (camera 0 first): one slice each, empty where it has none."""
        bounds = np.searchsorted(self.camera, np.arange(self.n_cams + 1)).tolist()
        return [slice(lo, hi) for lo, hi in itertools.pairwise(bounds)]

    @functools.cached_property
    def _cell_index(self) -> np.ndarray:
        """The pairs' cells as bincount reads them (intp): cast once, not at every per_cell
        (2.8 M pairs, 3 ms a cast)."""
        return self.cell.astype(np.intp)

    def per_cell(self, values: np.ndarray) -> np.ndarray:
        """`values` of the pairs summed over each cell's cameras, dense over all cells (0 where
        none). A bincount adds them one after another in camera order, as the sum down the
        cameras of a dense camera x cell array did, to the bit (a reduceat sums eight or more
        values pairwise, which rounds differently)."""
        total = np.bincount(self._cell_index, values, self.n_cells)
        return total.astype(np.int64) if values.dtype.kind in "iu" else total


@dataclass(frozen=True)
class FusedCloud:
    """Points of all cameras in the silo frame, cropped to the region and under the ceiling."""

    points: np.ndarray  # (N, 3) float32
    camera: np.ndarray  # (N,) uint8 index into the scan's cameras
    cell: np.ndarray  # (N,) int32 flat cell index (row * cols + col)
    raw_count: int
    moments: CellMoments  # of these points


def fuse_and_crop(
    cameras: list[CameraCloud], site: Site, grid: Grid, consume: bool = False
) -> FusedCloud:
    """Paper 2.3.1: transform every cloud by its extrinsic, crop the ceiling and the region.

    Each camera's kept points are written straight into arrays sized for all the points (the
    pages past the last kept point are never touched), not gathered and concatenated: the
    fused cloud never exists twice. With `consume` the list is emptied as its clouds are
    read, so they are gone before the moments are summed (the caller's last reference: 8
    full-resolution cameras' wall-free clouds are 45 MB more at that peak)."""
    rows, cols = grid.shape
    inside_flat = grid.inside.ravel() > 0
    total = sum(len(c.points) for c in cameras)
    points = np.empty((total, 3), np.float32)
    camera_of = np.empty(total, np.uint8)
    cell = np.empty(total, np.int32)  # MAX_GRID_CELLS fits
    used = 0
    pending = cameras[::-1]  # taken from the end: each cloud leaves the list as it is read
    n_clouds = len(pending)
    if consume:
        cameras.clear()
    for index in range(n_clouds):
        silo = pending.pop().points_in_silo()
        row, col = grid.cell_index(silo[:, 0], silo[:, 1])
        keep = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        if site.ceiling_z is not None:
            keep &= silo[:, 2] <= site.ceiling_z
        flat = np.where(keep, row * cols + col, 0)
        keep &= inside_flat[flat]
        kept = np.flatnonzero(keep)
        end = used + len(kept)
        np.take(silo, kept, axis=0, out=points[used:end])
        cell[used:end] = flat[kept]
        camera_of[used:end] = index
        used = end
        del silo
    points, camera_of, cell = points[:used], camera_of[:used], cell[:used]
    moments = CellMoments.of(points, camera_of, cell, rows * cols, n_clouds)
    return FusedCloud(points, camera_of, cell, total, moments)
