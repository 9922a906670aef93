"""The robot stays out of the live map (#25.5): mixed pixels along depth edges are dropped,
cells are held ahead of the robot's motion at the lowest value measured with no robot near,
and a session whose cameras cannot keep the robot out is refused with the reason.

Against the moving-robot scene's exact surface: four wall D455s at 424x240 (the resolution
a gateway streams four cameras at), one map every half second, the robot raking the first
heap, half the pixels along every depth edge mixed."""

from __future__ import annotations

import threading
from typing import cast

import numpy as np
import pytest

from silo_agent.base.d455 import BASELINE_M as D455_BASELINE_M
from silo_agent.config import Config, LiveConfig, parse_config
from silo_agent.grid.grid import Grid
from silo_agent.live.coverage import session_problem
from silo_agent.live.map import DepthFrame, LiveMap, mixed_pixels
from silo_agent.service.live_control import LiveControl
from silo_agent.sim.grains import grain
from silo_agent.sim.layouts import view_pose
from silo_agent.sim.robot import RobotRig
from silo_agent.sim.scenes import bin_scene
from silo_agent.telemetry.client import CommandRejected, Telemetry
from silo_agent.telemetry.live_command import LiveCommand, LiveRequest
from tests.support.robot import robot_rig

TIMES = np.arange(0.0, 10.5, 0.5)
WARM_UP_S = 3.0  # the robot stands in the bay from the start: nothing is known under it yet
AWAY_M = 0.5
FOCAL_424 = 216.0


def test_mixed_pixels_along_an_edge_are_dropped_and_the_grain_and_rim_kept() -> None:
    rng = np.random.default_rng(3)
    rows, cols = 240, 424
    v = np.arange(rows)[:, None] * np.ones(cols)
    grain = 2.0 + 2.0 * v / rows  # a floor seen at a grazing angle: 2 m at the top, 4 m below
    depth = grain.copy()
    box = (slice(100, 160), slice(200, 260))
    depth[box] = 1.6  # a robot's top in front of it
    rim = np.zeros((rows, cols), dtype=bool)
    rim[99, 199:261] = rim[160, 199:261] = rim[99:161, 199] = rim[99:161, 260] = True
    mix = rng.uniform(0.3, 1.0, rim.sum())  # between the rim (0) and the grain behind (1)
    depth[rim] = 1.6 + mix * (grain[rim] - 1.6)
    disparity_noise = 0.08  # px, the D455's
    noise = rng.standard_normal(depth.shape) * disparity_noise
    depth = depth * (1 + noise * depth / (FOCAL_424 * D455_BASELINE_M))
    codes = np.rint(depth * 1000).astype(np.uint16)
    dropped = mixed_pixels(codes, 0.001, FOCAL_424, LiveConfig().edge_disparity_px)
    assert dropped[rim].mean() > 0.95
    far = np.ones((rows, cols), dtype=bool)
    far[96:164, 196:264] = False
    assert dropped[far].mean() < 0.01  # noisy grain stays
    inner = np.zeros((rows, cols), dtype=bool)
    inner[box] = True
    assert dropped[inner].mean() < 0.05  # the robot's top, its rim too, stays: it finds it


def sim_config(views: tuple[str, ...], width: int, height: int) -> Config:
    rig = RobotRig(views=views, width=width, height=height)
    site = rig.robot.base.site
    cameras = [
        {"serial": v.serial, "source": "sim", "view": v.key, "width": width, "height": height}
        for v in rig.views
    ]
    data = {
        "silo": {"id": "live-min", "region": site.region.tolist(), "ceiling_z": site.ceiling_z},
        "cameras": cameras,
    }
    return parse_config(data, "test")


@pytest.mark.parametrize(
    ("views", "size", "accepted"),
    [
        (("A2", "A4", "A6", "A8"), (424, 240), True),
        (("A2", "A4", "A6", "A8"), (848, 480), True),
        (("A2", "A6"), (424, 240), False),
        (("A2", "A4", "A6", "A8"), (320, 180), False),
    ],
)
def test_a_session_that_cannot_keep_the_robot_out_is_refused_saying_why(
    views: tuple[str, ...], size: tuple[int, int], accepted: bool
) -> None:
    config = sim_config(views, *size)
    serials = [c.serial for c in config.cameras]
    problem = session_problem(config, serials)
    assert (problem is None) == accepted, problem
    control = LiveControl(config, cast(Telemetry, None), threading.Event())
    command = LiveCommand(LiveRequest(on=True), "replies", None)
    if accepted:
        assert control.requested(command).startswith("live-min-live-")
        return
    with pytest.raises(CommandRejected) as refused:
        control.requested(command)
    message = str(refused.value)
    assert "cannot keep the robot out" in message and f"{size[0]}x{size[1]}" in message
    control.tend(scan_due=False)  # the main loop's turn applies what was accepted: nothing
    assert control.session is None


