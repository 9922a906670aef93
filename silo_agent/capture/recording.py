"""Write synthetic RealSense recordings (rosbag2 `.db3`) from numpy depth images.

The simulator and the tests need recordings that play back through the very same `rs.pipeline`
code path as a field recording, so they are made by librealsense itself: a `software_device` that
looks like a D455 (serial, name, firmware, depth units, stereo baseline) wrapped in an
`rs.recorder`, fed one software frame per image.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pyrealsense2 as rs

D455_BASELINE_MM = 95.0  # lets the disparity filter of the post-processing chain work on playback
SYNTHETIC_FIRMWARE = "5.16.0.1"


def _intrinsics(values: Mapping[str, float]) -> rs.intrinsics:
    intr = rs.intrinsics()
    intr.width = int(values["width"])
    intr.height = int(values["height"])
    intr.fx, intr.fy = float(values["fx"]), float(values["fy"])
    intr.ppx, intr.ppy = float(values["ppx"]), float(values["ppy"])
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0] * 5
    return intr


def _video_stream(
    kind: rs.stream, fmt: rs.format, bpp: int, intr: rs.intrinsics, fps: int, uid: int
) -> rs.video_stream:
    stream = rs.video_stream()
    stream.type, stream.fmt, stream.bpp = kind, fmt, bpp
    stream.index, stream.uid = 0, uid
    stream.width, stream.height, stream.fps = intr.width, intr.height, fps
    stream.intrinsics = intr
    return stream


def _identity_extrinsics() -> rs.extrinsics:
    extr = rs.extrinsics()
    extr.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    extr.translation = [0.0, 0.0, 0.0]
    return extr


def _frame(
    image: np.ndarray, profile: rs.stream_profile, bpp: int, index: int, fps: int
) -> rs.software_video_frame:
    frame = rs.software_video_frame()
    frame.pixels = np.ascontiguousarray(image)
    frame.bpp = bpp
    frame.stride = image.shape[1] * bpp
    frame.timestamp = index * 1000.0 / fps
    frame.domain = rs.timestamp_domain.hardware_clock
    frame.frame_number = index + 1
    frame.profile = profile.as_video_stream_profile()
    return frame


def _accel_stream(fps: int) -> rs.motion_stream:
    stream = rs.motion_stream()
    stream.type, stream.fmt = rs.stream.accel, rs.format.motion_xyz32f
    stream.index, stream.uid, stream.fps = 0, 2, fps
    intr = rs.motion_device_intrinsic()
    intr.data = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
    intr.noise_variances = [0.0, 0.0, 0.0]
    intr.bias_variances = [0.0, 0.0, 0.0]
    stream.intrinsics = intr
    return stream


def _accel_frame(
    accel: Sequence[float], profile: rs.stream_profile, index: int, fps: int
) -> rs.software_motion_frame:
    vector = rs.vector()
    vector.x, vector.y, vector.z = (float(a) for a in accel)
    frame = rs.software_motion_frame()
    frame.data = vector
    frame.timestamp = index * 1000.0 / fps
    frame.domain = rs.timestamp_domain.hardware_clock
    frame.frame_number = index + 1
    frame.profile = profile.as_motion_stream_profile()
    return frame


def _check(frames: Sequence[np.ndarray], shape: tuple[int, ...], dtype: type, what: str) -> None:
    if not frames:
        raise ValueError(f"{what}: at least one frame is needed")
    for i, image in enumerate(frames):
        if image.shape != shape or image.dtype != dtype:
            raise ValueError(
                f"{what}[{i}]: expected shape {shape} {np.dtype(dtype).name}, "
                f"got {image.shape} {image.dtype}"
            )


def write_recording(
    path: Path,
    serial: str,
    intrinsics: dict,
    depth_frames: Sequence[np.ndarray],
    depth_units: float,
    fps: int,
    color_frames: Sequence[np.ndarray] | None = None,
    accel: Sequence[float] | None = None,
) -> None:
    """Record `depth_frames` (uint16 HxW, in `depth_units` metres) as a D455-like `.db3`.

    `intrinsics` has width, height, fx, fy, ppx, ppy (no distortion). Colour frames, when given,
    are RGB8 HxWx3 already aligned to depth (same intrinsics, identity extrinsics), one per depth
    frame with the same timestamp so the pipeline's syncer pairs them. `accel`, when given, adds
    a motion module whose accelerometer reads this vector (m/s², depth-camera axes; a level
    camera at rest reads about (0, -9.81, 0)) once per depth frame.
    """
    path = Path(path)
    width, height = int(intrinsics["width"]), int(intrinsics["height"])
    _check(depth_frames, (height, width), np.uint16, "depth_frames")
    if color_frames is not None:
        _check(color_frames, (height, width, 3), np.uint8, "color_frames")
        if len(color_frames) != len(depth_frames):
            raise ValueError("color_frames: one colour frame per depth frame is needed")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)  # the recorder refuses to append to an existing bag

    intr = _intrinsics(intrinsics)
    device = rs.software_device()
    device.register_info(rs.camera_info.name, "Intel RealSense D455")
    device.register_info(rs.camera_info.serial_number, serial)
    device.register_info(rs.camera_info.firmware_version, SYNTHETIC_FIRMWARE)
    device.register_info(rs.camera_info.product_line, "D400")
    device.register_info(rs.camera_info.usb_type_descriptor, "3.2")

    depth_sensor = device.add_sensor("Stereo Module")
    depth_profile = depth_sensor.add_video_stream(
        _video_stream(rs.stream.depth, rs.format.z16, 2, intr, fps, uid=0), True
    )
    depth_sensor.add_read_only_option(rs.option.depth_units, float(depth_units))
    depth_sensor.add_read_only_option(rs.option.stereo_baseline, D455_BASELINE_MM)

    color_sensor = color_profile = None
    if color_frames is not None:
        color_sensor = device.add_sensor("RGB Camera")
        color_profile = color_sensor.add_video_stream(
            _video_stream(rs.stream.color, rs.format.rgb8, 3, intr, fps, uid=1), True
        )
        depth_profile.register_extrinsics_to(color_profile, _identity_extrinsics())

    motion_sensor = motion_profile = None
    if accel is not None:
        motion_sensor = device.add_sensor("Motion Module")
        motion_profile = motion_sensor.add_motion_stream(_accel_stream(fps), True)
        motion_profile.register_extrinsics_to(depth_profile, _identity_extrinsics())

    recorder = rs.recorder(str(path), device)
    sensors = [(depth_sensor, depth_profile)]
    if color_sensor is not None:
        sensors.append((color_sensor, color_profile))
    if motion_sensor is not None:
        sensors.append((motion_sensor, motion_profile))
    for sensor, profile in sensors:
        sensor.open(profile)
        sensor.start(lambda _frame: None)
    try:
        for index, depth in enumerate(depth_frames):
            frame = _frame(depth, depth_profile, 2, index, fps)
            frame.depth_units = float(depth_units)
            depth_sensor.on_video_frame(frame)
            if color_sensor is not None and color_frames is not None:
                color = _frame(color_frames[index], color_profile, 3, index, fps)
                color_sensor.on_video_frame(color)
            if motion_sensor is not None and accel is not None:
                motion_sensor.on_motion_frame(_accel_frame(accel, motion_profile, index, fps))
    finally:
        for sensor, _profile in sensors:
            sensor.stop()
            sensor.close()
        del recorder  # the bag is finalised when the recorder is released
