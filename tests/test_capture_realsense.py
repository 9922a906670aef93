"""RealSenseCamera through real librealsense playback of recordings made in the test (no mocks)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import structlog

# ruff: noqa: E402 (the imports below need pyrealsense2, or this module is skipped first)
# pyrealsense2 has x86-64 wheels only: elsewhere these tests are skipped, the rest runs
rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed")
pytestmark = pytest.mark.realsense

from silo_agent.capture import CaptureError, capture_all
from silo_agent.capture.realsense import RealSenseCamera, deproject, median_of_valid
from silo_agent.capture.recording import write_recording
from silo_agent.config import Config, parse_config

# A downward-looking camera 3 m above the floor: camera x -> silo x, y -> -y, z -> -z.
LOOKING_DOWN = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3.0], [0, 0, 0, 1]]
SMALL = {"width": 160, "height": 96, "fx": 80.0, "fy": 80.0, "ppx": 79.5, "ppy": 47.5}
UNITS = 0.001


def make_config(cameras: list[dict[str, Any]]) -> Config:
    """A config of playback cameras; each entry overrides the defaults below."""
    base = {
        "source": "playback",
        "extrinsic": LOOKING_DOWN,
        "warmup_frames": 2,
        "frames": 3,
        "timeout_s": 3.0,
        "spatial_filter": False,
        "temporal_filter": False,
    }
    return parse_config(
        {
            "silo": {"id": "silo-t", "region": [[-2, -2], [2, -2], [2, 2], [-2, 2]]},
            "cameras": [
                {**base, **{k: str(v) if isinstance(v, Path) else v for k, v in c.items()}}
                for c in cameras
            ],
        },
        "test",
    )


def plane(intrinsics: dict[str, float], distance_m: float) -> np.ndarray:
    return np.full(
        (intrinsics["height"], intrinsics["width"]), round(distance_m / UNITS), np.uint16
    )


def pile_surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A 1 m high cone of radius 1.5 m on the floor (silo frame)."""
    return np.maximum(0.0, 1.0 - np.hypot(x, y) / 1.5)


def pile_depth(intrinsics: dict[str, float]) -> np.ndarray:
    """Ray-cast the cone from the LOOKING_DOWN camera: z = 3 - h(x_n z, -y_n z), by fixed point."""
    v, u = np.mgrid[0 : intrinsics["height"], 0 : intrinsics["width"]].astype(float)
    xn = (u - intrinsics["ppx"]) / intrinsics["fx"]
    yn = (v - intrinsics["ppy"]) / intrinsics["fy"]
    z = np.full_like(xn, 3.0)
    for _ in range(200):  # |dh/dz| <= |(xn, yn)| / 1.5 < 1: a contraction
        z = 3.0 - pile_surface(xn * z, -yn * z)
    return np.round(z / UNITS).astype(np.uint16)


def record(path: Path, serial: str, frames: list[np.ndarray], **kwargs: Any) -> Path:
    write_recording(path, serial, kwargs.pop("intrinsics", SMALL), frames, UNITS, 30, **kwargs)
    return path


def capture_one(config: Config) -> Any:
    return RealSenseCamera(config.cameras[0], config).capture()


# ---------------------------------------------------------------- geometry


