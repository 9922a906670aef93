"""The incremental live height map. Pure numpy: depth frames in, a map with its layers out.

A full scan takes a 9-frame median per camera and clusters every cell's points; a robot moves
between those frames, and the work is far too much for 2 maps a second. Here every map costs one
pass over the newest frame of each camera:

- every valid depth pixel goes to its cell through a ray table precomputed per camera (silo
  frame, z = 1 scale), so a point costs three multiply-adds; the frame's cell height is the
  mean of its points, each weighted by 1 / its D455 depth variance (the RMS grows with range
  squared: a far camera's point counts a sixteenth of one at half the range), with the
  variance of that mean; each cell's running value carries its variance along;
- each cell keeps a running value: the mean of its first frame heights, then an exponential
  average of them (noise down by sqrt(smoothing / (2 - smoothing))), replaced by the frame
  height when it is more than `reset_m` away and confirmed, by most of its neighbours
  jumping the same way or by the previous frame (the rake just cut it: a moving scene cannot
  wait for an average to catch up; one noisy cell in one frame does not count);
- depth pixels along a depth edge (a robot's rim against the grain behind it) that may read
  between the two surfaces are dropped (`mixed_pixels`, judged in disparity);
- the robot is found from depth alone, as a compact object with steep sides standing at least
  `robot_min_height_m` above the local surface (a morphological top-hat wider than the robot,
  grain never rising more steeply than its angle of repose); its cells and the disc of
  `robot_radius_m` around their centre (a robot on a slope shows less than its whole top), plus
  `robot_margin_m`, swept ahead along its tracked motion for `hold_ahead_s`, are held at their
  last good value, at most the local median and the nearest trusted value (`_trusted`: the
  local noise-weighted mean of the values measured with no robot near, less a share of their
  RMS: a far camera's one noisy reading of a grain cell does not stand under the robot), and
  marked in the `held` layer; a
  site's YOLO model (live/model.py) adds its robot boxes, placed through the depth under them
  (`sighting_of`), and a model sighting alone holds its disc as a depth one does;
- `changed` marks the cells more than `change_m` from the value they had when last reported
  changed, so a slow drift is reported once it adds up, not lost under the threshold.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from silo_agent.base.d455 import BASELINE_M, CORRELATED_SHARE, depth_rms_m
from silo_agent.config import LiveConfig
from silo_agent.grid.bin_shape import BinShape
from silo_agent.grid.grid import Grid
from silo_agent.grid.heightmap import HeightMap
from silo_agent.reconstruct.walls import (
    FIRST_PASS_MIN_MARGIN_M,
    FIRST_PASS_SIGMAS,
    WALL_CLEARANCE_M,
    cell_inward,
)

if TYPE_CHECKING:
    from silo_agent.sim.camera import Frame

WALL_LEVEL_M = 0.5  # the grain by a bin's wall: the map opened over this width (below)
ROBOT_STEEP_M = 0.12  # rise of the top-hat within ROBOT_STEEP_CELLS that no grain slope makes
# ... 3 cells, not 2: seen from eave cameras 5-6 m away, the robot's rim spreads over 3 cells of
# 2 cm, and with 2 an 8 m bin's map found only 10 of the 20 steep cells a robot needs and let
# it in, 0.3 m high (bench/results/live-robot.md); 0.12 m within 6 cm is still a 63 deg slope
ROBOT_STEEP_CELLS = 3
ROBOT_MIN_EDGE_M = 0.4  # steep edge a robot shows at least (a fifth of a 0.6 x 0.4 m outline)
ROBOT_AREA_M2 = (0.04, 1.0)  # a robot's top, its noisy edge, a heap's tip it stands on
ROBOT_TOPHAT_M = 0.45  # a square this wide fits in no 0.4 m wide robot: the opening removes it
MIN_POINTS = 1  # a frame's cell height needs this many points
SPARSE_NEIGHBOURS = 4  # a one-point cell needs this many measured neighbours (of 8)
REFILL_GROWTH = 0.01  # share of the grid newly measured that renews the hole-filling table
TRUST_RMS_M = 0.05  # a cell measured within this RMS with no robot near may stand under it
TRUST_SIGMAS = 0.75  # ... at most this many RMS below its block's noise-weighted mean
TRUST_CELLS = 11  # a newly held cell's value: at most its block's trusted, noise-weighted mean
MIN_VARIANCE_M2 = 1e-6  # a cell's variance as a weight: the noise's correlated part keeps
# any cell above 1 mm RMS
ROBUST_CELLS = 5  # a newly held cell's value: at most the median of this block around it
MAX_ROBOT_SPEED_M_S = 1.5  # a sighting farther from the last one than this is another robot
JUMP_MIN_VOTES = 3  # cells of a 3 x 3 block, and two thirds of those measured, jumping the
# same way: a real change, not noise


@dataclass(frozen=True)
class DepthFrame:
    """One camera's newest depth image and where the camera is."""

    serial: str
    depth: np.ndarray  # (H, W) uint16, 0 = invalid
    depth_unit_m: float
    fx: float
    fy: float
    ppx: float
    ppy: float
    extrinsic: np.ndarray  # 4x4 camera -> silo
    color: np.ndarray | None = None  # (h, w, 3) uint8 RGB aligned to depth (any size), if any

    @classmethod
    def rendered(
        cls, serial: str, frame: Frame, extrinsic: np.ndarray, color: np.ndarray | None = None
    ) -> DepthFrame:
        """A simulated camera's frame as the live map takes it, placed by `extrinsic`."""
        k = frame.intrinsics
        return cls(
            serial, frame.depth, frame.depth_unit_m, k.fx, k.fy, k.ppx, k.ppy, extrinsic, color
        )


