"""The engine's per-camera statistics kept only where a camera has points (issue 22), against
their dense camera x cell definitions, to the bit; and the region's cut cells by scanlines
against the even-odd test of every supersample point."""

from __future__ import annotations

import numpy as np
import pytest

from silo_agent.grid.geometry import _boundary_band, cell_fractions, grid_shape, points_in_polygon
from silo_agent.grid.grid import Grid
from silo_agent.reconstruct.fuse import CellMoments, FusedCloud
from silo_agent.reconstruct.residual import MAX_SLOPE, MAX_SPREAD_M, registration_residuals


def _cloud(n_cams: int, n_cells: int, n_points: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    camera = np.sort(rng.integers(0, n_cams, n_points)).astype(np.uint8)  # fused: camera-major
    cell = rng.integers(0, n_cells, n_points)
    points = rng.normal([3.0, -2.0, 1.5], 0.3, (n_points, 3)).astype(np.float32)
    return points, camera, cell


@pytest.mark.parametrize("camera_major", [True, False])
@pytest.mark.parametrize("n_cams", [2, 8, 12])
def test_moments_are_the_dense_per_camera_bincounts_to_the_bit(
    n_cams: int, camera_major: bool
) -> None:
    n_cells = 400
    points, camera, cell = _cloud(n_cams, n_cells, 30_000)
    if not camera_major:  # a voxel-downsampled cloud's order
        shuffle = np.random.default_rng(n_cams).permutation(len(camera))
        points, camera, cell = points[shuffle], camera[shuffle], cell[shuffle]
    moments = CellMoments.of(points, camera, cell, n_cells, n_cams)
    # the pairs come camera by camera, each camera's cells ascending
    np.testing.assert_array_equal(
        np.lexsort((moments.cell, moments.camera)), np.arange(len(moments.cell))
    )
    dense = np.zeros((5, n_cams, n_cells))
    for k in range(n_cams):  # the former layout: one row per camera, one bincount each
        mine = camera == k
        z = points[mine, 2].astype(np.float64)
        dense[0, k] = np.bincount(cell[mine], None, n_cells)
        dense[1, k] = np.bincount(cell[mine], points[mine, 0], n_cells)
        dense[2, k] = np.bincount(cell[mine], points[mine, 1], n_cells)
        dense[3, k] = np.bincount(cell[mine], z, n_cells)
        dense[4, k] = np.bincount(cell[mine], z * z, n_cells)
    at = (moments.camera, moments.cell)
    assert np.count_nonzero(dense[0]) == len(moments.cell)
    np.testing.assert_array_equal(dense[0][at], moments.count)
    sums = (moments.sum_x, moments.sum_y, moments.sum_z, moments.sum_zz)
    for row, values in enumerate(sums, start=1):
        np.testing.assert_array_equal(dense[row][at], values)
        # a cell's total is the dense rows added down the cameras, bit for bit
        np.testing.assert_array_equal(moments.per_cell(values), dense[row].sum(axis=0))
    np.testing.assert_array_equal(moments.per_cell(moments.count), dense[0].sum(axis=0))
    assert moments.per_cell(moments.count).dtype == np.int64


def _dense_residuals(fused: FusedCloud, grid: Grid, n_cams: int, min_points: int, min_cells: int):
    """The residual as it was computed on camera x cell arrays: (i, j) -> (median, mad, cells)."""
    m = fused.moments
    shape = (n_cams, m.n_cells)
    count, sum_x, sum_y, sum_z, sum_zz = (np.zeros(shape) for _ in range(5))
    for dense, values in zip(
        (count, sum_x, sum_y, sum_z, sum_zz),
        (m.count, m.sum_x, m.sum_y, m.sum_z, m.sum_zz),
        strict=True,
    ):
        dense[m.camera, m.cell] = values
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_z = sum_z / count
        spread = np.sqrt(np.maximum(sum_zz / count - mean_z**2, 0.0))
        seen = (count >= min_points) & (spread <= MAX_SPREAD_M)
        surface = np.where(seen, mean_z, 0.0).sum(axis=0) / seen.sum(axis=0)
        mx, my = sum_x / count, sum_y / count
    grad_y, grad_x = (g.ravel() for g in np.gradient(surface.reshape(grid.shape), grid.step))
    usable = (seen.sum(axis=0) >= 2) & np.isfinite(grad_x) & np.isfinite(grad_y)
    usable &= np.hypot(grad_x, grad_y) <= MAX_SLOPE
    out = {}
    for i in range(n_cams):
        for j in range(i + 1, n_cams):
            both = usable & seen[i] & seen[j]
            if both.sum() < min_cells:
                continue
            diff = (
                (mean_z[i, both] - mean_z[j, both])
                - grad_x[both] * (mx[i, both] - mx[j, both])
                - grad_y[both] * (my[i, both] - my[j, both])
            )
            middle = float(np.median(diff))
            out[(i, j)] = (middle, float(np.median(np.abs(diff - middle))), int(both.sum()))
    return out


def test_registration_residuals_are_the_dense_computation_to_the_bit() -> None:
    region = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    grid = Grid.over(region, 0.05)
    n_cams, n_cells = 9, grid.shape[0] * grid.shape[1]
    rng = np.random.default_rng(5)
    n = 60_000
    camera = np.sort(rng.integers(0, n_cams, n)).astype(np.uint8)
    xy = rng.uniform(0.0, 1.0, (n, 2))
    z = 0.3 * xy[:, 0] + 0.004 * camera + rng.normal(0, 0.003, n)  # camera k sits 4k mm high
    points = np.column_stack([xy, z]).astype(np.float32)
    row, col = grid.cell_index(points[:, 0], points[:, 1])
    cell = np.clip(row, 0, grid.shape[0] - 1) * grid.shape[1] + np.clip(col, 0, grid.shape[1] - 1)
    moments = CellMoments.of(points, camera, cell, n_cells, n_cams)
    fused = FusedCloud(points, camera, cell, n, moments)
    serials = [f"cam{k}" for k in range(n_cams)]
    got = registration_residuals(fused, grid, serials, min_points=5, min_cells=10)
    expected = _dense_residuals(fused, grid, n_cams, 5, 10)
    assert len(expected) == n_cams * (n_cams - 1) // 2
    assert list(got) == [f"cam{i}|cam{j}" for i, j in expected]  # same pairs, same order
    for (i, j), (middle, mad, cells) in expected.items():
        residual = got[f"cam{i}|cam{j}"]
        assert (residual.median_m, residual.mad_m, residual.cells) == (middle, mad, cells)
        assert residual.median_m == pytest.approx(0.004 * (i - j), abs=0.001)


def _round(radius: float, vertices: int) -> np.ndarray:
    angle = np.linspace(0.0, 2 * np.pi, vertices, endpoint=False)
    return np.column_stack([radius * np.cos(angle) + 0.013, radius * np.sin(angle) - 0.021])


@pytest.mark.parametrize(
    ("polygon", "cuts"),
    [
        (_round(1.7, 256), True),
        (np.array([[0.0, 0.0], [3.0, 0.5], [2.2, 2.7], [1.0, 1.1], [0.3, 3.0]]), True),  # concave
        (np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]]), False),  # on cell lines
    ],
)
def test_cut_cells_by_scanlines_are_the_even_odd_test_of_every_sample(polygon, cuts) -> None:
    step, supersample = 0.02, 16
    origin = (float(polygon[:, 0].min()), float(polygon[:, 1].min()))
    shape = grid_shape(polygon, step)
    fraction = cell_fractions(polygon, origin, step, shape, supersample)
    band = _boundary_band(polygon, origin, step, shape)
    rows, cols = np.nonzero(band)
    offsets = ((np.arange(supersample) + 0.5) / supersample - 0.5) * step
    ox, oy = np.meshgrid(offsets, offsets)
    sx = origin[0] + (cols[:, None] + 0.5) * step + ox.ravel()[None, :]
    sy = origin[1] + (rows[:, None] + 0.5) * step + oy.ravel()[None, :]
    np.testing.assert_array_equal(fraction[band], points_in_polygon(sx, sy, polygon).mean(axis=1))
    assert np.any((fraction[band] > 0) & (fraction[band] < 1)) == cuts
