"""Live frames through real librealsense playback: the moving-robot scene recorded as four
`.db3` files (one per corner camera), streamed by the live source frame after frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from silo_agent.capture import CaptureError
from silo_agent.config import parse_config
from silo_agent.grid.grid import Grid
from silo_agent.live.map import LiveMap
from silo_agent.live.session import open_source
from silo_agent.sim.robot import RobotRig
from tests.support.robot import robot_rig

TIMES = (0.0, 0.5, 1.0, 1.5)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[RobotRig, list[list[np.ndarray]], Path]:
    from silo_agent.capture.recording import write_recording

    rig = robot_rig(width=424, height=240)
    frames = [[f.depth for f in rig.frames(t, i)] for i, t in enumerate(TIMES)]
    directory = tmp_path_factory.mktemp("live-recordings")
    for k, view in enumerate(rig.views):
        write_recording(
            directory / f"{view.serial}.db3",
            view.serial,
            view.intrinsics.to_json(),
            [per_time[k] for per_time in frames],
            0.001,
            30,
        )
    return rig, frames, directory


def playback_config(rig: RobotRig, directory: Path):
    cameras = [
        {
            "serial": v.serial,
            "source": "playback",
            "playback": str(directory / f"{v.serial}.db3"),
            "extrinsic": v.nominal.tolist(),
            "width": 424,
            "height": 240,
            "timeout_s": 2.0,
            "spatial_filter": False,
            "temporal_filter": True,
        }  # configured, yet not used live: it smears a robot
        for v in rig.views
    ]
    site = rig.robot.base.site
    return parse_config(
        {
            "silo": {"id": "live-rs", "region": site.region.tolist(), "ceiling_z": site.ceiling_z},
            "cameras": cameras,
            "live": {"decimation": 1},
        },
        "test",
    )


def test_playback_streams_every_frame_unblended_then_ends_with_a_clear_error(recorded):
    rig, frames, directory = recorded
    config = playback_config(rig, directory)
    source = open_source(config)
    grid = Grid.over(rig.robot.base.site.region, 0.02)
    live = LiveMap(grid, config.live, config.silo.ceiling_z)
    try:
        for index, t in enumerate(TIMES):
            got = source.frames(t)
            assert [f.serial for f in got] == [v.serial for v in rig.views]
            for frame, written, view in zip(got, frames[index], rig.views, strict=True):
                # frame by frame as recorded: no temporal blending of successive frames
                np.testing.assert_array_equal(frame.depth, written)
                assert frame.fx == pytest.approx(view.intrinsics.fx)
                np.testing.assert_array_equal(frame.extrinsic, view.nominal)
            update = live.update(got, t)
        (robot,) = update.robots
        pose = rig.robot.pose(TIMES[-1])
        assert np.hypot(robot.x - pose.x, robot.y - pose.y) < 0.3
        with pytest.raises(CaptureError, match=r"camera sim-A2: no depth frame within 2 s"):
            source.frames(2.0)
    finally:
        source.close()


def test_mixing_sim_and_recorded_cameras_is_refused(recorded):
    rig, _frames, directory = recorded
    config = playback_config(rig, directory)
    data = config.model_dump(mode="json", exclude_none=True)
    data["cameras"][0] = {"serial": "sim-x", "source": "sim", "view": "A1"}
    mixed = parse_config(data, "test")
    with pytest.raises(CaptureError, match="cannot mix sim cameras"):
        open_source(mixed)
