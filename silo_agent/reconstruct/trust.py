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

import numpy as np

from silo_agent.base.d455 import CORRELATED_SHARE, blob_area_px, depth_rms_m
from silo_agent.grid.grid import Grid
from silo_agent.reconstruct.fuse import CellMoments
from silo_agent.scan import CameraCloud


def cell_information(
    grid: Grid, moments: CellMoments, cameras: list[CameraCloud], noise_factor: float
) -> np.ndarray:
    """Per cell, the information density (1 / (m^2 x m^2)) the cameras' points bring on its
    height: 0 where no camera saw it.

    `moments` are the fused points' per (cell, camera) counts and sums; each camera's mean
    height in the cell sets its range and drop to the cell (its noise, a few tenths of a
    metre against a drop of 5-10 m, barely moves them)."""
    xs, ys = grid.centres()
    cell, camera = moments.cell, moments.camera.astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = moments.sum_z / moments.count
    origins = np.array([c.extrinsic[:3, 3] for c in cameras], dtype=np.float64)
    axes = np.array([c.extrinsic[:3, 2] for c in cameras], dtype=np.float64)  # optical axes
    focal = np.array(
        [float(c.intrinsics["fx"]) if c.intrinsics else 1.0 for c in cameras], dtype=np.float64
    )
    o, axis, f = origins[camera], axes[camera], focal[camera]
    rel = np.column_stack([xs.ravel()[cell], ys.ravel()[cell], z]) - o
    depth = np.einsum("ij,ij->i", rel, axis)
    reach = np.linalg.norm(rel, axis=1)
    drop = -rel[:, 2]
    usable = np.isfinite(z) & (depth > 0) & (drop > 0)
    depth, reach, drop = (np.where(usable, a, 1.0) for a in (depth, reach, drop))
    rms_v = depth_rms_m(depth, 1.0, noise_factor) / f * drop / depth  # vertical, per pixel
    pixel_area = np.square(reach / f) * reach / drop  # one pixel's footprint on the ground
    variance_area = (
        np.square(rms_v)
        * pixel_area
        * (CORRELATED_SHARE * blob_area_px() + (1.0 - CORRELATED_SHARE))
    )
    covered = np.minimum(1.0, moments.count * pixel_area / grid.cell_area)
    information = np.where(usable, covered / variance_area, 0.0)
    return np.bincount(cell, information, moments.n_cells).reshape(grid.shape)
