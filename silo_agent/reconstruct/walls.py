"""Walls are never grain: drop the points a camera took of the bin's wall, whatever the depth
noise did to them. Pure numpy.

Depth noise moves a point along its camera ray; it never moves the ray. So a point is judged
by its ray, not by where the noise put it: the ray through a pixel leaves the bin through the
known wall at a height z_wall, and the pixel saw the wall exactly when z_wall is above the grain
there (the ray meets the wall before it comes down to the grain). Wall points thrown 0.5 m
inward at 10 m are dropped as surely as those on the wall; grain points right at the wall are
kept. The grain height at the wall comes from a first, coarse reconstruction made only of
points that are certainly not wall: each camera's depth image is rebuilt from its cloud (the
cloud is the image deprojected through the intrinsics), box-smoothed, and a pixel whose smoothed
depth is within the D455 noise (RMS = factor x z^2 x 0.08 / (f x 0.095 m)) of the wall's depth
along its ray is left out of that first pass.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from silo_agent.base.d455 import CORRELATED_SHARE, CORRELATION_PX, depth_rms_m
from silo_agent.grid.bin_shape import BinShape
from silo_agent.grid.filters import block_sums
from silo_agent.grid.grid import Grid
from silo_agent.grid.smooth import masked_smooth
from silo_agent.grid.volume import LEVEL_SCALES_M, level_surface
from silo_agent.scan import CameraCloud, rows_where

SMOOTHING_PX_AT_848 = 9  # box window over the depth image, scaled with the image width
SMOOTHED_NOISE_SHARE = 0.5  # D455 noise is spatially correlated: a 9 px box keeps about half
FIRST_PASS_SIGMAS = 3.0
FIRST_PASS_MIN_MARGIN_M = 0.10
WALL_CLEARANCE_M = 0.05  # a ray meeting the wall this far above the grain still saw grain
RESEAT_SCALE_M = 0.4  # the first pass's surface, smoothed at this scale, gives the slope
RESEAT_MIN_FALL = 0.1  # rays within ~6 deg of the surface are left where the noise put them
RESEAT_MAX_SIGMAS = 3.0  # no point moves along its ray by more than this many depth RMS
CHUNK_POINTS = 1 << 16  # per-point work a chunk at a time: its temporaries stay in cache
BARE_SCALE_M = 0.5  # bare steel is told from grain on the surface smoothed at this scale ...
BARE_SIGMAS = 4.0  # ... by standing within this many of that mean's noise sigmas of the steel
BARE_LINES_MEDIAN = 5  # a hopper's cut up the cone: the median of this many neighbouring lines
BARE_STEP_M = 0.02  # the cone is judged on cells at least this wide (a finer grid's pooled)


def smoothed_depth(
    cloud: CameraCloud, among: np.ndarray | None = None, window_at_848: int = SMOOTHING_PX_AT_848
) -> np.ndarray | None:
    """Each point's depth averaged (as disparity, 1 / depth: exact on a plane) over its pixel's
    neighbourhood in the camera's depth image, rebuilt from the cloud through the intrinsics,
    among the points in `among` (default all); None without intrinsics."""
    k = cloud.intrinsics
    if not k or not all(key in k for key in ("width", "height", "fx", "fy", "ppx", "ppy")):
        return None
    width, height = int(k["width"]), int(k["height"])
    points = cloud.points
    n = len(points)
    # each point's pixel and disparity, a chunk at a time, in float32 like the points: the
    # disparity 1 / z is float64's rounded to float32 (double rounding of a quotient from 53 to
    # 24 bits is exact), and a pixel's u = x / z * fx + ppx is off float64's by ~1e-4 px, which
    # rounds to the same pixel for every point that lies on a pixel's ray (a cloud deprojected
    # from its image: the same pixels, 8 cameras of 0.9 M points). 6.2 -> 4.2 ms a
    # full-resolution camera against float64 columns, with the disparity in it
    disparity = np.empty(n, dtype=np.float32)
    on_image = np.empty(n, dtype=bool)
    # numpy's own index type: an int32 index is cast on every scatter and gather (a
    # full-resolution camera's two of each: 8.6 -> 3.0 ms), for 4 more bytes a point
    pixel = np.empty(n, dtype=np.intp)
    column = np.empty(n, dtype=np.intp)  # u * height + v: the pixel in the transposed image
    fx, fy, ppx, ppy = (np.float32(k[key]) for key in ("fx", "fy", "ppx", "ppy"))
    for start in range(0, n, CHUNK_POINTS):
        rows = slice(start, start + CHUNK_POINTS)
        depth = points[rows, 2]
        inverse = disparity[rows]  # a view: written in place
        with np.errstate(divide="ignore", invalid="ignore"):  # in place: x / z * fx + ppx
            np.divide(np.float32(1.0), depth, out=inverse)
            u = points[rows, 0] * inverse
            u *= fx
            u += ppx
            np.rint(u, out=u)
            v = points[rows, 1] * inverse
            v *= fy
            v += ppy
            np.rint(v, out=v)
        valid = on_image[rows]  # a view: written in place
        np.greater(depth, 0, out=valid)
        valid &= u >= 0
        valid &= u < width
        valid &= v >= 0
        valid &= v < height
        off = ~valid
        with np.errstate(invalid="ignore"):  # inf - inf at z = 0: off the image
            across = u * np.float32(height)  # exact: a pixel's index is below 2^24
            across += v
            v *= width
            v += u
        v[off] = 0  # off the image: any pixel, never read
        across[off] = 0
        pixel[rows] = v
        column[rows] = across
    if among is not None:
        on_image &= among
    # a cloud deprojected from its image lies on it: then a slice, not a gather per array
    on: slice | np.ndarray = slice(None) if np.all(on_image) else np.flatnonzero(on_image)
    del on_image
    pixel = pixel[on]
    column = column[on]
    if len(pixel) == 0:
        return points[:, 2].astype(np.float64)
    size = window_px(width, window_at_848)
    # only the image's rows from half a window above the first row with a point to half a
    # window below the last: outside them both planes are zero, and scipy's running sums
    # (float64, exactly zero until the first value enters the window) give the kept rows
    # the very values of the whole image's filter. A camera's wall-free points leave its top
    # rows (the far wall): 40 % of them over the 20 m bin
    top = max(0, int(pixel.min()) // width - size // 2 - 1)
    bottom = min(height, int(pixel.max()) // width + size // 2 + 2)
    if top:
        pixel -= top * width
    # float32 planes: scipy sums each window in float64 and rounds the mean to float32 after
    # each of its two passes (a depth off by ~1e-7 of itself, a micrometre at 10 m), at 16 ms
    # a 1280x720 image against 25
    image = np.zeros((2, width * height), np.float32)
    inverse, seen = image  # views
    inverse[column] = disparity[on]
    del disparity
    seen[column] = 1.0
    del inverse, seen, column
    # the image transposed (a pixel's column contiguous) for scipy's first pass, down the
    # columns, then transposed once for its second, along the rows: each pass runs along
    # contiguous lines, the same lines in the same order as on the upright image, so the very
    # same values. A pass across the lines' stride was two thirds of the filter: 12 m bin,
    # 8 full-resolution cameras, 1 cm, one core: 24 calls in `process` 0.34-0.40 -> 0.25-0.29
    # s, 21 -> 16.5 ms a full camera
    down = image.reshape(2, width, height)[:, :, top:bottom]
    ndimage.uniform_filter1d(down, size, axis=2, mode="constant", output=down)
    planes = np.ascontiguousarray(down.transpose(0, 2, 1))
    del image, down
    # in place, as scipy runs its own passes: a line at a time through a buffer
    ndimage.uniform_filter1d(planes, size, axis=2, mode="constant", output=planes)
    total, count = planes
    del planes
    # the mean disparity's inverse at the points' pixels only, not over the whole image
    mean = np.divide(np.take(count.ravel(), pixel), np.take(total.ravel(), pixel), dtype=np.float64)
    if isinstance(on, slice):  # every point's: no float64 copy of the depths to write into
        return mean
    z = points[:, 2].astype(np.float64)
    z[on] = mean
    return z


def _ray_walls(
    points: np.ndarray, rotation: np.ndarray, origin: np.ndarray, shape: BinShape
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the rays through camera-frame `points` meet the wall: (depth along the ray,
    silo-frame x, y, z), -inf height for a ray that never does. Point by point: the same for a
    point in any chunk of a cloud (what WallCrossing's exact look-up relies on)."""
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = np.float32(1.0) / z  # the ray through a point, scaled to camera z = 1
    across, down = points[:, 0] * inverse, points[:, 1] * inverse
    # column by column: a (N, 3) @ (3, 3) product is BLAS with an inner dimension of 3, slow
    dx, dy, dz = (r[0] * across + r[1] * down + r[2] for r in rotation.astype(np.float32))
    depth = shape.ray_wall_depth(float(origin[0]), float(origin[1]), dx, dy)
    finite = np.isfinite(depth)
    reach = np.where(finite, depth, 0.0)
    wall_x, wall_y = origin[0] + dx * reach, origin[1] + dy * reach
    wall_z = np.where(finite, origin[2] + dz * reach, -np.inf)
    return depth, wall_x, wall_y, wall_z