@dataclass(frozen=True)
class RobotSighting:
    """Where the robot is: centroid of its raised cells, its top, and their extent."""

    x: float
    y: float
    top_z: float
    radius_m: float  # of the disc around its cells, margin not included
    cells: int
    by: str = "depth"  # which detectors saw it: "depth", "model" or "depth+model"

    def to_json(self) -> dict[str, Any]:
        return {
            "x": round(self.x, 3),
            "y": round(self.y, 3),
            "top_z": round(self.top_z, 3),
            "radius_m": round(self.radius_m, 3),
            "cells": self.cells,
            "by": self.by,
        }


@dataclass(frozen=True)
class LiveUpdate:
    """One live map: the height map (observed = measured within `stale_s` and not held), the
    cells changed since the previous map, the held (robot) cells, the robots, a sequence."""

    sequence: int
    heightmap: HeightMap
    changed: np.ndarray
    held: np.ndarray
    robots: list[RobotSighting]


def neighbours(mask: np.ndarray) -> np.ndarray:
    """How many of each cell's 3 x 3 block (itself included) are set."""
    return np.rint(ndimage.uniform_filter(mask.astype(np.float32), 3, mode="constant") * 9)


def sum_by_label(values: np.ndarray, labels: np.ndarray, n: int, top: bool = False) -> np.ndarray:
    """Per label 1..n the sum (or the maximum) of `values`, over the labelled cells only: far
    fewer than the grid's, where ndimage's maximum sorts the whole grid."""
    cells = np.flatnonzero(labels)
    lab = labels.ravel()[cells]
    if not top:
        return np.bincount(lab, values.ravel()[cells], n + 1)[1:]
    out = np.full(n + 1, -np.inf)
    np.maximum.at(out, lab, values.ravel()[cells])
    return out[1:]


def merged(sightings: list[RobotSighting], within_m: float) -> list[RobotSighting]:
    """Parts of one robot (split by a shadow or a rake's cut face) as one sighting: those whose
    centres are closer than `within_m` join, weighted by their cells."""
    out: list[RobotSighting] = []
    for part in sorted(sightings, key=lambda r: -r.cells):  # a few per map
        near = next(
            (k for k, r in enumerate(out) if np.hypot(r.x - part.x, r.y - part.y) < within_m), None
        )
        if near is None:
            out.append(part)
            continue
        big = out[near]
        n = big.cells + part.cells
        x = (big.x * big.cells + part.x * part.cells) / n
        y = (big.y * big.cells + part.y * part.cells) / n
        reach = max(
            np.hypot(big.x - x, big.y - y) + big.radius_m,
            np.hypot(part.x - x, part.y - y) + part.radius_m,
        )
        by = "+".join(sorted(set(big.by.split("+")) | set(part.by.split("+"))))
        out[near] = RobotSighting(x, y, max(big.top_z, part.top_z), float(reach), n, by)
    return out


def mixed_pixels(depth: np.ndarray, unit_m: float, fx: float, edge_px: float) -> np.ndarray:
    """Pixels along a depth edge (a robot's rim against the grain behind it) that may read a
    depth between the two surfaces: where the 3 x 3 disparity range is above `edge_px`, all
    but those within a quarter of it of the nearest surface. A mixed pixel's point lies on
    its ray between the rim and the grain, above the grain and up to metres behind the robot
    at a wall camera's grazing angle, where no robot disc holds it; the rim itself stays (the
    robot is found by it), and the grain lost is a pixel wide band in the robot's shadow.
    Disparity (f x baseline / depth), not depth: a stereo camera's noise and its edges are the
    same size in it at every range."""
    valid = depth > 0
    with np.errstate(divide="ignore"):
        disparity = np.float32(fx * BASELINE_M / unit_m) / depth.astype(np.float32)
    low = ndimage.minimum_filter(np.where(valid, disparity, np.inf), 3)
    high = ndimage.maximum_filter(np.where(valid, disparity, 0.0), 3)
    spread = high - low
    return valid & (spread > edge_px) & (high - disparity > spread / 4)