def bin_config(width: int, height: int, noise_factor: float | None = None) -> Config:
    """An 8 m bin (eave 6 m) with eight eave D455s placed by their extrinsics, as a site
    configures real cameras; `noise_factor`: `[reconstruction] depth_noise_factor` if given."""
    scene = bin_scene(grain("wheat"), name="bin-8m", diameter_m=8.0, eave_m=6.0)
    cameras = [
        {
            "serial": f"eave-{k}",
            "extrinsic": view_pose(scene, f"A{k}").tolist(),
            "width": width,
            "height": height,
        }
        for k in range(1, 9)
    ]
    data: dict[str, object] = {
        "silo": {"id": "bin-8", "bin": {"diameter_m": 8.0, "eave_height_m": 6.0}},
        "cameras": cameras,
    }
    if noise_factor is not None:
        data["reconstruction"] = {"depth_noise_factor": noise_factor}
    return parse_config(data, "test")


def test_a_bins_cameras_are_judged_at_the_noise_the_site_gives_them() -> None:
    """Real grain is noisier than the D455's ideal target (`depth_noise_factor`, 2.5 by
    default). Judged at the ideal target's noise, eight eave cameras at 424x240 over an 8 m
    bin passed, and on the moving-robot bench (simulated D455s at that factor) the robot
    stood 0.36 m high in the map and up to 13 robots were found where there were none
    (bench/results/live-robot.md): now they are refused, saying why; at 1280x720 they pass;
    a site whose cameras are as good as the ideal target says so and passes at 424x240."""
    serials = [f"eave-{k}" for k in range(1, 9)]
    problem = session_problem(bin_config(424, 240), serials)
    assert problem is not None and "8 camera(s) at 424x240 cannot keep the robot out" in problem
    assert session_problem(bin_config(1280, 720), serials) is None
    assert session_problem(bin_config(424, 240, noise_factor=1.0), serials) is None


@pytest.fixture(scope="module")
def run_424():
    rig = robot_rig(width=424, height=240)
    site = rig.robot.base.site
    grid = Grid.over(site.region, 0.02)
    live = LiveMap(grid, LiveConfig(), site.ceiling_z)
    xs, ys = grid.centres()
    steps = []
    for index, t in enumerate(TIMES):
        frames = [
            DepthFrame.rendered(v.serial, f, v.nominal)
            for v, f in zip(rig.views, rig.frames(float(t), index), strict=True)
        ]
        update = live.update(frames, float(t))
        steps.append((float(t), update, rig.robot.height(float(t))(xs, ys)))
    return rig, grid, steps


@pytest.mark.slow
def test_at_424x240_the_robot_stays_out_and_the_grain_is_within_20mm(run_424) -> None:
    rig, grid, steps = run_424
    xs, ys = grid.centres()
    worst, typical, ahead = [], [], []
    for t, update, truth in steps:
        pose = rig.robot.pose(t)
        under = pose.footprint(xs, ys)
        excess = update.heightmap.heights[under] - truth[under]
        # no map, from the first, stands more than 30 mm above the grain under the robot
        worst.append(float(excess.max()))
        if t < WARM_UP_S:
            continue
        away = update.heightmap.observed & ~pose.footprint(xs, ys, AWAY_M)
        rms = float(np.sqrt(np.mean((update.heightmap.heights[away] - truth[away]) ** 2)))
        assert rms <= 0.020, f"t={t}: grain {rms * 1000:.1f} mm RMS"
        assert update.held[under].all(), f"t={t}"
        typical.append(float(np.median(excess)))
        # held before the robot gets there: where it will be a second later is held already
        ahead.append(float(update.held[rig.robot.pose(t + 1.0).footprint(xs, ys)].mean()))
    # the robot does not leak in: no cell of its footprint more than 30 mm above the grain
    # (#25's target; before the noise weighting 62 mm after the warm-up, 78 mm in it: grain
    # cells a far camera read high once, held under the robot)
    assert max(worst) <= 0.030, np.round(np.array(worst) * 1000).tolist()
    # the price: a held cell stands a fraction of its noise below the grain, not in a hole
    assert np.median(typical) >= -0.060, np.round(np.array(typical) * 1000).tolist()
    assert np.mean(ahead) >= 0.98, np.round(ahead, 2).tolist()