def _clear_of_wall(
    smoothed: np.ndarray | None, depth: np.ndarray, focal: float, noise_factor: float
) -> np.ndarray:
    """The first pass's verdict: a point's smoothed depth short of the wall's (`depth` along
    its ray) by FIRST_PASS_SIGMAS of the smoothed depth noise there."""
    if smoothed is None:
        return np.ones(len(depth), dtype=bool)
    rms = depth_rms_m(np.where(np.isfinite(depth), depth, 0.0), focal, noise_factor)
    margin = np.maximum(FIRST_PASS_MIN_MARGIN_M, FIRST_PASS_SIGMAS * SMOOTHED_NOISE_SHARE * rms)
    return np.asarray(smoothed < depth - margin)


def with_points(cloud: CameraCloud, keep: np.ndarray) -> CameraCloud:
    """`cloud` with only the points in `keep`, a mask or row indices (colours alike)."""
    colors = rows_where(cloud.colors, keep) if cloud.colors is not None else None
    return replace(cloud, points=rows_where(cloud.points, keep), colors=colors)


def window_px(width: int, window_at_848: int = SMOOTHING_PX_AT_848) -> int:
    """`smoothed_depth`'s box side in pixels on an image `width` wide: odd, at least 3."""
    return max(3, 2 * round(window_at_848 * width / 848 / 2) + 1)


