"""write_recording round trip through real librealsense playback (no mocks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

# ruff: noqa: E402 (the imports below need pyrealsense2, or this module is skipped first)
# pyrealsense2 has x86-64 wheels only: elsewhere these tests are skipped, the rest runs
rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed")
pytestmark = pytest.mark.realsense

from silo_agent.capture.recording import write_recording
from tests.support.playback import play_stream

INTRINSICS = {"width": 64, "height": 48, "fx": 50.0, "fy": 52.0, "ppx": 31.5, "ppy": 23.0}


def test_round_trip_frames_serial_intrinsics(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 5000, size=(48, 64), dtype=np.uint16) for _ in range(6)]
    path = tmp_path / "cam.db3"
    write_recording(path, "SN-042", INTRINSICS, frames, depth_units=0.0005, fps=15)

    profile, played = play_stream(path)
    device = profile.get_device()
    assert device.get_info(rs.camera_info.serial_number) == "SN-042"
    assert device.first_depth_sensor().get_depth_scale() == pytest.approx(0.0005)
    stream = profile.get_stream(rs.stream.depth).as_video_stream_profile()
    intr = stream.get_intrinsics()
    assert (intr.width, intr.height) == (64, 48)
    assert (intr.fx, intr.fy, intr.ppx, intr.ppy) == (50.0, 52.0, 31.5, 23.0)
    assert stream.fps() == 15
    assert len(played) == len(frames)
    for got, want in zip(played, frames, strict=True):
        np.testing.assert_array_equal(got, want)


def test_round_trip_with_colour(tmp_path: Path) -> None:
    depth = [np.full((48, 64), 1000 + i, dtype=np.uint16) for i in range(3)]
    color = [np.full((48, 64, 3), (10 * i, 20, 30), dtype=np.uint8) for i in range(3)]
    path = tmp_path / "rgb.db3"
    write_recording(path, "SN-7", INTRINSICS, depth, 0.001, 30, color_frames=color)

    _, played_depth = play_stream(path)
    profile, played_color = play_stream(path, rs.stream.color)
    assert [int(d[0, 0]) for d in played_depth] == [1000, 1001, 1002]
    assert [tuple(c[5, 5]) for c in played_color] == [(0, 20, 30), (10, 20, 30), (20, 20, 30)]
    color_stream = profile.get_stream(rs.stream.color)
    assert color_stream.format() == rs.format.rgb8
    depth_stream = profile.get_device().first_depth_sensor().get_stream_profiles()[0]
    extrinsics = depth_stream.get_extrinsics_to(color_stream)
    assert list(extrinsics.rotation) == [1, 0, 0, 0, 1, 0, 0, 0, 1]


def test_accelerometer_is_recorded(tmp_path: Path) -> None:
    depth = [np.full((48, 64), 1000, dtype=np.uint16)] * 4
    path = tmp_path / "imu.db3"
    write_recording(path, "SN-8", INTRINSICS, depth, 0.001, 30, accel=(0.5, -9.7, 0.25))
    _, played = play_stream(path, rs.stream.accel)
    assert len(played) == 4
    xyz = np.asarray(played, dtype=np.uint8).view(np.float32).reshape(4, 3)  # motion_xyz32f
    np.testing.assert_allclose(xyz, [[0.5, -9.7, 0.25]] * 4, rtol=1e-6)


def test_rejects_frames_of_the_wrong_shape(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"depth_frames\[1\]"):
        write_recording(
            tmp_path / "bad.db3",
            "SN",
            INTRINSICS,
            [np.zeros((48, 64), np.uint16), np.zeros((40, 64), np.uint16)],
            0.001,
            30,
        )