def test_plane_points_equal_the_deprojection_at_default_resolution(tmp_path: Path) -> None:
    d455 = {"width": 848, "height": 480, "fx": 426.1, "fy": 425.7, "ppx": 423.4, "ppy": 241.2}
    path = record(tmp_path / "p.db3", "111", [plane(d455, 1.5)] * 5, intrinsics=d455)
    config = make_config([{"serial": "111", "playback": path}])
    assert (config.cameras[0].width, config.cameras[0].height) == (848, 480)

    cloud = capture_one(config)

    assert cloud.serial == "111"
    assert cloud.points.shape == (848 * 480, 3) and cloud.points.dtype == np.float32
    v, u = np.divmod(np.arange(848 * 480), 848)
    expected = np.stack(
        [(u - 423.4) / 426.1 * 1.5, (v - 241.2) / 425.7 * 1.5, np.full(u.shape, 1.5)], axis=1
    )
    np.testing.assert_allclose(cloud.points, expected, atol=1e-5)
    for pixel in [(0, 0), (847, 479), (400, 100)]:
        index = pixel[1] * 848 + pixel[0]
        want = rs.rs2_deproject_pixel_to_point(
            _rs_intrinsics(cloud.intrinsics), [float(pixel[0]), float(pixel[1])], 1.5
        )
        np.testing.assert_allclose(cloud.points[index], want, atol=1e-5)
    assert cloud.intrinsics == {
        **{k: pytest.approx(v) for k, v in d455.items()},
        "model": "brown_conrady",
        "coeffs": [0.0] * 5,
    }
    assert cloud.extra["firmware"] == "5.16.0.1"
    assert cloud.extra["depth_units"] == pytest.approx(UNITS)
    assert cloud.extra["frames_aggregated"] == 3
    assert cloud.extra["source"] == "playback" and cloud.extra["recording"] == "p.db3"
    assert cloud.extra["imu_present"] is False and "gravity" not in cloud.extra
    np.testing.assert_array_equal(cloud.extrinsic, np.asarray(LOOKING_DOWN, dtype=float))


def test_pile_through_the_default_filter_chain_lands_on_the_surface(tmp_path: Path) -> None:
    depth = pile_depth(SMALL)
    path = record(tmp_path / "pile.db3", "222", [depth] * 6)
    config = make_config(
        [{"serial": "222", "playback": path, "spatial_filter": True, "temporal_filter": True}]
    )
    assert config.cameras[0].aggregation == "median"

    cloud = capture_one(config)

    silo = cloud.points_in_silo()
    error = silo[:, 2] - pile_surface(silo[:, 0], silo[:, 1])
    assert len(silo) > 0.99 * SMALL["width"] * SMALL["height"]
    assert np.median(np.abs(error)) < 0.002
    assert np.percentile(np.abs(error), 99) < 0.03
    assert 0.9 < silo[:, 2].max() <= 1.0  # the apex is smoothed a little, not cut off
    assert cloud.extra["filters"] == [
        "threshold_filter",
        "disparity_transform",
        "spatial_filter",
        "temporal_filter",
        "disparity_transform",
    ]


def test_threshold_and_decimation_use_the_filtered_stream_intrinsics(tmp_path: Path) -> None:
    depth = plane(SMALL, 2.0)
    depth[:, :40] = round(0.2 / UNITS)  # nearer than min_depth_m: dropped by the threshold
    path = record(tmp_path / "d.db3", "333", [depth] * 5)
    config = make_config([{"serial": "333", "playback": path, "decimation": 2}])

    cloud = capture_one(config)

    assert (cloud.intrinsics["width"], cloud.intrinsics["height"]) == (80, 48)
    assert cloud.intrinsics["fx"] == pytest.approx(40.0)
    np.testing.assert_allclose(cloud.points[:, 2], 2.0, atol=1e-6)
    assert cloud.points[:, 0].min() > (40 - 1 - 79.5) / 80.0 * 2.0  # left band is gone
    assert 0.6 * 80 * 48 < len(cloud.points) < 0.8 * 80 * 48