def kept_noise_share(size: int) -> float:
    """The share of a pixel's disparity noise variance that a mean over a `size` x `size` box
    keeps, from the D455 model (base/d455.py): the independent part (1 - CORRELATED_SHARE)
    over the box's pixels, and the correlated part (blobs, Gaussian-smoothed noise of sigma
    CORRELATION_PX, whose correlation at a lag of r px is exp(-r^2 / (4 sigma^2))) times its
    mean correlation over the box's pairs of pixels: a 9 px box keeps 0.35."""
    lags = np.arange(size)[:, None] - np.arange(size)[None, :]
    mean_correlation = float(np.mean(np.exp(-(lags**2) / (4 * CORRELATION_PX**2)))) ** 2
    return (1 - CORRELATED_SHARE) / size**2 + CORRELATED_SHARE * mean_correlation


def steadied(cloud: CameraCloud, noise_factor: float) -> CameraCloud:
    """Each point moved along its ray to its pixel neighbourhood's mean disparity, less the
    depth skew the noise left in that mean.

    Depth noise moves points along their rays, and where the grain ends at the wall a cell by
    the far wall gets the points noise pushed down towards it from nearer grain but none from
    beyond the wall: it reads low (by up to a third of the noise at 10 m). Averaging in the
    image, among grain pixels only, takes noise out before the points are placed; on a plane
    the mean disparity is exact. Cost: a 9 px box (at 848 wide) rounds a heap's apex by ~1 cm.

    The mean disparity is unbiased, its inverse not: a stereo camera errs in disparity, and a
    disparity known to a variance v reads, inverted, a depth z + z^3 v too far on average
    (sigma_z^2 / z for sigma_z = z^2 sqrt(v), the skew of a raw pixel's depth). The box keeps
    `kept_noise_share` of a pixel's variance (its blobs are about as wide as it), so each
    point is brought back by that share of sigma_z^2 / z, sigma_z the D455's at its depth
    (`depth_rms_m`, `noise_factor` times the ideal target's): 6 mm at 9 m from an eave
    camera, 2.5x the ideal target's noise. Left in, reseating keeps it in every point's
    height above the first surface (`reseated`): the volume's bias (antithetic noise pairs,
    four cameras) was -1.39 % on a drawn-down hopper's crater, -0.47 % on a 10 m bin's heap,
    now -0.19 % and -0.30 %. Cost: a noise factor set too high (or too low) reads the grain as much
    too near (far) as the skew it assumes: a factor off by 20 % moves 9 m grain by 2-3 mm.
    """
    depth = smoothed_depth(cloud)
    if depth is None:
        return cloud
    k = cloud.intrinsics or {}
    share = kept_noise_share(window_px(int(k["width"])))
    with np.errstate(divide="ignore", invalid="ignore"):  # depth 0: off the image, kept as is
        skew = share * np.square(depth_rms_m(depth, float(k["fx"]), noise_factor)) / depth
    depth -= np.where(depth > 0, skew, 0.0)
    z = cloud.points[:, 2].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(z > 0, depth / z, 1.0)
    # computed in float64 and rounded to float32 on the way out, as a float64 product cast
    # after; a column at a time, not broadcast over (N, 3) rows (numpy's inner loop three
    # values long): the same values, 1.9 -> 1.1 ms for 0.42 M points
    points = np.empty_like(cloud.points)
    for axis in range(3):
        np.multiply(cloud.points[:, axis], scale, out=points[:, axis])
    return replace(cloud, points=points)


