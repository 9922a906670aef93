"""Can these cameras keep the robot out of the live map? Checked before a session starts.

The live map finds the robot as a steep-sided object standing `robot_min_height_m` above the
grain, and holds the cells it covers. That needs, everywhere the robot may drive, two cameras
(one sees the cells the robot shadows from the other) whose depth noise is small against the
robot's height. The stated minimum: at least MIN_SHARE of the region is seen by MIN_VIEWS
cameras, each within the D455's range there and with a single-pixel depth RMS (the D455
model, z² x 0.08 px / (f x 95 mm), times the cameras' noise factor) of at most
MAX_NOISE_SHARE x `robot_min_height_m`. Measured on the moving-robot bench
(bench/live_robot.py): four wall cameras pass at 424x240 and keep the robot out; two cameras,
or four at 320x180, fail the check, and in the map the robot's top stood in the grain or was
missed. The noise factor is `[reconstruction] depth_noise_factor` (2.5 by default, real grain):
judged at the ideal target's noise the check passed eight eave cameras at 424x240 over an 8 m
bin whose simulated D455s carry that factor, and the robot stood up to 0.36 m in the map
with up to 13 robots found where there were none; at 848x480 they pass and keep it out.

Cameras are placed by their extrinsics (a sim camera by its view in the moving-robot scene)
with the D455's nominal focal length at their resolution; the surface is the last full scan's
mean level, or without one the level halfway between the floor and the lowest camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from silo_agent.base.d455 import depth_rms_m
from silo_agent.config import Config
from silo_agent.grid.grid import Grid
from silo_agent.grid.heightmap import HeightMap

MIN_VIEWS = 2
MIN_SHARE = 0.9
MAX_NOISE_SHARE = 0.8
D455_FOCAL_PX_848 = 431.0  # nominal depth focal length at 848 px wide
D455_RANGE_M = (0.4, 6.0)
CHECK_STEP_M = 0.05


@dataclass(frozen=True)
class CameraView:
    serial: str
    pose: np.ndarray  # 4x4 camera -> silo
    width: int
    height: int
    noise_factor: float  # its depth RMS over the D455's ideal-target figure


def camera_views(config: Config, serials: list[str]) -> list[CameraView]:
    """Where each live camera is, and how noisy: its extrinsic and `[reconstruction]
    depth_noise_factor`, or a sim camera's view in the moving scene and that scene's noise."""
    views = []
    cameras = [c for c in config.cameras if c.serial in serials]
    sim = [c for c in cameras if c.source == "sim" and c.view is not None]
    if sim:
        from silo_agent.sim.grains import grain
        from silo_agent.sim.layouts import view_pose
        from silo_agent.sim.robot import mounded_bay

        scene = mounded_bay(grain("wheat"))
        for c in sim:
            assert c.view is not None
            pose = view_pose(scene, c.view, "wall")
            views.append(CameraView(c.serial, pose, c.width, c.height, scene.surface_factor))
    factor = config.reconstruction.depth_noise_factor
    for c in cameras:
        matrix = c.extrinsic_matrix() if c.source != "sim" else None
        if matrix is not None:
            pose = np.asarray(matrix, float)
            views.append(CameraView(c.serial, pose, c.width, c.height, factor))
    return views


def surface_z(config: Config, views: list[CameraView], last_map: HeightMap | None) -> float:
    """The level the robot drives at: the last full scan's mean, else halfway to the cameras."""
    if last_map is not None and np.isfinite(last_map.heights).any():
        return float(np.nanmean(last_map.heights))
    lowest = min((float(v.pose[2, 3]) for v in views), default=config.silo.floor_z)
    return (config.silo.floor_z + lowest) / 2


def good_views(config: Config, views: list[CameraView], z: float) -> tuple[np.ndarray, Grid]:
    """Per region cell (at level `z`), how many cameras see it within range and noise."""
    grid = Grid.over(config.silo.region_polygon(), CHECK_STEP_M)  # `region` or the bin's wall
    xs, ys = grid.centres()
    points = np.stack([xs, ys, np.full(xs.shape, z)], axis=-1)
    limit = MAX_NOISE_SHARE * config.live.robot_min_height_m
    count = np.zeros(grid.shape, dtype=int)
    for view in views:
        rotation, origin = view.pose[:3, :3], view.pose[:3, 3]
        camera = (points - origin) @ rotation  # silo -> camera frame
        depth = camera[..., 2]
        f = D455_FOCAL_PX_848 * view.width / 848
        with np.errstate(divide="ignore", invalid="ignore"):
            u = camera[..., 0] / depth * f + (view.width - 1) / 2
            v = camera[..., 1] / depth * f + (view.height - 1) / 2
        seen = (depth >= D455_RANGE_M[0]) & (depth <= D455_RANGE_M[1])
        seen &= (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
        noise = depth_rms_m(depth, f, view.noise_factor)
        count += seen & (noise <= limit)
    return count, grid


def session_problem(
    config: Config, serials: list[str], last_map: HeightMap | None = None
) -> str | None:
    """Why these cameras cannot keep the robot out of the live map, or None if they can."""
    views = camera_views(config, serials)
    if len(views) < MIN_VIEWS:
        return (
            f"live mode needs at least {MIN_VIEWS} placed cameras to keep the robot out of the "
            f"map; {len(views)} of {len(serials)} have an extrinsic or a sim view"
        )
    z = surface_z(config, views, last_map)
    count, grid = good_views(config, views, z)
    inside = grid.inside > 0
    share = float(np.mean(count[inside] >= MIN_VIEWS))
    if share >= MIN_SHARE:
        return None
    limit_mm = MAX_NOISE_SHARE * config.live.robot_min_height_m * 1000
    sizes = sorted({f"{v.width}x{v.height}" for v in views})
    problem = (
        f"{len(views)} camera(s) at {', '.join(sizes)} cannot keep the robot out of the live "
        f"map: only {share:.0%} of the region (at z = {z:.2f} m) is seen by {MIN_VIEWS} cameras "
        f"with depth noise under {limit_mm:.0f} mm, {MIN_SHARE:.0%} needed; add cameras or "
        "raise their resolution"
    )
    if any(c.source == "sim" for c in config.cameras if c.serial in serials):
        from silo_agent.sim.robot import REGION_HALF_M

        side = 2 * REGION_HALF_M
        problem += (
            f" (sim cameras watch the moving-robot scene, a {side:g} x {side:g} m bay around "
            "(0, 0), whatever the config's bin or region: keep [silo] region within it)"
        )
    return problem