def capsule_distance(
    xs: np.ndarray, ys: np.ndarray, start: tuple[float, float], end: tuple[float, float]
) -> np.ndarray:
    """Distance of every point to the segment start -> end (a disc's sweep along it)."""
    dx, dy = end[0] - start[0], end[1] - start[1]
    length2 = dx * dx + dy * dy
    if length2 == 0.0:
        return np.hypot(xs - start[0], ys - start[1])
    along = np.clip(((xs - start[0]) * dx + (ys - start[1]) * dy) / length2, 0.0, 1.0)
    return np.hypot(xs - start[0] - along * dx, ys - start[1] - along * dy)


def _rays_key(frame: DepthFrame) -> tuple[object, ...]:
    """What a camera's rays depend on: a frame with another key needs them made again."""
    return (
        frame.depth.shape,
        frame.fx,
        frame.fy,
        frame.ppx,
        frame.ppy,
        np.asarray(frame.extrinsic).tobytes(),
    )


class _Rays:
    """Silo-frame ray of every (decimated) pixel of one camera, scaled to unit depth, and in a
    bin where it meets the wall: the height there and the cell just inside (`wall_z`,
    `wall_cell`; None without a bin)."""

    def __init__(
        self,
        frame: DepthFrame,
        decimation: int,
        shape: BinShape | None,
        grid: Grid,
        noise_factor: float,
    ) -> None:
        h, w = frame.depth.shape
        v, u = np.mgrid[0:h:decimation, 0:w:decimation]
        rotation = np.asarray(frame.extrinsic, dtype=np.float64)[:3, :3]
        camera = np.stack(
            [(u - frame.ppx) / frame.fx, (v - frame.ppy) / frame.fy, np.ones(u.shape)], axis=-1
        ).reshape(-1, 3)
        silo = camera @ rotation.T
        self.x, self.y, self.z = (
            np.ascontiguousarray(silo[:, k], dtype=np.float32) for k in range(3)
        )
        self.origin = np.asarray(frame.extrinsic, dtype=np.float32)[:3, 3]
        # a point's weight is 1 / its depth variance, depth_rms_m(z)^2 = (z^2 x this)^2:
        # this / z^4 (its height moves along the ray too, but a grazing far ray's small rise
        # meets slopes, shadows' edges and sparse sampling, which that model does not know)
        per_depth = depth_rms_m(1.0, frame.fx)
        self.weight = np.float32(1.0 / np.square(per_depth))
        self.key = _rays_key(frame)
        self.wall_z: np.ndarray | None = None
        self.wall_cell: np.ndarray | None = None
        self.clear_depth: np.ndarray | None = None
        if shape is not None:
            ox, oy, oz = (float(a) for a in self.origin)
            depth = shape.ray_wall_depth(ox, oy, silo[:, 0], silo[:, 1])
            finite = np.isfinite(depth)
            reach = np.where(finite, depth, 0.0)
            x, y = ox + silo[:, 0] * reach, oy + silo[:, 1] * reach
            # -inf: a ray that never meets the wall is never the wall's
            self.wall_z = np.where(finite, oz + silo[:, 2] * reach, -np.inf).astype(np.float32)
            row, col = cell_inward(shape, grid, x, y)
            # int32 (the cell limit is far below 2^31): 4 bytes a pixel, 59 MB less for
            # sixteen 1280x720 cameras than numpy's index type; `take` casts it fast
            self.wall_cell = (row * grid.shape[1] + col).astype(np.int32)
            # a depth this far short of the wall's is not the wall's, whatever the grain's
            # height: FIRST_PASS_SIGMAS of a pixel's noise there (the full scan's first pass)
            rms = depth_rms_m(reach, frame.fx, noise_factor)
            margin = np.maximum(FIRST_PASS_MIN_MARGIN_M, FIRST_PASS_SIGMAS * rms)
            self.clear_depth = np.where(finite, depth - margin, np.inf).astype(np.float32)