def cell_inward(
    shape: BinShape, grid: Grid, x: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) of the cell whose surface gives the grain height at wall points (x, y):
    1.5 cells inward, towards the bin's centre (a polygon's: its vertices' mean), so the cell
    is inside. The distance by sqrt(dx^2 + dy^2), not np.hypot: glibc's scalar hypot (~20 ns a
    point) was most of this function's time; the square root is at most 1 ulp off it."""
    if shape.diameter_m is not None:
        cx, cy = shape.centre
    else:
        cx, cy = np.mean(shape.wall_polygon(), axis=0)
    dx, dy = cx - x, cy - y
    length = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-9)
    pull = np.minimum(1.5 * grid.step, length)
    row, col = grid.cell_index(x + dx / length * pull, y + dy / length * pull)
    rows, cols = grid.shape
    return np.clip(row, 0, rows - 1), np.clip(col, 0, cols - 1)


@dataclass(frozen=True)
class WallCrossing:
    """What `wall_free` reads of one camera's rays, per point: the cell of the first pass's
    grid that gives the grain height at the wall there (`cell_inward`'s), and the height at
    which the ray meets the wall, rounded to float32. 6 bytes a point (8 on a grid of over
    65536 cells) where a whole cloud's float64 rays took 29: they are kept through the first pass (8
    full-resolution cameras: 44 MB against 214 MB).

    The height is float64 where it is computed; rounded, it is off by at most half a float32
    step (0.5 um at 8 m), and `wall_free` computes it again, exactly, for the few points
    whose rounded height is within two steps of their grain height: its verdicts are the
    float64 height's."""

    cell: np.ndarray  # (N,) uint16 or int32 flat index into the first pass's grid (_cell_of)
    wall_z: np.ndarray  # (N,) float32, rounded from the float64 height

    def every(self, stride: int) -> WallCrossing:
        """The crossings of every `stride`-th point."""
        return self if stride < 2 else WallCrossing(self.cell[::stride], self.wall_z[::stride])

    @classmethod
    def of_cloud(
        cls, cloud: CameraCloud, shape: BinShape, grid: Grid, noise_factor: float
    ) -> tuple[WallCrossing, np.ndarray]:
        """A camera's crossings and which of its points are certainly clear of the wall
        (`_clear_of_wall`), a chunk of points at a time: the rays' float64 columns
        never exist for the whole cloud (the wall step's peak: 95 -> 30 bytes a point)."""
        rotation, origin = cloud.extrinsic[:3, :3], cloud.extrinsic[:3, 3]
        focal = float(cloud.intrinsics["fx"]) if cloud.intrinsics else 1.0
        smoothed = smoothed_depth(cloud)
        n = len(cloud.points)
        cell = np.empty(n, dtype=_cell_dtype(grid))
        wall_z = np.empty(n, dtype=np.float32)
        clear = np.empty(n, dtype=bool)
        for start in range(0, n, CHUNK_POINTS):
            rows = slice(start, start + CHUNK_POINTS)
            depth, x, y, z = _ray_walls(cloud.points[rows], rotation, origin, shape)
            cell[rows] = _cell_of(shape, grid, x, y)
            wall_z[rows] = z
            near = None if smoothed is None else smoothed[rows]
            clear[rows] = _clear_of_wall(near, depth, focal, noise_factor)
        return cls(cell, wall_z), clear


