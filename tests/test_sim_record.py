"""Simulated recordings play back through real librealsense, frame for frame, and through the
playback camera onto the scene's surface (no mocks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

# ruff: noqa: E402 (the imports below need pyrealsense2, or this module is skipped first)
# pyrealsense2 has x86-64 wheels only: elsewhere these tests are skipped, the rest runs
rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed")
pytestmark = pytest.mark.realsense

from silo_agent.capture import capture_all
from silo_agent.capture.sim_recording import record_views
from silo_agent.cli import main
from silo_agent.config import parse_config
from silo_agent.scan import read_scan
from silo_agent.sim import SimRig, make_scene
from silo_agent.sim.simulate import plan_views
from tests.support.playback import play_stream


def test_recording_plays_back_the_rendered_frames(tmp_path: Path) -> None:
    scene = make_scene("piles")
    rig = SimRig(scene)
    (view,) = plan_views(scene, ["A3"], seed=5)
    (path,) = record_views(rig, [view], 5, tmp_path, frames=3, color=True)
    assert path.name == "sim-A3.db3"
    rendered = rig.frames(view, 5, 3, color=True)
    profile, depth = play_stream(path)
    _, color = play_stream(path, rs.stream.color)
    assert profile.get_device().get_info(rs.camera_info.serial_number) == "sim-A3"
    assert profile.get_device().first_depth_sensor().get_depth_scale() == pytest.approx(0.001)
    intr = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
    want = view.intrinsics
    assert (intr.width, intr.height) == (848, 480)
    assert [intr.fx, intr.fy, intr.ppx, intr.ppy] == pytest.approx(
        [want.fx, want.fy, want.ppx, want.ppy], rel=1e-6
    )
    assert len(depth) == 3 and len(color) == 3
    for got, frame in zip(depth, rendered, strict=True):
        np.testing.assert_array_equal(got, frame.depth)
    assert not np.array_equal(depth[0], depth[1])  # independent noise per frame
    np.testing.assert_array_equal(color[0], rendered[0].color)


def test_simulate_record_plays_through_the_playback_camera(tmp_path: Path) -> None:
    out, recordings = tmp_path / "scan", tmp_path / "rec"
    argv = [
        "simulate",
        "--scene",
        "cone",
        "--views",
        "A1",
        "--out",
        str(out),
        "--seed",
        "3",
        "--calib-error",
        "2,0.01",
        "--record",
        str(recordings),
        "--record-frames",
        "4",
    ]
    assert main(argv) == 0
    (camera,) = read_scan(out).cameras
    config = parse_config(
        {
            "silo": {"id": "t", "region": [[-2, -2], [2, -2], [2, 2], [-2, 2]]},
            "cameras": [
                {
                    "serial": camera.serial,
                    "source": "playback",
                    "playback": str(recordings / f"{camera.serial}.db3"),
                    "extrinsic": camera.extrinsic.tolist(),
                    "warmup_frames": 1,
                    "frames": 3,
                }
            ],
        },
        "test",
    )
    result = capture_all(config)
    assert result.failures == []
    (cloud,) = result.clouds
    true = np.asarray(camera.extra["sim_true_extrinsic"])
    p = cloud.points.astype(float) @ true[:3, :3].T + true[:3, 3]
    near = np.hypot(p[:, 0], p[:, 1]) < 2.0
    scene = make_scene("cone")
    gap = p[near, 2] - scene.height(p[near, 0], p[near, 1])
    assert near.sum() > 100_000 and np.sqrt(np.mean(gap**2)) < 0.005
    # the accelerometer follows the true pose: the IMU check sees the calibration error
    up_true = true[:3, :3].T @ [0, 0, 1]
    up_nominal = camera.extrinsic[:3, :3].T @ [0, 0, 1]
    tilt = np.degrees(np.arccos(np.clip(up_true @ up_nominal, -1, 1)))
    assert 0.1 < tilt <= 2.0 + 1e-9
    assert cloud.extra["gravity_angle_deg"] == pytest.approx(tilt, abs=0.01)


def test_record_frames_must_be_positive(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        main(
            [
                "simulate",
                "--scene",
                "cone",
                "--views",
                "A1",
                "--out",
                str(tmp_path / "s"),
                "--record",
                str(tmp_path / "r"),
                "--record-frames",
                "0",
            ]
        )
