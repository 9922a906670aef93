"""Fusing the cameras' clouds onto the grid: transform, crop to the ceiling and the region,
and the per-camera cell moments the residual and the clustered means share."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from silo_agent.grid.grid import Grid
from silo_agent.scan import CameraCloud, Site


@dataclass(frozen=True)
class CellMoments:
    """Per (camera, cell): point count and sums of x, y, z and z^2; arrays (cameras, cells).

    Computed once per scan while fusing and shared by the registration residual (per-camera
    means and spreads) and the clustered means (cell centroids, the noise that sets eps).
    Camera-major, so that sums over cameras add whole rows (summing a short last axis is
    several times slower), and filled one camera at a time: a bincount into one camera's row
    stays in cache where one into all cameras' does not.
    """

    count: np.ndarray  # int64
    sum_x: np.ndarray  # float64, like the other sums
    sum_y: np.ndarray
    sum_z: np.ndarray
    sum_zz: np.ndarray

    @classmethod
    def zeros(cls, n_cams: int, n_cells: int) -> CellMoments:
        count = np.zeros((n_cams, n_cells), dtype=np.int64)
        return cls(count, *(np.zeros((n_cams, n_cells)) for _ in range(4)))

    @classmethod
    def of(
        cls, points: np.ndarray, camera: np.ndarray, cell: np.ndarray, n_cells: int, n_cams: int
    ) -> CellMoments:
        moments = cls.zeros(n_cams, n_cells)
        for index in range(n_cams):
            mine = camera == index
            moments.set_camera(index, points[mine], cell[mine])
        return moments

    def set_camera(self, index: int, points: np.ndarray, cell: np.ndarray) -> None:
        """Fill camera `index`'s row from its points and their cells."""
        n_cells = self.count.shape[1]
        z = points[:, 2].astype(np.float64)
        self.count[index] = np.bincount(cell, None, n_cells)
        self.sum_x[index] = np.bincount(cell, points[:, 0], n_cells)
        self.sum_y[index] = np.bincount(cell, points[:, 1], n_cells)
        self.sum_z[index] = np.bincount(cell, z, n_cells)
        self.sum_zz[index] = np.bincount(cell, z * z, n_cells)


@dataclass(frozen=True)
class FusedCloud:
    """Points of all cameras in the silo frame, cropped to the region and under the ceiling."""

    points: np.ndarray  # (N, 3) float32
    camera: np.ndarray  # (N,) uint8 index into the scan's cameras
    cell: np.ndarray  # (N,) int64 flat cell index (row * cols + col)
    raw_count: int
    moments: CellMoments  # of these points


def fuse_and_crop(cameras: list[CameraCloud], site: Site, grid: Grid) -> FusedCloud:
    """Paper 2.3.1: transform every cloud by its extrinsic, crop the ceiling and the region.

    Each camera's kept points are written straight into arrays sized for all the points (the
    pages past the last kept point are never touched), not gathered and concatenated: the
    fused cloud never exists twice."""
    rows, cols = grid.shape
    inside_flat = grid.inside.ravel() > 0
    total = sum(len(c.points) for c in cameras)
    points = np.empty((total, 3), np.float32)
    camera_of = np.empty(total, np.uint8)
    cell = np.empty(total, np.int64)
    moments = CellMoments.zeros(len(cameras), rows * cols)
    used = 0
    for index, camera in enumerate(cameras):
        silo = camera.points_in_silo()
        row, col = grid.cell_index(silo[:, 0], silo[:, 1])
        keep = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        if site.ceiling_z is not None:
            keep &= silo[:, 2] <= site.ceiling_z
        flat = np.where(keep, row * cols + col, 0)
        keep &= inside_flat[flat]
        kept = np.flatnonzero(keep)
        end = used + len(kept)
        np.take(silo, kept, axis=0, out=points[used:end])
        np.take(flat, kept, out=cell[used:end])
        camera_of[used:end] = index
        moments.set_camera(index, points[used:end], cell[used:end])
        used = end
    return FusedCloud(points[:used], camera_of[:used], cell[:used], total, moments)