def _cell_of(shape: BinShape, grid: Grid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """`cell_inward`'s cell as a flat index into `grid`: uint16 where the grid's cells fit
    (a first pass's 10 cm grid over a bin up to 25 m across), else int32 (base/limits.py)."""
    row, col = cell_inward(shape, grid, x, y)
    cell = row.astype(_cell_dtype(grid))
    cell *= grid.shape[1]
    cell += col.astype(cell.dtype)
    return cell


def _cell_dtype(grid: Grid) -> type[np.integer]:
    return np.uint16 if grid.shape[0] * grid.shape[1] <= 1 << 16 else np.int32


def _below_wall(
    cloud: CameraCloud, ray: WallCrossing, shape: BinShape, limit: np.ndarray
) -> np.ndarray:
    """Whether each point's ray meets the wall at or below `limit`: judged on the rounded
    height, and where that is within two float32 steps of `limit`, on the exact one.

    Two float32 steps of a height are at most 2^-22 of it (2^-148 below the normal range),
    so a gap within two steps is within 2^-21 max|limit| + 2^-148: np.spacing only on the
    few points within that, not on every point (8.7 -> 5.0 ms for 0.9 M points, the same
    verdicts)."""
    keep = ray.wall_z <= limit
    gap = ray.wall_z - limit
    np.abs(gap, out=gap)
    largest = float(np.max(np.abs(limit))) if len(gap) else 0.0
    # a limit not finite: every point is a candidate (NaN compares false, as before)
    bound = np.ldexp(largest, -21) + 2.0**-148 if np.isfinite(largest) else np.inf
    near = np.flatnonzero(gap <= bound)
    rows = near[gap[near] <= 2 * np.abs(np.spacing(ray.wall_z[near]))]
    if len(rows):
        rotation, origin = cloud.extrinsic[:3, :3], cloud.extrinsic[:3, 3]
        exact = _ray_walls(cloud.points[rows], rotation, origin, shape)[3]
        keep[rows] = exact <= limit[rows]
    return keep


def wall_free(
    cameras: list[CameraCloud],
    crossings: list[WallCrossing],
    shape: BinShape,
    heights: np.ndarray,
    noise_factor: float,
) -> tuple[list[CameraCloud], int]:
    """The cameras without the points whose ray met the wall above the grain (`heights`, a
    first filled surface on the grid of the crossings' cells), `steadied`, and how many points
    went. Consumes `crossings`: each camera's go as soon as it is judged (the list ends
    empty)."""
    if len(crossings) != len(cameras):
        raise ValueError(f"{len(cameras)} cameras, {len(crossings)} crossings")
    out, dropped = [], 0
    for cloud in cameras:
        ray = crossings.pop(0)
        level = np.take(heights.ravel(), ray.cell)  # uint16 or int32: take casts it fastest
        level = np.where(np.isfinite(level), level, shape.floor_z)
        level += WALL_CLEARANCE_M
        keep = _below_wall(cloud, ray, shape, level)
        del ray, level
        dropped += int(len(keep) - keep.sum())
        out.append(steadied(with_points(cloud, keep), noise_factor))
    return out, dropped


@dataclass(frozen=True)
class FirstSurface:
    """The first pass's surface as `reseated` reads it, built once for all cameras: its level
    (measured where measured, else smoothed) and its slope (from the smoothed surface)."""

    grid: Grid
    level: np.ndarray
    slope_x: np.ndarray
    slope_y: np.ndarray

    @classmethod
    def of(cls, grid: Grid, heights: np.ndarray, level: np.ndarray | None = None) -> FirstSurface:
        """The slope from `heights` smoothed, the level `level` (`reseat_level`; default
        `heights`) where it has one, else the smoothed surface.

        Beyond the wall (no heights) the smoothed surface carries on at the nearest known
        cell's height, so the slope at the wall's last cells is the grain's own: it was the
        whole surface's mean there, 0.14-0.16 m above the ring by the wall of a 10 m bin with a
        heap, and the points seen there were reseated along a false slope."""
        known = np.isfinite(heights)
        smooth = masked_smooth(heights, known, max(RESEAT_SCALE_M / grid.step, 1.0))
        smooth = _extended(smooth)
        grad_y, grad_x = np.gradient(smooth, grid.step)  # the slope from the smoothed surface
        # ... the level not: a crater's tip stays sharp
        level = heights if level is None else level
        return cls(grid, np.where(np.isfinite(level), level, smooth), grad_x, grad_y)

    @functools.cached_property
    def bilinear(self) -> np.ndarray:
        """(12, cells) float64: for each of level, slope_x, slope_y, the coefficients
        (a, b, d, e) of the bilinear patch a + b t + d s + e s t per cell (r, c) between the
        cell centres (r, c), (r, c + 1), (r + 1, c), (r + 1, c + 1), s and t in [0, 1] down the
        rows and the columns; the last row and column repeat the edge (`map_coordinates`' mode
        "nearest" on coordinates clamped to the grid). A coefficient's row is a table of the
        grid's cells: `_surface_at` gathers each into a column of its own."""
        rows, cols = self.level.shape
        table = np.empty((3, 4, rows, cols))
        for k, values in enumerate((self.level, self.slope_x, self.slope_y)):
            padded = np.pad(values, ((0, 1), (0, 1)), mode="edge")
            v00, v01 = padded[:-1, :-1], padded[:-1, 1:]
            v10, v11 = padded[1:, :-1], padded[1:, 1:]
            table[k, 0] = v00
            table[k, 1] = v01 - v00
            table[k, 2] = v10 - v00
            table[k, 3] = (v11 - v10) - (v01 - v00)
        return table.reshape(12, rows * cols)


def _extended(values: np.ndarray) -> np.ndarray:
    """`values` with each NaN cell given its nearest finite cell's value (all NaN: zeros)."""
    missing = ~np.isfinite(values)
    if not np.any(missing):
        return values
    if np.all(missing):
        return np.zeros_like(values)
    nearest = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
    return values[tuple(nearest)]


def _surface_at(
    first: FirstSurface, x: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(level, slope_x, slope_y) of `first` at silo-frame (x, y), bilinear between the cell
    centres, clamped at the grid's edge: what `ndimage.map_coordinates(order=1,
    mode="nearest")` gives each of them, to within the last bits of a float64.

    Own code, not map_coordinates: the three share one look-up and one pair of weights, where
    map_coordinates computes the weights and gathers the corners again for each array. On the
    20 m bin's 16 cameras at 1 cm (the bench's clouds: 0.42 M points reseated per camera) a
    whole `reseated` takes 32-35 ms with it against 50-54 ms with three map_coordinates calls
    on the same chunks: 2-3x less for the interpolation itself. Each coefficient is gathered
    from its own row of the table (a cell's 12 in one gather made a chunk's 65536 x 96-byte
    patch, read back a strided column at a time): the same values, 12 m bin / 8 cameras at
    1 cm, 64 calls in process 0.22-0.28 -> 0.14 s."""
    rows, cols = first.level.shape
    s = (y - first.grid.origin[1]) / first.grid.step - 0.5
    t = (x - first.grid.origin[0]) / first.grid.step - 0.5
    np.clip(s, 0, rows - 1, out=s)
    np.clip(t, 0, cols - 1, out=t)
    row, col = s.astype(np.intp), t.astype(np.intp)  # the floor: s, t >= 0
    s -= row
    t -= col
    row *= cols
    row += col
    table = first.bilinear
    out = []
    for k in range(3):  # NaN coordinates: no error (mode "clip")
        across = np.take(table[4 * k + 3], row, mode="clip")
        across *= t
        across += np.take(table[4 * k + 2], row, mode="clip")
        across *= s
        value = np.take(table[4 * k + 1], row, mode="clip")
        value *= t
        value += np.take(table[4 * k], row, mode="clip")
        value += across
        out.append(value)
    return out[0], out[1], out[2]


def reseat_level(
    grid: Grid,
    heights: np.ndarray,
    observed: np.ndarray,
    information: np.ndarray,
    blob: np.ndarray,
) -> np.ndarray:
    """The level a bin's points are reseated on: the first pass's `heights`, but where the
    cameras' noise blobs (`blob`, trust.blob_scale) are wider than the finest scale a level is
    read at (LEVEL_SCALES_M[0]), the observed cells averaged as a bin's levels are
    (`level_surface`: weighted by their `information`, over the widest scale that agrees
    with every finer one).

    A point is reseated to undo what noise did to where it landed, and noise moves a blob
    of points together: at 15-18 m from an eave camera a blob pushed away from it lands low
    and spread thin over cells of one or two points that border holes, one pushed nearer
    lands high and dense. Levelled on such a cell's own mean, the blob's points stay where
    they landed (the level is their own mean): an 18 m bin's four corners between the eave
    cameras, seen only from there, read 0.2-0.3 m low in their sparse cells and in the holes
    filled from them (-0.4 to -1 % of the volume). Averaged over more than a blob, the level
    is set by many blobs and each point moves by its own error. Where the blobs are smaller
    (a 10 m bin's grain seen from 5-9 m) the cell's own mean already averages several, and
    keeps a crater's tip and a hopper's crease sharp."""
    measured = observed & np.isfinite(heights) & (information > 0)
    averaged = level_surface(grid, heights, measured, information)[0]
    wide = measured & (blob > LEVEL_SCALES_M[0]) & np.isfinite(averaged)
    return np.where(wide, averaged, heights)


def reseated(cloud: CameraCloud, first: FirstSurface, noise_factor: float) -> CameraCloud:
    """Each point moved along its own ray to where that ray meets the first surface, keeping
    its measured height above that surface.

    Depth noise moves a point along its ray, and so across the floor: at 8-10 m from an eave
    camera by 0.1-0.3 m. Binned where the noise put it, a cell's points come from its
    neighbours too, more from the side the camera sees more densely (the flank of a crater
    that faces it): a draw-down crater at 8-9 m read 1-2 cm high over its whole area (2-4 %
    of a hopper's small volume). Placed where its ray meets the first surface, a point lands
    in the cell its pixel saw; its height is that surface's there plus its own residual (one
    Newton step along the ray, the slope read on the surface smoothed at RESEAT_SCALE_M), so
    the first surface's own error cancels and only its slope matters. Rays within ~6 deg of the
    surface stay put; no point moves more than 3 depth RMS. Cost: a bilinear look-up and a
    transform per point."""
    rotation, origin = cloud.extrinsic[:3, :3], cloud.extrinsic[:3, 3]
    focal = float(cloud.intrinsics["fx"]) if cloud.intrinsics else 1.0
    n = len(cloud.points)
    points = np.empty((n, 3), np.float32)
    at = origin[:, None]
    for start in range(0, n, CHUNK_POINTS):  # point by point: a chunk's temporaries stay in cache
        rows = slice(start, start + CHUNK_POINTS)
        # the coordinates as rows (3, N), not columns: an (N, 3) array's arithmetic with a
        # column or a row broadcast runs numpy's inner loop three values at a time (7-9x the
        # time of a flat one); the same values, the rays' product with R as before
        silo = cloud.points_in_silo(rows).T.astype(np.float64, order="C")
        depth = cloud.points[rows, 2].astype(np.float64)
        level, slope_x, slope_y = _surface_at(first, silo[0], silo[1])
        with np.errstate(divide="ignore", invalid="ignore"):  # in place, each value as written
            ray = silo - at
            ray /= depth  # silo-frame ray per unit of camera depth
            rise = slope_x * ray[0]
            rise += slope_y * ray[1]  # surface rise per unit depth
            fall = rise - ray[2]  # how fast the ray closes on the surface
            shift = silo[2] - level
            shift /= fall  # along the ray to the first surface
        bound = RESEAT_MAX_SIGMAS * depth_rms_m(depth, focal, noise_factor)
        usable = np.isfinite(shift) & (fall > RESEAT_MIN_FALL) & (depth > 0)
        shift = np.where(usable, np.clip(shift, -bound, bound), 0.0)
        moved = ray
        moved *= shift
        moved += silo
        moved[2] = silo[2] + shift * rise
        moved -= at
        # back to the camera frame: R^T (p - o), row-wise, on (N, 3) rows as before
        points[rows] = np.ascontiguousarray(moved.T) @ rotation
    return replace(cloud, points=points)


def bare_bottom(
    grid: Grid,
    shape: BinShape,
    heights: np.ndarray,
    observed: np.ndarray,
    bottom: np.ndarray,
    information: np.ndarray,
    repose_slope: float,
) -> np.ndarray:
    """The measured cells that are a hopper's bare cone, not grain: left to the fill, which
    the steel holds up, they count nothing (none without a hopper steeper than `repose_slope`).

    Grain cannot lie on a cone steeper than its angle of repose in a thin layer (a hopper is
    built so that it slides off): where its surface meets the steel it leaves it as a wedge
    (a crater's rim in a drawn-down hopper), and up the cone from bare steel there is none. A
    measured cell of bare steel reads the steel plus noise, and counts that noise into the
    volume: clipped at the steel, the half above it, and over a ring of bare cone the noise
    blobs of 8-10 cm a few metres from an eave camera average to +-3 mm, +-5 mm with a 0.1 deg
    placement error (a hopper drawn down: 27 m^2 of bare cone around 11 m^3 of grain, +-1 %).

    A cell looks thin where its measured `heights`, averaged over BARE_SCALE_M, stand within
    BARE_SIGMAS of that mean's noise (from the cameras' `information`, trust.py) of the
    `bottom` (four: a 0.1 deg placement error adds its own offset to the steel, and at three
    5-10 % of a drawn-down hopper's bare cone looked thick). Noise makes some bare cells look
    thick and some grain thin, and keeping the thick-looking ones of a bare cone kept exactly
    those that read high; so the cone is cut along each of its lines of steepest ascent
    (`BinShape.uphill_lines`, sectors BARE_SCALE_M wide at the wall) at the one point above
    which it is bare: where the fewest cells look thin below it and thick above. The contact
    moves little from a line to the next, and a line takes the median cut of BARE_LINES_MEDIAN
    around it. The wedge's edge, averaged, looks thicker than it is: the cut falls up to a few
    tenths of a metre up the steel, whose cells below it count their noise as before; where
    the cone is barely steeper than the repose, it may fall on the wedge's thin edge, whose
    cells are then filled from the grain beside them.

    The cone is judged on cells at least BARE_STEP_M wide, so a finer grid finds the same cut:
    the lines count cells, and where a fine grid's cells hold a point in one of three (5 mm,
    8-10 m away) the mean of a few measured cells was taken for better known than it is and
    the bare cone's noise for grain (hopper-low, four cameras, 0.1 deg / 3 mm: +2.26 % at 5 mm
    against +1.42 % at 1 cm). A wider cell holds its measured cells' mean height and their
    information; the cut is read back onto the measured fine cells."""
    none = np.zeros(grid.shape, dtype=bool)
    if shape.floor != "hopper" or not shape.hopper_depth_m > 0:
        return none
    k = int(np.ceil(BARE_STEP_M / grid.step - 1e-9))
    if k > 1:
        count = block_sums(observed.astype(np.float64), k)
        with np.errstate(invalid="ignore", divide="ignore"):
            wide_heights = block_sums(np.where(observed, heights, 0.0), k) / count
        wide = Grid(grid.origin, grid.step * k, count.shape, block_sums(grid.inside, k) / k**2)
        wide_bare = bare_bottom(
            wide,
            shape,
            wide_heights,
            count > 0,
            shape.bottom(*wide.centres()),
            block_sums(np.where(observed, information, 0.0), k) / k**2,  # a density: per area
            repose_slope,
        )
        rows, cols = grid.shape
        return np.repeat(np.repeat(wide_bare, k, axis=0), k, axis=1)[:rows, :cols] & observed
    x, y = grid.centres()
    candidates = observed & (shape.bottom_slope(x, y) > repose_slope)
    if not np.any(candidates):
        return none
    scale = max(BARE_SCALE_M / grid.step, 1.0)
    measured = observed & (information > 0)
    relative = masked_smooth(np.where(observed, heights - bottom, 0.0), observed, scale)
    # a mean over area A of a surface known with information density I is known to
    # 1 / sqrt(A I); a Gaussian of sigma s weighs an area of 4 pi s^2, and the harmonic mean
    # of I over it sets the noise
    spread = np.divide(1.0, information, out=np.zeros(grid.shape), where=measured)
    variance = masked_smooth(spread, measured, scale) / (4 * np.pi * BARE_SCALE_M**2)
    with np.errstate(invalid="ignore"):  # NaN away from any measured cell: not thin
        thin = relative < BARE_SIGMAS * np.sqrt(variance)
    cells = np.flatnonzero(candidates)
    line, along, lines = shape.uphill_lines(x.ravel()[cells], y.ravel()[cells], BARE_SCALE_M)
    order = np.lexsort((along, line))
    line, along, looks = line[order], along[order], thin.ravel()[cells[order]]
    starts = np.flatnonzero(np.r_[True, line[1:] != line[:-1]])
    sizes = np.diff(np.r_[starts, len(line)])
    group = np.repeat(np.arange(len(starts)), sizes)
    below = np.arange(len(line)) - starts[group]  # the line's cells below each
    thin_below: np.ndarray = np.cumsum(looks) - looks
    thin_below -= thin_below[starts][group]
    # cut just below a cell: its thin cells below are grain that looked thin, its thick ones
    # from it up bare steel that looked thick; up to a constant of the line, 2 thin_below - below
    cost = 2 * thin_below - below
    best = np.lexsort((-below, cost, group))  # per line, the least cost, the highest cut on a tie
    first = best[np.r_[True, group[best][1:] != group[best][:-1]]]
    total_thin = np.add.reduceat(looks.astype(np.intp), starts)
    found = np.where(cost[first] < 2 * total_thin - sizes, along[first], np.inf)  # else none
    # the contact moves little from a line to the next (the grain's surface along it rises no
    # faster than its repose): a line whose noise hid or moved its cut takes its neighbours'
    cuts = np.full(lines, np.inf)
    cuts[line[starts]] = found
    cuts = ndimage.median_filter(cuts, BARE_LINES_MEDIAN, mode="wrap")
    cut = cuts[line[starts]]
    bare = np.zeros(len(cells), dtype=bool)
    bare[order] = along >= cut[group]
    out = none
    out.ravel()[cells] = bare
    return out
