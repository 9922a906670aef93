"""How well each cell's measured height is known: the D455's noise model applied to the
cameras that saw the cell, from where they saw it. Pure numpy, per (cell, camera) pair.

A stereo camera errs in disparity, so along the ray its depth RMS grows with depth squared
(base/d455.py); a height errs by that times the ray's vertical share (drop / depth). Half the
variance is common to the pixels of a ~4 px blob (CORRELATED_SHARE, CORRELATION_PX): averaging
the points of one frame inside a blob does not take it down, averaging over many blobs does.
So a camera tells a surface's height to (variance x area) v = share x rms_v^2 x blob area on
the ground + the rest x rms_v^2 x one pixel's ground area; per unit area it brings 1 / v of
"information". A cell's information is the sum over the cameras that saw it (weighted by the
share of the cell their points cover), and the mean of a surface over an area A with that
information density I is known to 1 / sqrt(A x I). At 5 m under an eave camera a 0.2 m disc
is known to ~1 cm; at 10 m, from the far side of a 10 m bin, a 1 m disc only to ~3 cm; at
15-19 m across an 18 m bin, 3 m of floor to ~5 cm.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from silo_agent.base.d455 import CORRELATED_SHARE, CORRELATION_PX, blob_area_px, depth_rms_m
from silo_agent.grid.grid import Grid
from silo_agent.grid.volume import LEVEL_GRID_M
from silo_agent.reconstruct.fuse import CellMoments
from silo_agent.reconstruct.walls import kept_noise_share, window_px
from silo_agent.scan import CameraCloud


@dataclass(frozen=True)
class _Sightlines:
    """One camera's (cell, camera) pairs and how it sees each cell: from where its points'
    mean height in the cell lies (a few tenths of a metre of noise against a drop of 5-10 m
    barely moves these)."""

    cloud: CameraCloud
    pairs: slice  # the camera's pairs among the moments
    cell: np.ndarray  # flat cell index
    row: np.ndarray
    col: np.ndarray
    focal: float  # pixels
    across_x: np.ndarray  # from the camera to the cell's centre, horizontally (m)
    across_y: np.ndarray
    drop: np.ndarray  # from the camera down to the cell's mean height (m; NaN if none)
    reach: np.ndarray  # the distance from the camera to there (m)


def _sightlines(
    grid: Grid, moments: CellMoments, cameras: list[CameraCloud]
) -> Iterator[_Sightlines]:
    """Each camera's `_Sightlines` that has points, one camera at a time (its pairs only,
    component by component): the pairs of a silo at 1 cm run to millions, and (pairs, 3)
    float64 temporaries to hundreds of MB."""
    step, (x0, y0) = grid.step, grid.origin
    cols = grid.shape[1]
    for cloud, pairs in zip(cameras, moments.camera_slices(), strict=False):
        if pairs.start == pairs.stop:
            continue
        cell = moments.cell[pairs]
        ox, oy, oz = cloud.extrinsic[:3, 3]
        row, col = np.divmod(cell, cols)
        across_x = x0 + (col + 0.5) * step - ox
        across_y = y0 + (row + 0.5) * step - oy
        with np.errstate(invalid="ignore", divide="ignore"):
            drop = oz - moments.sum_z[pairs] / moments.count[pairs]
        reach = np.sqrt(across_x**2 + across_y**2 + drop**2)
        focal = float(cloud.intrinsics["fx"]) if cloud.intrinsics else 1.0
        yield _Sightlines(cloud, pairs, cell, row, col, focal, across_x, across_y, drop, reach)


def _where_not_all(mask: np.ndarray) -> Callable[[np.ndarray, float], np.ndarray]:
    """`np.where(mask, values, other)` as a function of (values, other); the values themselves
    where `mask` holds everywhere."""
    if np.all(mask):
        return lambda values, _other: values
    return lambda values, other: np.where(mask, values, other)


def _axis_depth(seen: _Sightlines) -> tuple[np.ndarray, np.ndarray]:
    """Each of a camera's cells' depth along its optical axis, and whether the cell is usable
    (in front of the camera, below it)."""
    ax, ay, az = seen.cloud.extrinsic[:3, 2]
    depth = seen.across_x * ax + seen.across_y * ay - seen.drop * az
    return depth, np.isfinite(seen.drop) & (depth > 0) & (seen.drop > 0)


def cell_information(
    grid: Grid, moments: CellMoments, cameras: list[CameraCloud], noise_factor: float
) -> np.ndarray:
    """Per cell, the information density (1 / (m^2 x m^2)) the cameras' points bring on its
    height: 0 where no camera saw it.

    `moments` are the fused points' per (cell, camera) counts and sums; each camera's mean
    height in the cell sets its range and drop to the cell (its noise, a few tenths of a
    metre against a drop of 5-10 m, barely moves them). On a grid finer than LEVEL_GRID_M
    (levels are read on blocks of about that size) a point informs its pixel's footprint:
    at 1 cm a pixel seen from 10 m covers several cells, most of which hold no point, so the
    coverage is counted per block and the block's information shared by its measured cells."""
    share = CORRELATED_SHARE * blob_area_px() + (1.0 - CORRELATED_SHARE)
    information = np.zeros(moments.n_cells)
    factor = max(1, round(LEVEL_GRID_M / grid.step))  # levels read on blocks of factor^2 cells
    block_cols = -(-grid.shape[1] // factor)
    for seen in _sightlines(grid, moments, cameras):
        pairs, cell, row, col, focal = seen.pairs, seen.cell, seen.row, seen.col, seen.focal
        depth, usable = _axis_depth(seen)
        # where the camera's every cell is usable (a bin's eave camera: all of them), the
        # masks below would copy each array as it is
        masked = _where_not_all(usable)
        depth, reach, drop = (masked(a, 1.0) for a in (depth, seen.reach, seen.drop))
        rms_v = depth_rms_m(depth, focal, noise_factor) * drop / depth  # vertical, per pixel
        pixel_area = np.square(reach / focal) * reach / drop  # a pixel's footprint on the ground
        variance_area = np.square(rms_v) * pixel_area * share
        if factor < 2:
            covered = np.minimum(1.0, moments.count[pairs] * pixel_area / grid.cell_area)
            contribution = masked(covered / variance_area, 0.0)
        else:  # a point informs its pixel's footprint, not just the cell it fell in
            block = ((row // factor) * block_cols + col // factor).astype(np.intp)  # cast once
            footprint = masked(moments.count[pairs] * pixel_area, 0.0)
            area = np.bincount(block, footprint)
            with np.errstate(invalid="ignore", divide="ignore"):
                per_area = np.bincount(block, footprint / variance_area) / area
                covered = np.minimum(1.0, area / (grid.cell_area * factor * factor))
                cells = np.bincount(block, usable.astype(np.float64))
                # the block's information, shared by the camera's cells in it (their mean
                # over the block's factor^2 cells is the block's)
                spread = covered * per_area * factor * factor / cells
            contribution = masked(spread[block], 0.0)
        # a camera has one pair a cell: a fancy-indexed add is right, and adds what a dense
        # bincount added to every cell (a 4 M-cell array a camera, 1 cm over a 20 m bin)
        # by an intp index: numpy casts an int32 one on both the gather and the scatter
        information[cell.astype(np.intp)] += contribution
    return information.reshape(grid.shape)


def point_spread(
    grid: Grid, moments: CellMoments, cameras: list[CameraCloud], noise_factor: float
) -> np.ndarray:
    """Per cell (flat), the RMS vertical error of one steadied point there (float32, 0 where
    no camera saw it): the D455's depth RMS at the range its cameras see it from, times the
    ray's vertical share, times the root of the share of it a steadied point keeps
    (`walls.kept_noise_share` of its image's box), RMS over the cell's points."""
    squares = np.zeros(moments.n_cells)
    points = np.zeros(moments.n_cells)
    for seen in _sightlines(grid, moments, cameras):
        depth, usable = _axis_depth(seen)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms_v = depth_rms_m(depth, seen.focal, noise_factor) * seen.drop / depth
        kept = kept_noise_share(window_px(int((seen.cloud.intrinsics or {})["width"])))
        count = np.where(usable, moments.count[seen.pairs], 0.0)
        # one pair a cell a camera: a fancy-indexed add, as `cell_information`'s
        cell = seen.cell.astype(np.intp)
        squares[cell] += count * np.where(usable, kept * rms_v * rms_v, 0.0)
        points[cell] += count
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.sqrt(squares / points)
    return np.where(points > 0, spread, 0.0).astype(np.float32)


def blob_scale(grid: Grid, moments: CellMoments, cameras: list[CameraCloud]) -> np.ndarray:
    """Per cell, how wide (Gaussian sigma, metres) the correlated noise blobs of the cameras
    that saw it are on the ground: CORRELATION_PX pixels' footprint, RMS over the cell's
    points; 0 where no camera saw it. The points of one blob share its error: a cell narrower
    than its blob holds one blob's points, and their mean is that blob's, not the surface's."""
    squares = np.zeros(moments.n_cells)
    points = np.zeros(moments.n_cells)
    for seen in _sightlines(grid, moments, cameras):
        cell, reach, drop = seen.cell, seen.reach, seen.drop
        usable = np.isfinite(drop) & (drop > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            pixel_area = np.square(reach / seen.focal) * reach / drop  # its ground footprint
        count = np.where(usable, moments.count[seen.pairs], 0.0)
        squares += np.bincount(cell, count * np.where(usable, pixel_area, 0.0), moments.n_cells)
        points += np.bincount(cell, count, moments.n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = CORRELATION_PX * np.sqrt(squares / points)
    return np.where(points > 0, scale, 0.0).reshape(grid.shape)