class LiveMap:
    """Per-cell state of one live session over `grid`; `update(frames)` makes the next map."""

    def __init__(
        self,
        grid: Grid,
        settings: LiveConfig,
        ceiling_z: float | None = None,
        start: HeightMap | None = None,
        shape: BinShape | None = None,
        noise_factor: float = 1.0,
    ) -> None:
        """`start`, the last full scan's map on the same grid, gives cells not yet seen live a
        value; without it they take their nearest seen cell's. `shape`, a bin's: the pixels
        that saw its wall are not grain (`frame_heights`), judged with the cameras' depth RMS
        `noise_factor` times the ideal target's (`[reconstruction] depth_noise_factor`)."""
        self.grid = grid
        self.settings = settings
        self.ceiling_z = np.inf if ceiling_z is None else ceiling_z
        self.shape = shape
        self.noise_factor = noise_factor
        self.region = grid.inside > 0
        self.height = np.full(grid.shape, np.nan)
        if start is not None and (start.heights.shape, start.step, start.origin) == (
            grid.shape,
            grid.step,
            grid.origin,
        ):
            self.height = np.where(self.region, start.heights, np.nan).astype(np.float64)
        self.seen = np.zeros(grid.shape, dtype=bool)
        self.reported = np.full(grid.shape, np.nan)
        self.held = np.zeros(grid.shape, dtype=bool)
        self.jumped = np.zeros(grid.shape, dtype=np.int8)  # last frame's side beyond reset_m
        self.frames = np.zeros(grid.shape, dtype=np.int16)  # averaged since the last reset
        self.measured_at = np.full(grid.shape, -np.inf)
        # each cell's value when last measured with no robot near: what it is held at
        self.safe = self.height.copy()
        # the variance of each cell's running value, and of its `safe` value (inf: unknown)
        self.variance = np.full(grid.shape, np.inf)
        self.safe_variance = np.full(grid.shape, np.inf)
        self.sequence = 0
        self._tracks: list[tuple[float, float, float, float, float]] = []  # x, y, t, vx, vy
        self._rays: dict[str, _Rays] = {}
        rows, cols = grid.shape
        self._region_flat = self.region.ravel()
        self._scale = np.float32(1.0 / grid.step)
        self._origin = np.asarray(grid.origin, dtype=np.float32)
        self._limits = (rows, cols)
        self._centres = grid.centres()
        self._nearest: tuple[int, tuple[np.ndarray, ...]] | None = None

    # ------------------------------------------------------------ frames -> cell heights

    def _rays_of(self, frame: DepthFrame) -> _Rays:
        rays = self._rays.get(frame.serial)
        if rays is None or rays.key != _rays_key(frame):
            rays = _Rays(frame, self.settings.decimation, self.shape, self.grid, self.noise_factor)
            self._rays[frame.serial] = rays
        return rays

    def frame_heights(self, frames: list[DepthFrame]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per cell the frames' points' height, weighted by the D455's noise at each point's
        range (NaN: none), the point counts, and the weighted height's variance.

        In a bin, a pixel whose ray meets the wall more than WALL_CLEARANCE_M above the grain
        there (the map so far, 1.5 cells inside the wall) saw the wall, whatever depth noise
        made of it, and is left out: the full scan's verdict (reconstruct/walls.py). Depth
        noise throws the points of a far wall a camera looks across up to metres along their
        rays, into the bin: an 8 m bin seen by eight eave cameras read up to 2.7 m high in
        the ring by the wall (bench/live_robot.py). Before the map has a height (a session's
        first frames, without a full scan's map to start from) the grain at the wall comes
        from a first pass of the pixels whose depth is short of the wall's by three times its
        noise, as the full scan's first pass: with the floor for it, the grain by the wall
        was left out and the points noise carried there from farther in read it 0.2-0.3 m
        low, a ring of holes whose rims passed for robots. The grain is the map opened over
        WALL_LEVEL_M: a blob of wall pixels that read three sigma short passes the first pass
        and lands by the wall at wall heights, and taken as the grain it let every wall pixel
        below it in (a 12 m bin's ring up to 2.5 m high, kept so by itself); an opening takes
        away what is narrower than its window and keeps a level or a slope as it is."""
        wall_level = None
        if self.shape is not None:
            level = self._filled()
            if not np.isfinite(level).any():
                first = self._frame_heights(frames, None)[0]
                known = np.isfinite(first)
                level = first
                if known.any() and not known.all():
                    nearest = ndimage.distance_transform_edt(
                        ~known, return_distances=False, return_indices=True
                    )
                    level = first[tuple(nearest)]
            level = np.where(np.isfinite(level), level, self.shape.floor_z)
            window = max(3, int(np.ceil(WALL_LEVEL_M / self.grid.step)) | 1)
            wall_level = ndimage.grey_opening(level, size=(window, window)).ravel()
            wall_level += WALL_CLEARANCE_M
        return self._frame_heights(frames, wall_level)

    def _frame_heights(
        self, frames: list[DepthFrame], wall_level: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`frame_heights` with the wall judged against `wall_level` (flat, per cell), or in
        a bin without it by depth alone (the first pass)."""
        rows, cols = self._limits
        n_cells = rows * cols
        count: np.ndarray = np.zeros(n_cells)  # flat while summing, then (rows, cols)
        weight: np.ndarray = np.zeros(n_cells)
        total: np.ndarray = np.zeros(n_cells)
        d = self.settings.decimation
        for frame in frames:
            rays = self._rays_of(frame)
            image = frame.depth[::d, ::d]
            mixed = mixed_pixels(
                image, frame.depth_unit_m, frame.fx, self.settings.edge_disparity_px
            )
            depth = image.ravel()
            valid = np.flatnonzero((depth > 0) & ~mixed.ravel())
            if rays.wall_z is not None and rays.wall_cell is not None:
                if wall_level is not None:
                    level = np.take(wall_level, rays.wall_cell[valid])
                    valid = valid[rays.wall_z[valid] <= level]
                elif rays.clear_depth is not None:
                    reading = depth[valid] * np.float32(frame.depth_unit_m)
                    valid = valid[reading < rays.clear_depth[valid]]
            z_cam = depth[valid].astype(np.float32) * np.float32(frame.depth_unit_m)
            ox, oy, oz = rays.origin
            col = ((ox + z_cam * rays.x[valid] - self._origin[0]) * self._scale).astype(np.int64)
            row = ((oy + z_cam * rays.y[valid] - self._origin[1]) * self._scale).astype(np.int64)
            z = oz + z_cam * rays.z[valid]
            keep = (row >= 0) & (row < rows) & (col >= 0) & (col < cols) & (z <= self.ceiling_z)
            cell = (row * cols + col)[keep]
            w = np.square(z_cam[keep])
            np.square(w, out=w)
            np.divide(rays.weight, w, out=w)  # 1 / its depth variance
            count += np.bincount(cell, None, n_cells)
            weight += np.bincount(cell, w, n_cells)
            total += np.bincount(cell, w * z[keep], n_cells)
        count[~self._region_flat] = 0
        weight[~self._region_flat] = 0
        total[~self._region_flat] = 0
        count = count.reshape(rows, cols)
        weight, total = weight.reshape(rows, cols), total.reshape(rows, cols)
        # the mean over the cell and its 8 neighbours: a few points of a far camera per cell
        # are noisy, and a grain surface is smooth at 3 cells (a slope's mean is its centre's);
        # a near camera's point counts for more than a far one's (noise grows with range^2)
        near_count = ndimage.uniform_filter(count, 3, mode="constant") * 9
        near_weight = ndimage.uniform_filter(weight, 3, mode="constant") * 9
        near_total = ndimage.uniform_filter(total, 3, mode="constant") * 9
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count >= MIN_POINTS, near_total / near_weight, np.nan)
            # n points of mean variance n / weight, CORRELATED_SHARE of it common to them all
            spread = (CORRELATED_SHARE * near_count + 1 - CORRELATED_SHARE) / near_weight
            variance = np.where(count >= MIN_POINTS, spread, np.inf)
        return mean, count, variance

    # ------------------------------------------------------------ robot

    def find_robots(
        self, surface: np.ndarray, measured: np.ndarray, now_s: float
    ) -> tuple[np.ndarray, list[RobotSighting]]:
        """Cells of compact, steep-sided objects standing above the local surface, and of a
        compact raised one where a robot of the last map can have driven to by `now_s`: seen
        from eave cameras 6 m away, at the point of a bin farthest from all of them, a robot's
        rim blurs into a slope its steep cells no longer show (an 8 m bin's centre: 7-13 of
        the 20 asked), while its raised top stays as plain (bench/results/live-robot.md)."""
        settings, step = self.settings, self.grid.step
        work = surface
        holes = ~np.isfinite(surface)
        if holes.any():  # the first map: cells no frame has measured yet take their neighbour's
            table = ndimage.distance_transform_edt(
                holes, return_distances=False, return_indices=True
            )
            work = surface[tuple(table)]
        window = max(3, int(np.ceil(ROBOT_TOPHAT_M / step)))
        tophat = work - ndimage.grey_opening(work, size=(window, window))
        raised = self.region & (tophat > settings.robot_min_height_m)
        low = ndimage.minimum_filter(tophat, size=2 * ROBOT_STEEP_CELLS + 1)
        steep = measured & (tophat - low > ROBOT_STEEP_M)
        labels, n = ndimage.label(raised, structure=np.ones((3, 3)))
        if n == 0:
            return np.zeros(self.grid.shape, dtype=bool), []
        index = np.arange(1, n + 1)
        count = sum_by_label(np.ones(labels.shape), labels, n)
        area = count * step * step
        steep_cells = sum_by_label(steep & raised, labels, n)
        compact = (area >= ROBOT_AREA_M2[0]) & (area <= ROBOT_AREA_M2[1])
        steep_sided = compact & (steep_cells >= ROBOT_MIN_EDGE_M / step)
        xs, ys = self._centres
        # the centre of its steep edge, not of all raised cells: a robot on a heap's tip
        # raises the tip's cells with it, and they would pull the centre off the robot; a
        # blob found by its track alone has too few steep cells for that: all of its cells
        by_edge = np.concatenate([[False], steep_sided])[labels]
        edge = np.where(by_edge, np.where(steep, labels, 0), labels)
        edge_cells = np.where(steep_sided, steep_cells, count)
        centre_x = sum_by_label(xs, edge, n) / edge_cells
        centre_y = sum_by_label(ys, edge, n) / edge_cells
        robot = steep_sided | self._tracked(centre_x, centre_y, steep_sided, compact, now_s)
        if not robot.any():
            return np.zeros(self.grid.shape, dtype=bool), []
        keep = np.concatenate([[False], robot])
        cells = keep[labels]
        ids = index[robot]
        centre_x, centre_y = np.concatenate([[0.0], centre_x]), np.concatenate([[0.0], centre_y])
        top = sum_by_label(work, labels, n, top=True)
        spread = np.hypot(xs - centre_x[labels], ys - centre_y[labels])
        radius = sum_by_label(spread, edge, n, top=True) + step / 2
        sightings = [
            RobotSighting(
                float(centre_x[i]),
                float(centre_y[i]),
                float(top[i - 1]),
                float(radius[i - 1]),
                int(count[i - 1]),
            )
            for i in ids
        ]
        return cells, merged(sightings, 2 * self.settings.robot_radius_m)

    def sighting_of(
        self,
        frame: DepthFrame,
        box: tuple[float, float, float, float],
    ) -> RobotSighting | None:
        """A model's robot box (x1, y1, x2, y2 in `frame.color` pixels) in the silo frame: the
        depth points of the box's central half (a robot fills the middle of its box; the
        corners see the grain beside it) give its centre (median x, y) and top (the 90th
        percentile z: the single highest points are depth noise);
        its reach is the box's half diagonal at their median depth. None: no depth there."""
        assert frame.color is not None  # a box comes from the colour image
        height, width = frame.depth.shape
        sx, sy = width / frame.color.shape[1], height / frame.color.shape[0]
        x1, y1, x2, y2 = box[0] * sx, box[1] * sy, box[2] * sx, box[3] * sy
        qw, qh = (x2 - x1) / 4, (y2 - y1) / 4
        u0, u1 = max(int(np.floor(x1 + qw)), 0), min(int(np.ceil(x2 - qw)), width)
        v0, v1 = max(int(np.floor(y1 + qh)), 0), min(int(np.ceil(y2 - qh)), height)
        v, u = np.nonzero(frame.depth[v0:v1, u0:u1])
        if len(v) == 0:
            return None
        z_cam = frame.depth[v + v0, u + u0] * frame.depth_unit_m
        camera = np.column_stack(
            [
                (u + u0 - frame.ppx) / frame.fx * z_cam,
                (v + v0 - frame.ppy) / frame.fy * z_cam,
                z_cam,
            ]
        )
        extrinsic = np.asarray(frame.extrinsic, dtype=np.float64)
        silo = camera @ extrinsic[:3, :3].T + extrinsic[:3, 3]
        depth = float(np.median(z_cam))
        reach = np.hypot((x2 - x1) / frame.fx, (y2 - y1) / frame.fy) * depth / 2
        row, col = self.grid.cell_index(silo[:, 0], silo[:, 1])
        cells = len(np.unique(row * self.grid.shape[1] + col))
        return RobotSighting(
            float(np.median(silo[:, 0])),
            float(np.median(silo[:, 1])),
            float(np.percentile(silo[:, 2], 90)),
            float(reach),
            cells,
            "model",
        )

    # ------------------------------------------------------------ update

    def _reach(self, track: tuple[float, ...], now_s: float) -> float:
        """How far from a track's last sighting its robot can be by `now_s`."""
        return MAX_ROBOT_SPEED_M_S * (now_s - track[2]) + self.settings.robot_radius_m

    def _tracked(
        self,
        xs: np.ndarray,
        ys: np.ndarray,
        found: np.ndarray,
        compact: np.ndarray,
        now_s: float,
    ) -> np.ndarray:
        """Which `compact` blobs (centres xs, ys) a robot of the last map has driven onto: for
        each robot not `found` again by its steep edge within its reach, the compact blob
        within its reach nearest to where its motion takes it. One blob a robot: a heap's cut
        face the robot left beside it is not taken up as a second robot."""
        out = np.zeros(len(xs), dtype=bool)
        for x, y, t, vx, vy in self._tracks:  # a few
            if now_s <= t:
                continue
            reach = self._reach((x, y, t), now_s)
            gap = np.hypot(xs - x, ys - y)
            if np.any(found & (gap <= reach)):
                continue
            free = compact & ~found & ~out & (gap <= reach)
            if free.any():
                ahead = np.hypot(xs - x - vx * (now_s - t), ys - y - vy * (now_s - t))
                out[np.argmin(np.where(free, ahead, np.inf))] = True
        return out

    def _motions(self, robots: list[RobotSighting], now_s: float) -> list[tuple[float, float]]:
        """Each robot's velocity (m/s) from its sighting in the last map (the nearest one it
        can have driven from), smoothed over maps; 0 for a robot new to the map."""
        tracks = []
        for robot in robots:

            def gap(track: tuple[float, ...], robot: RobotSighting = robot) -> float:
                return float(np.hypot(robot.x - track[0], robot.y - track[1]))

            reachable = [
                t for t in self._tracks if now_s > t[2] and gap(t) <= self._reach(t, now_s)
            ]
            best = min(reachable, key=gap, default=None)
            if best is None:
                vx = vy = 0.0
            else:
                dt = now_s - best[2]
                vx = 0.5 * (robot.x - best[0]) / dt + 0.5 * best[3]
                vy = 0.5 * (robot.y - best[1]) / dt + 0.5 * best[4]
                speed = float(np.hypot(vx, vy))
                if speed > MAX_ROBOT_SPEED_M_S:
                    vx, vy = vx * MAX_ROBOT_SPEED_M_S / speed, vy * MAX_ROBOT_SPEED_M_S / speed
            tracks.append((robot.x, robot.y, now_s, vx, vy))
        self._tracks = tracks
        return [(t[3], t[4]) for t in tracks]

    def _filled(self) -> np.ndarray:
        """The running heights with every cell never measured taken from its nearest measured
        one (a hole's edge value, not a guess across it; `observed` says which is which).

        A distance transform per map would be a fifth of a map's time; measured cells stay
        measured, so an older nearest-cell table still points every hole at a measured cell
        and is only renewed when REFILL_GROWTH more of the grid has been measured since."""
        known = np.isfinite(self.height)
        n_known = int(known.sum())
        if n_known in (0, known.size):
            return self.height
        if self._nearest is None or n_known > self._nearest[0] + REFILL_GROWTH * known.size:
            table = ndimage.distance_transform_edt(
                ~known, return_distances=False, return_indices=True
            )
            self._nearest = (n_known, tuple(table))
        return np.where(known, self.height, self.height[self._nearest[1]])

    def _trusted(self, box: tuple[slice, slice]) -> np.ndarray:
        """Within `box`, how high the grain surely is: the mean of the TRUST_CELLS block's
        values measured with no robot near, each weighted by 1 / its variance, less
        TRUST_SIGMAS of their RMS (NaN: no such value in the block). A cell a far camera's
        few points measured once counts for little against ones near cameras measured for
        many frames; cells noisier than TRUST_RMS_M do not count. The block's RMS is its
        cells' (their harmonic mean): a far camera's noise is common to pixels a few apart,
        so neighbouring cells measured by it in the same frames are not independent."""
        variance = np.maximum(self.safe_variance[box], MIN_VARIANCE_M2)
        good = np.isfinite(self.safe[box]) & (variance <= TRUST_RMS_M**2)
        weight = np.where(good, MIN_VARIANCE_M2 / variance, 0.0)  # 1 at best, never near 0
        value = np.where(good, self.safe[box], 0.0)
        total = ndimage.uniform_filter(weight * value, TRUST_CELLS, mode="constant")
        norm = ndimage.uniform_filter(weight, TRUST_CELLS, mode="constant")
        cells = ndimage.uniform_filter(good.astype(np.float64), TRUST_CELLS, mode="constant")
        # running sums: a block with no good cell sums to rounding error, far below the least
        # weight a good cell has
        least = MIN_VARIANCE_M2 / TRUST_RMS_M**2 / TRUST_CELLS**2
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(MIN_VARIANCE_M2 * cells / norm)
            return np.where(norm > least / 2, total / norm - TRUST_SIGMAS * rms, np.nan)

    def _held_at(self, cells: np.ndarray, lowest: bool = False) -> np.ndarray:
        """For `cells` the robot holds, the trusted value (`_trusted`) at the nearest cell
        that has one: the grain beside the robot as the cameras measured it well with no robot
        near, not a far camera's one noisy reading or a value taken with the robot beside it,
        which its rim, noise and mixed pixels raise (NaN: none near). `lowest`: the lowest
        trusted value within TRUST_CELLS of that cell (for a cell never measured: beside a
        heap's foot, which a far camera's range noise blurs upwards, the flat one)."""
        rows, cols = np.nonzero(cells)
        pad = 2 * TRUST_CELLS  # a newly held cell's nearest trusted one is close by ...
        if lowest:  # ... one never measured may lie under the robot's whole disc and margin
            s = self.settings
            pad += int(np.ceil((s.robot_radius_m + 2 * s.robot_margin_m) / self.grid.step))
        box = (
            slice(max(rows.min() - pad, 0), rows.max() + pad + 1),
            slice(max(cols.min() - pad, 0), cols.max() + pad + 1),
        )
        trusted = self._trusted(box)
        known = np.isfinite(trusted)
        if not known.any():
            return np.full(len(rows), np.nan)
        if lowest:
            trusted = ndimage.minimum_filter(np.where(known, trusted, np.inf), TRUST_CELLS)
        here = (rows - box[0].start, cols - box[1].start)
        value = trusted[here]
        missing = ~known[here]
        if missing.any():  # the nearest trusted cell's (a distance transform: only if needed)
            table = ndimage.distance_transform_edt(
                ~known, return_distances=False, return_indices=True
            )
            value[missing] = trusted[tuple(axis[here][missing] for axis in table)]
        return value

    def update(
        self, frames: list[DepthFrame], now_s: float, seen: Sequence[RobotSighting] = ()
    ) -> LiveUpdate:
        """Fold the newest frames, taken at `now_s` (any clock in seconds), into the cells and
        make the next map; `seen`, the model's robot sightings, are held as the depth ones."""
        s = self.settings
        frame, count, noise = self.frame_heights(frames)
        # a lone sparse cell at the edge of a shadow holds points depth noise carried past the
        # crest that casts it, and reads high: it counts only with data all around it
        measured = np.isfinite(frame)
        measured &= (count >= 2) | (neighbours(measured) > SPARSE_NEIGHBOURS)
        frame = np.where(measured, frame, np.nan)
        surface = np.where(measured, frame, self._filled())
        robot_cells, robots = self.find_robots(surface, measured, now_s)
        if seen:
            robots = merged([*robots, *seen], 2 * s.robot_radius_m)
        margin = int(np.ceil(s.robot_margin_m / self.grid.step))
        held = robot_cells
        if margin and robot_cells.any():
            held = ndimage.binary_dilation(robot_cells, iterations=margin)
        xs, ys = self._centres
        # each robot's disc, swept along where its tracked motion takes it within
        # hold_ahead_s: a cell is held before the robot's rim, its noise and its mixed pixels
        # reach it, not once they have got into its value
        for robot, (vx, vy) in zip(robots, self._motions(robots, now_s), strict=True):
            ahead = (robot.x + vx * s.hold_ahead_s, robot.y + vy * s.hold_ahead_s)
            reach = max(robot.radius_m, s.robot_radius_m) + s.robot_margin_m
            held = held | (capsule_distance(xs, ys, (robot.x, robot.y), ahead) <= reach)
        # a cell the robot covered stays held while the frame still reads well above its last
        # good value: the robot has not left it, whether or not this frame's detection says so
        held |= self.held & measured & (frame - self.height > s.reset_m)
        held &= self.region
        # a cell newly held keeps the lower of its value and the median of the values its
        # ROBUST_CELLS block had when last measured with no robot near: the robot's rim, its
        # mixed pixels and its depth noise only raise cells near it, and a lone cell that a
        # burst of noise raised is outvoted by its neighbours
        near = held
        if margin and held.any():
            near = ndimage.maximum_filter(held, size=2 * margin + 1)
        onset = held & ~self.held
        if onset.any():  # the median over the onset cells' bounding box, not the whole grid
            rows, cols = np.nonzero(onset)
            pad = ROBUST_CELLS // 2
            box = (
                slice(max(rows.min() - pad, 0), rows.max() + pad + 1),
                slice(max(cols.min() - pad, 0), cols.max() + pad + 1),
            )
            known = np.where(np.isfinite(self.safe[box]), self.safe[box], self.height[box])
            robust = ndimage.median_filter(known, size=ROBUST_CELLS, mode="nearest")
            here = onset[box]
            lowest = np.fmin(robust[here], self._held_at(onset))
            self.height[box][here] = np.fmin(self.height[box][here], lowest)
        update = measured & ~held
        delta = frame - self.height
        side = np.where(update & (np.abs(delta) > s.reset_m), np.sign(delta), 0).astype(np.int8)
        voters = neighbours(update)
        same = np.where(side > 0, neighbours(side > 0), neighbours(side < 0))
        agree = (same >= JUMP_MIN_VOTES) & (3 * same >= 2 * voters)
        confirmed = (side != 0) & ((side == self.jumped) | agree)
        self.jumped = np.where(update, side, self.jumped)
        replace = update & (~np.isfinite(self.height) | ~self.seen | confirmed)
        blend = update & ~replace & (side == 0)
        self.height[replace] = frame[replace]
        self.frames[replace] = 1
        # a plain mean over a cell's first frames, then the exponential average
        self.frames[blend] = np.minimum(self.frames[blend] + 1, np.iinfo(np.int16).max)
        weight = np.maximum(s.smoothing, 1.0 / self.frames[blend])
        self.height[blend] += weight * delta[blend]
        # the running value's variance, through the same weights (grid-wide: cheaper than
        # gathering the blended cells)
        share = np.maximum(s.smoothing, 1.0 / np.maximum(self.frames, 1))
        with np.errstate(invalid="ignore"):  # inf x 0 in cells neither blended nor measured
            blended = np.square(1 - share) * self.variance + np.square(share) * noise
        np.copyto(self.variance, blended, where=blend)
        np.copyto(self.variance, noise, where=replace)
        self.seen |= update
        self.measured_at[update] = now_s
        clear = update & ~near
        self.safe[clear] = self.height[clear]
        np.copyto(self.safe_variance, self.variance, where=clear)

        heights = np.where(self.region, self._filled(), np.nan)
        # a held cell never measured with no robot near (one the robot has stood on since the
        # session began) has no value of its own to keep: the trusted one nearest to it
        unknown = held & ~np.isfinite(self.safe)
        if unknown.any():
            heights[unknown] = np.fmin(heights[unknown], self._held_at(unknown, lowest=True))
        changed = (
            self.region & np.isfinite(heights) & ~(np.abs(heights - self.reported) <= s.change_m)
        )
        changed |= held != self.held
        self.reported = np.where(changed, heights, self.reported)
        self.held = held
        self.sequence += 1
        fresh = now_s - self.measured_at <= s.stale_s
        hm = HeightMap(
            self.grid.origin,
            self.grid.step,
            heights.astype(np.float32),
            fresh & ~held,
            self.grid.inside,
        )
        return LiveUpdate(self.sequence, hm, changed, held, robots)