@pytest.mark.parametrize("model", ["brown_conrady", "inverse_brown_conrady"])
def test_deproject_matches_librealsense_with_distortion(model: str) -> None:
    intrinsics = {**SMALL, "model": model, "coeffs": [0.08, -0.05, 0.001, -0.002, 0.01]}
    depth = np.linspace(0.5, 4.0, 96 * 160).reshape(96, 160)
    points, index = deproject(depth, intrinsics)
    assert len(index) == depth.size
    intr = _rs_intrinsics(intrinsics)
    for i in [0, 159, 5000, 96 * 160 - 1]:
        v, u = divmod(i, 160)
        want = rs.rs2_deproject_pixel_to_point(intr, [float(u), float(v)], float(depth[v, u]))
        np.testing.assert_allclose(points[i], want, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------- aggregation


def test_median_of_noisy_frames_reduces_noise_as_expected(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    sigma = 8.0  # depth units (mm)
    frames = [np.round(2000 + rng.normal(0, sigma, (96, 160))).astype(np.uint16) for _ in range(11)]
    path = record(tmp_path / "n.db3", "444", frames)
    single = capture_one(make_config([{"serial": "444", "playback": path, "frames": 1}]))
    nine = capture_one(make_config([{"serial": "444", "playback": path, "frames": 9}]))

    want = np.median(np.stack(frames[2:11]), axis=0).reshape(-1) * UNITS
    np.testing.assert_allclose(nine.points[:, 2], want, atol=1e-6)
    noise_1 = np.std(single.points[:, 2]) / UNITS
    noise_9 = np.std(nine.points[:, 2]) / UNITS
    assert noise_1 == pytest.approx(sigma, rel=0.05)
    # The median of n normal samples has a standard deviation of about 1.2533 sigma / sqrt(n).
    assert noise_9 == pytest.approx(1.2533 * sigma / 3, rel=0.1)
    assert nine.extra["frames_aggregated"] == 9


def test_temporal_aggregation_smooths_too(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    frames = [np.round(2000 + rng.normal(0, 8.0, (96, 160))).astype(np.uint16) for _ in range(10)]
    path = record(tmp_path / "t.db3", "445", frames)
    config = make_config(
        [
            {
                "serial": "445",
                "playback": path,
                "frames": 8,
                "temporal_filter": True,
                "aggregation": "temporal",
            }
        ]
    )
    cloud = capture_one(config)
    assert np.std(cloud.points[:, 2]) / UNITS < 0.7 * 8.0
    assert cloud.extra["aggregation"] == "temporal"


def test_median_ignores_missing_depth_and_drops_flickering_pixels() -> None:
    stack = np.array([[[1000, 0]], [[0, 0]], [[1010, 0]], [[1030, 500]]], dtype=np.uint16)
    got = median_of_valid(stack, 0.5)
    assert got[0, 0] == 1010.0  # median of 1000, 1010, 1030: the zero is not a sample
    assert got[0, 1] == 0.0  # depth in 1 of 4 frames: not trusted


# ---------------------------------------------------------------- several cameras, failures


def test_two_cameras_with_different_serials_are_both_captured(tmp_path: Path) -> None:
    a = record(tmp_path / "a.db3", "AAA1", [plane(SMALL, 1.0)] * 5)
    b = record(tmp_path / "b.db3", "BBB2", [plane(SMALL, 2.5)] * 5)
    config = make_config([{"serial": "AAA1", "playback": a}, {"serial": "BBB2", "playback": b}])

    result = capture_all(config)

    assert not result.degraded
    assert [c.serial for c in result.clouds] == ["AAA1", "BBB2"]
    assert [float(np.median(c.points[:, 2])) for c in result.clouds] == pytest.approx([1.0, 2.5])


def test_recording_that_ends_early_times_out_and_degrades_the_scan(tmp_path: Path) -> None:
    short = record(tmp_path / "short.db3", "SHORT", [plane(SMALL, 1.0)] * 3)
    good = record(tmp_path / "good.db3", "GOOD", [plane(SMALL, 1.0)] * 5)
    config = make_config(
        [
            {"serial": "SHORT", "playback": short, "frames": 5, "timeout_s": 1.0},
            {"serial": "GOOD", "playback": good},
        ]
    )

    result = capture_all(config)

    assert result.degraded
    assert [c.serial for c in result.clouds] == ["GOOD"]
    [failure] = result.failures
    assert failure.serial == "SHORT"
    assert "camera SHORT" in failure.error and "timed out after 1 s" in failure.error
    assert "3 of 7 frames" in failure.error


def test_missing_live_serial_is_a_clear_error() -> None:
    config = make_config([{"serial": "000000000000", "source": "realsense"}])
    connected = {d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()}
    with pytest.raises(CaptureError, match="camera 000000000000: not connected") as info:
        capture_one(config)
    if not connected:
        assert "no RealSense devices are connected" in str(info.value)
    else:
        assert all(serial in str(info.value) for serial in connected)


def test_missing_recording_file_is_a_clear_error(tmp_path: Path) -> None:
    config = make_config([{"serial": "X1", "playback": tmp_path / "nope.db3"}])
    result = capture_all(config)
    assert result.failures[0].serial == "X1"
    assert f"recording {tmp_path / 'nope.db3'} not found" in result.failures[0].error


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_corrupt_recording_is_a_clear_error(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "bad.db3"
    if damage == "garbage":
        path.write_bytes(b"this is not a rosbag2 database" * 100)
    else:
        record(tmp_path / "ok.db3", "C1", [plane(SMALL, 1.0)] * 5)
        path.write_bytes((tmp_path / "ok.db3").read_bytes()[:20000])
    config = make_config([{"serial": "C1", "playback": path}])
    with pytest.raises(CaptureError, match=r"camera C1: cannot play recording .*bad\.db3") as info:
        capture_one(config)
    assert "SQLite" in str(info.value) or "database" in str(info.value)


def test_recording_of_another_camera_is_refused(tmp_path: Path) -> None:
    path = record(tmp_path / "other.db3", "OTHER", [plane(SMALL, 1.0)] * 5)
    config = make_config([{"serial": "MINE", "playback": path}])
    with pytest.raises(CaptureError, match="is of camera 'OTHER', not 'MINE'"):
        capture_one(config)


# ---------------------------------------------------------------- colour and IMU


def test_colour_per_point(tmp_path: Path) -> None:
    depth = plane(SMALL, 1.2)
    color = np.zeros((96, 160, 3), np.uint8)
    color[:, :80] = (200, 10, 10)
    color[:, 80:] = (10, 10, 200)
    # Spare frames: the pipeline's depth/colour syncer may drop a pair when the machine is busy.
    path = record(tmp_path / "c.db3", "RGB1", [depth] * 15, color_frames=[color] * 15)
    cloud = capture_one(make_config([{"serial": "RGB1", "playback": path, "color": True}]))
    assert cloud.colors is not None and cloud.colors.shape == (96 * 160, 3)
    left = cloud.points[:, 0] < (70 - 79.5) / 80 * 1.2
    right = cloud.points[:, 0] > (90 - 79.5) / 80 * 1.2
    assert (cloud.colors[left] == (200, 10, 10)).all()
    assert (cloud.colors[right] == (10, 10, 200)).all()


def test_imu_gravity_is_stored_and_a_tilt_is_warned(tmp_path: Path) -> None:
    # Looking straight down, the accelerometer's reaction to gravity points back up the axis.
    level = record(tmp_path / "lvl.db3", "IMU1", [plane(SMALL, 2.0)] * 5, accel=(0, 0, -9.81))
    tilt = np.radians(10.0)
    knocked = record(
        tmp_path / "tilt.db3",
        "IMU2",
        [plane(SMALL, 2.0)] * 5,
        accel=(0, 9.81 * np.sin(tilt), -9.81 * np.cos(tilt)),
    )
    config = make_config(
        [{"serial": "IMU1", "playback": level}, {"serial": "IMU2", "playback": knocked}]
    )
    with structlog.testing.capture_logs() as logs:
        result = capture_all(config)

    first, second = result.clouds
    assert first.extra["imu_present"] is True
    np.testing.assert_allclose(first.extra["gravity"], [0, 0, 9.81], atol=1e-4)
    assert first.extra["gravity_samples"] == 5
    assert first.extra["gravity_angle_deg"] == pytest.approx(0.0, abs=1e-3)
    assert second.extra["gravity_angle_deg"] == pytest.approx(10.0, abs=1e-3)
    warnings = [e for e in logs if e["log_level"] == "warning"]
    assert [e["camera"] for e in warnings] == ["IMU2"]
    assert "knocked out of position" in warnings[0]["event"]


def _rs_intrinsics(values: dict[str, Any]) -> rs.intrinsics:
    intr = rs.intrinsics()
    intr.width, intr.height = values["width"], values["height"]
    intr.fx, intr.fy, intr.ppx, intr.ppy = values["fx"], values["fy"], values["ppx"], values["ppy"]
    intr.model = getattr(rs.distortion, values.get("model", "none"))
    intr.coeffs = values.get("coeffs", [0.0] * 5)
    return intr
