"""RealSense D4xx capture through pyrealsense2, live by serial or from a `.db3` recording.

Live cameras and recordings go through the same `rs.pipeline` code, so a field recording (or a
synthetic one from `recording.write_recording`) exercises exactly what runs on the gateway.
One capture: warm-up frames (auto-exposure settles), then N frames through the camera's own
post-processing chain, aggregated per pixel, deprojected with the stream's own intrinsics.
A live camera that times out or errors is hardware-reset and retried a bounded number of times.
"""

from __future__ import annotations

import contextlib
import functools
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyrealsense2 as rs
import structlog

from silo_agent.capture import CaptureError
from silo_agent.config import CameraConfig, Config
from silo_agent.grid.geometry import gravity_angle_deg
from silo_agent.scan import CameraCloud, measured_only

log = structlog.get_logger(__name__)

_PRESETS = {
    "default": rs.rs400_visual_preset.default,
    "high_accuracy": rs.rs400_visual_preset.high_accuracy,
    "high_density": rs.rs400_visual_preset.high_density,
    "medium_density": rs.rs400_visual_preset.medium_density,
    "hand": rs.rs400_visual_preset.hand,
}
_TEMPERATURES = {
    "asic": rs.option.asic_temperature,
    "projector": rs.option.projector_temperature,
}
_RESET_SETTLE_S = 2.0  # a reset device takes this long to drop off the bus before it returns
_POLL_S = 0.5
_DRAIN_S = 30.0  # a long field recording, read without real-time pacing, ends well within this


@functools.cache
def _context() -> rs.context:
    """The process's one librealsense context.

    Destroying a context while its playback devices still have worker threads crashes
    librealsense 2.59 (SIGSEGV in a dispatcher thread), so contexts are never destroyed.
    """
    return rs.context()


class DeviceFault(Exception):
    """A timeout or librealsense error on an open device: what a hardware reset may cure."""


# ---------------------------------------------------------------- devices


@dataclass(frozen=True)
class DeviceInfo:
    serial: str
    name: str
    firmware: str
    usb_type: str
    has_imu: bool

    @property
    def usb2(self) -> bool:
        """USB 2 cannot carry 848x480 depth at 30 fps reliably: the operator must know."""
        return self.usb_type.startswith("2")


def _info(obj: rs.device | rs.sensor, key: rs.camera_info) -> str:
    return obj.get_info(key) if obj.supports(key) else ""


def _has_imu(device: rs.device) -> bool:
    return any(sensor.is_motion_sensor() for sensor in device.sensors)


def _connected(context: rs.context) -> dict[str, rs.device]:
    return {_info(d, rs.camera_info.serial_number): d for d in context.query_devices()}


def list_devices() -> list[DeviceInfo]:
    """Every RealSense device on the bus, for `silo-agent devices` and error messages."""
    return [
        DeviceInfo(
            serial=serial,
            name=_info(device, rs.camera_info.name),
            firmware=_info(device, rs.camera_info.firmware_version),
            usb_type=_info(device, rs.camera_info.usb_type_descriptor),
            has_imu=_has_imu(device),
        )
        for serial, device in sorted(_connected(_context()).items())
    ]


def _not_connected(serial: str) -> CaptureError:
    devices = list_devices()
    if devices:
        listing = ", ".join(f"{d.serial} ({d.name})" for d in devices)
        return CaptureError(
            f"camera {serial}: not connected; connected RealSense devices: {listing}"
        )
    return CaptureError(f"camera {serial}: not connected; no RealSense devices are connected")


# ---------------------------------------------------------------- pure numpy


def intrinsics_dict(intr: rs.intrinsics) -> dict[str, Any]:
    return {
        "width": intr.width,
        "height": intr.height,
        "fx": intr.fx,
        "fy": intr.fy,
        "ppx": intr.ppx,
        "ppy": intr.ppy,
        "model": intr.model.name,
        "coeffs": [float(c) for c in intr.coeffs],
    }


def deproject(depth_m: np.ndarray, intrinsics: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with depth -> (points (N,3) float32 in the camera frame, their flat pixel indices).

    Same maths as librealsense's `rs2_deproject_pixel_to_point`, for the whole image at once.
    """
    width = depth_m.shape[1]
    index = np.flatnonzero(np.isfinite(depth_m) & (depth_m > 0))
    v, u = np.divmod(index, width)
    z = depth_m.reshape(-1)[index].astype(np.float64)
    x = (u - intrinsics["ppx"]) / intrinsics["fx"]
    y = (v - intrinsics["ppy"]) / intrinsics["fy"]
    model = intrinsics.get("model", "none")
    coeffs = intrinsics.get("coeffs") or [0.0] * 5
    if any(coeffs) and model in ("brown_conrady", "inverse_brown_conrady"):
        x, y = _undistort(x, y, coeffs, inverse=model == "inverse_brown_conrady")
    elif any(coeffs) and model != "none":
        raise ValueError(f"cannot deproject through distortion model {model!r}")
    points = np.stack([x * z, y * z, z], axis=1).astype(np.float32)
    return points, index


def _undistort(
    x: np.ndarray, y: np.ndarray, c: list[float], inverse: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Iterative inversion of the Brown-Conrady model, as librealsense does it (10 steps)."""
    xo, yo = x, y
    for _ in range(10):
        r2 = x * x + y * y
        icdist = 1.0 / (1.0 + ((c[4] * r2 + c[1]) * r2 + c[0]) * r2)
        xq, yq = (x / icdist, y / icdist) if inverse else (x, y)
        dx = 2 * c[2] * xq * yq + c[3] * (r2 + 2 * xq * xq)
        dy = 2 * c[3] * xq * yq + c[2] * (r2 + 2 * yq * yq)
        x, y = (xo - dx) * icdist, (yo - dy) * icdist
    return x, y


def median_of_valid(stack: np.ndarray, min_valid_fraction: float) -> np.ndarray:
    """Per-pixel median over frames (N,H,W) of the non-zero samples; 0 where too few had depth.

    Zero is librealsense's "no depth": averaging it in would pull the surface toward the lens.
    """
    count = np.count_nonzero(stack, axis=0)
    values = stack.astype(np.float64)
    values[stack == 0] = np.nan
    values.sort(axis=0)  # NaN sorts last: the first `count` entries are the valid samples
    last = stack.shape[0] - 1
    lo = np.clip((count - 1) // 2, 0, last)[None]
    hi = np.clip(count // 2, 0, last)[None]
    median = 0.5 * (np.take_along_axis(values, lo, 0)[0] + np.take_along_axis(values, hi, 0)[0])
    needed = max(1, math.ceil(min_valid_fraction * stack.shape[0]))
    return np.where(count >= needed, median, 0.0)


# ---------------------------------------------------------------- camera


@dataclass
class _Frames:
    depth: np.ndarray  # aggregated, float, in depth units
    units: float
    intrinsics: dict[str, Any]
    color: np.ndarray | None  # (H, W, 3) uint8 RGB aligned to the unfiltered depth
    exposure_us: float | None


class RealSenseCamera:
    """One `[[cameras]]` entry with `source = "realsense"` (live) or `"playback"` (`.db3`)."""

    def __init__(self, camera: CameraConfig, config: Config) -> None:
        self.serial = camera.serial
        self._camera = camera
        self._live = camera.source == "realsense"
        extrinsic = camera.extrinsic_matrix()
        if extrinsic is None:
            raise CaptureError(f"camera {self.serial}: needs an extrinsic")
        self._extrinsic = extrinsic
        self._recording = Path(camera.playback) if camera.playback is not None else None
        if not self._live and (self._recording is None or not self._recording.is_file()):
            raise CaptureError(f"camera {self.serial}: recording {self._recording} not found")

    def capture(self) -> CameraCloud:
        """Capture, with hardware reset and bounded retries for live devices."""
        attempts = 1 + self._camera.retries if self._live else 1
        for attempt in range(1, attempts):
            try:
                return self._attempt()
            except DeviceFault as exc:
                log.warning(
                    "capture failed, resetting camera",
                    camera=self.serial,
                    error=str(exc),
                    attempt=attempt,
                    of=attempts,
                )
                self._reset()
        try:
            return self._attempt()
        except DeviceFault as exc:
            tries = f" (after {attempts} attempts)" if attempts > 1 else ""
            raise CaptureError(f"camera {self.serial}: {exc}{tries}") from None

    def _attempt(self) -> CameraCloud:
        try:
            return self._capture_once()
        except RuntimeError as exc:  # librealsense reports USB trouble from any call
            raise DeviceFault(str(exc)) from None

    def close(self) -> None:
        """Nothing to release: each capture starts and stops its own pipeline, so a stuck
        device is never left claimed between scans."""

    # -------------------------------------------------------- one attempt

    def _device_config(self) -> rs.config:
        """A pipeline config selecting this camera: the live device, or the recording."""
        cfg = rs.config()
        if self._live:
            if self.serial not in _connected(_context()):
                raise _not_connected(self.serial)
            cfg.enable_device(self.serial)
        else:
            cfg.enable_device_from_file(str(self._recording), repeat_playback=False)
        return cfg

    def _depth_config(self) -> rs.config:
        cfg = self._device_config()
        cam = self._camera
        if self._live:
            cfg.enable_stream(rs.stream.depth, cam.width, cam.height, rs.format.z16, cam.fps)
            if cam.color:
                cfg.enable_stream(rs.stream.color, cam.width, cam.height, rs.format.rgb8, cam.fps)
        else:  # a recording plays what it holds
            cfg.enable_stream(rs.stream.depth)
            if cam.color:
                cfg.enable_stream(rs.stream.color)
        return cfg

    @contextlib.contextmanager
    def _streaming(self, cfg: rs.config) -> Iterator[tuple[rs.pipeline, rs.pipeline_profile]]:
        """A started pipeline; always stopped, and a recording always unloaded, afterwards."""
        pipe = rs.pipeline(_context())
        try:
            try:
                if not self._live:
                    device = cfg.resolve(pipe).get_device()
                    self._check_recorded_serial(device)
                    # Non-real-time before the first frame: playback waits for us, drops nothing.
                    device.as_playback().set_real_time(False)
                profile = pipe.start(cfg)
            except RuntimeError as exc:
                if self._live:
                    raise DeviceFault(f"cannot start streaming: {exc}") from None
                raise CaptureError(
                    f"camera {self.serial}: cannot play recording {self._recording}: {exc}"
                ) from None
            try:
                yield pipe, profile
            finally:
                if not self._live:
                    with contextlib.suppress(RuntimeError):
                        _drain(pipe, profile.get_device().as_playback())
                with contextlib.suppress(RuntimeError):  # a dead device must not hide the cause
                    pipe.stop()
        finally:
            if not self._live:  # the shared context must not keep (possibly broken) recordings
                with contextlib.suppress(RuntimeError):
                    _context().unload_device(str(self._recording))

    def _check_recorded_serial(self, device: rs.device) -> None:
        recorded = _info(device, rs.camera_info.serial_number)
        if recorded != self.serial:
            raise CaptureError(
                f"camera {self.serial}: recording {self._recording} is of camera "
                f"{recorded!r}, not {self.serial!r}"
            )

    def _capture_once(self) -> CameraCloud:
        deadline = time.monotonic() + self._camera.timeout_s
        with self._streaming(self._depth_config()) as (pipe, profile):
            device = profile.get_device()
            sensor = device.first_depth_sensor()
            if self._live:
                configure_depth_sensor(sensor, self._camera)
            frames = self._collect(pipe, deadline)
            extra = self._metadata(device, sensor, frames)
        try:
            points, index = deproject(frames.depth * frames.units, frames.intrinsics)
        except ValueError as exc:
            raise CaptureError(f"camera {self.serial}: {exc}") from None
        colors = None
        if frames.color is not None:
            colors = _colors_at(frames.color, index, frames.depth.shape)
        if extra["imu_present"]:
            extra.update(self._gravity())
        cloud = CameraCloud(
            serial=self.serial,
            points=points,
            extrinsic=self._extrinsic,
            intrinsics=frames.intrinsics,
            colors=colors,
            extra=extra,
        )
        return measured_only(cloud)  # as read back from the audit cache, to the bit

    def _filters(self) -> list[rs.filter]:
        """librealsense's recommended chain; disparity domain for the edge-preserving filters."""
        cam = self._camera
        chain: list[rs.filter] = []
        if cam.decimation > 1:
            chain.append(rs.decimation_filter(float(cam.decimation)))
        chain.append(rs.threshold_filter(cam.min_depth_m, cam.max_depth_m))
        if cam.spatial_filter or cam.temporal_filter:
            chain.append(rs.disparity_transform(True))
            if cam.spatial_filter:
                chain.append(rs.spatial_filter())
            if cam.temporal_filter:
                chain.append(rs.temporal_filter())
            chain.append(rs.disparity_transform(False))
        return chain

    def _wait(self, pipe: rs.pipeline, deadline: float, got: int) -> rs.composite_frame:
        remaining_ms = int((deadline - time.monotonic()) * 1000)
        if remaining_ms > 0:
            ok, frames = pipe.try_wait_for_frames(remaining_ms)
            if ok:
                return frames
        cam = self._camera
        raise DeviceFault(
            f"timed out after {cam.timeout_s:g} s with {got} of {cam.warmup_frames + cam.frames} "
            f"frames ({cam.warmup_frames} warm-up + {cam.frames} to aggregate)"
        )

    def _collect(self, pipe: rs.pipeline, deadline: float) -> _Frames:
        cam = self._camera
        chain = self._filters()
        align = rs.align(rs.stream.depth) if cam.color else None
        depth_images: list[np.ndarray] = []
        color = None
        exposure = None
        filtered = None
        got = 0
        while len(depth_images) < cam.frames:
            frameset = self._wait(pipe, deadline, got)
            if not frameset.get_depth_frame():  # the syncer may hand over colour alone
                continue
            got += 1
            if got <= cam.warmup_frames:
                continue
            if align is not None:
                frameset = align.process(frameset)
                color_frame = frameset.get_color_frame()
                if color_frame:
                    color = rgb_image(color_frame)
            raw = frameset.get_depth_frame()
            if raw.supports_frame_metadata(rs.frame_metadata_value.actual_exposure):
                exposure = float(raw.get_frame_metadata(rs.frame_metadata_value.actual_exposure))
            filtered = raw
            for step in chain:
                filtered = step.process(filtered)
            depth_images.append(np.asanyarray(filtered.get_data()).copy())
        assert filtered is not None  # frames >= 1 (config)
        if cam.aggregation == "median":
            depth = median_of_valid(np.stack(depth_images), cam.min_valid_fraction)
        else:  # the temporal filter has already blended the N frames into the last one
            depth = depth_images[-1].astype(np.float64)
        intr = filtered.get_profile().as_video_stream_profile().get_intrinsics()
        return _Frames(
            depth=depth,
            units=filtered.as_depth_frame().get_units(),
            intrinsics=intrinsics_dict(intr),
            color=color,
            exposure_us=exposure,
        )

    def _metadata(self, device: rs.device, sensor: rs.sensor, frames: _Frames) -> dict[str, Any]:
        cam = self._camera
        extra: dict[str, Any] = {
            "source": cam.source,
            "name": _info(device, rs.camera_info.name),
            "firmware": _info(device, rs.camera_info.firmware_version),
            "depth_units": frames.units,
            "frames_aggregated": cam.frames,
            "warmup_frames": cam.warmup_frames,
            "aggregation": cam.aggregation,
            "filters": [type(step).__name__ for step in self._filters()],
            "depth_range_m": [cam.min_depth_m, cam.max_depth_m],
            "imu_present": _has_imu(device),
        }
        usb = _info(device, rs.camera_info.usb_type_descriptor)
        if usb:
            extra["usb_type"] = usb
        if self._recording is not None and not self._live:
            extra["recording"] = self._recording.name
        if frames.exposure_us is not None:
            extra["exposure_us"] = frames.exposure_us
        temperatures = {
            name: float(sensor.get_option(option))
            for name, option in _TEMPERATURES.items()
            if sensor.supports(option)
        }
        if temperatures:
            extra["temperature_c"] = temperatures
        return extra

    # -------------------------------------------------------- IMU

    def _gravity(self) -> dict[str, Any]:
        """Mean accelerometer reading while static, as gravity (pointing down) in depth axes.

        An IMU problem never fails the capture: the depth is good, the check is advisory.
        """
        samples: list[tuple[float, float, float]] = []
        try:
            cfg = self._device_config()
            cfg.enable_stream(rs.stream.accel)
            with self._streaming(cfg) as (pipe, profile):
                rotation = _accel_to_depth_rotation(profile)
                deadline = time.monotonic() + self._camera.timeout_s
                while len(samples) < self._camera.imu_samples:
                    remaining_ms = int((deadline - time.monotonic()) * 1000)
                    # A second of silence from a 100+ Hz sensor: it (or the recording) stopped.
                    ok, frameset = pipe.try_wait_for_frames(max(1, min(remaining_ms, 1000)))
                    if not ok:
                        break
                    for frame in frameset:
                        if frame.is_motion_frame():
                            data = frame.as_motion_frame().get_motion_data()
                            samples.append((data.x, data.y, data.z))
        except (RuntimeError, DeviceFault, CaptureError) as exc:
            log.warning("cannot read the IMU", camera=self.serial, error=str(exc))
            return {}
        if not samples:
            log.warning("the IMU delivered no samples", camera=self.serial)
            return {}
        gravity = -(rotation @ np.mean(samples, axis=0))  # the accelerometer reads the reaction
        angle = gravity_angle_deg(gravity, self._extrinsic)
        if angle > self._camera.gravity_tolerance_deg:
            log.warning(
                "camera tilt disagrees with its extrinsic: knocked out of position?",
                camera=self.serial,
                angle_deg=round(angle, 2),
                tolerance_deg=self._camera.gravity_tolerance_deg,
            )
        return {
            "gravity": [float(g) for g in gravity],
            "gravity_samples": len(samples),
            "gravity_angle_deg": angle,
        }

    # -------------------------------------------------------- recovery

    def _reset(self) -> None:
        """hardware_reset() the device, then wait (bounded) for it to re-enumerate."""
        try:
            device = _connected(_context()).get(self.serial)
            if device is not None:
                device.hardware_reset()
        except RuntimeError as exc:
            log.warning("hardware reset failed", camera=self.serial, error=str(exc))
        time.sleep(_RESET_SETTLE_S)
        deadline = time.monotonic() + self._camera.reset_wait_s
        while time.monotonic() < deadline:
            with contextlib.suppress(RuntimeError):  # enumeration can fail while it comes back
                if self.serial in _connected(_context()):
                    return
            time.sleep(_POLL_S)
        log.warning(
            "camera did not re-enumerate after reset",
            camera=self.serial,
            waited_s=self._camera.reset_wait_s,
        )


def _drain(pipe: rs.pipeline, playback: rs.playback) -> None:
    """Read a non-real-time recording to its end before the pipeline stops.

    librealsense 2.59 can crash (pure virtual call, SIGSEGV) when a playback device is stopped
    or destroyed while its reader thread is blocked handing a frame to a pipeline nobody reads;
    at the end of the file the reader is idle. Reading without a consumer's work is fast.
    """
    deadline = time.monotonic() + _DRAIN_S
    while playback.current_status() != rs.playback_status.stopped:
        if time.monotonic() > deadline:
            log.warning("recording still playing after draining", file=playback.file_name())
            return
        pipe.try_wait_for_frames(100)


def configure_depth_sensor(sensor: rs.sensor, cam: CameraConfig) -> None:
    """Live depth settings: preset first (it may change the others), then emitter and laser."""
    settings = [
        (rs.option.visual_preset, float(_PRESETS[cam.visual_preset])),
        (rs.option.emitter_enabled, 1.0 if cam.emitter else 0.0),
    ]
    if cam.laser_power_mw is not None and cam.emitter:
        settings.append((rs.option.laser_power, cam.laser_power_mw))
    for option, value in settings:
        if sensor.supports(option) and not sensor.is_option_read_only(option):
            limits = sensor.get_option_range(option)
            sensor.set_option(option, min(max(value, limits.min), limits.max))


def record_camera(cam: CameraConfig, path: Path, seconds: float) -> int:
    """Record a live camera, with the capture's settings, to a `.db3` for field support.

    Depth (and colour when configured) at the capture's size and rate, plus the accelerometer
    when the camera has one, so the recording replays through `source = "playback"` exactly
    like a capture. Returns the number of framesets recorded.
    """
    if path.exists():
        raise CaptureError(f"camera {cam.serial}: {path} already exists; not overwritten")
    device = _connected(_context()).get(cam.serial)
    if device is None:
        raise _not_connected(cam.serial)
    cfg = rs.config()
    cfg.enable_device(cam.serial)
    cfg.enable_stream(rs.stream.depth, cam.width, cam.height, rs.format.z16, cam.fps)
    if cam.color:
        cfg.enable_stream(rs.stream.color, cam.width, cam.height, rs.format.rgb8, cam.fps)
    if _has_imu(device):
        cfg.enable_stream(rs.stream.accel)
    cfg.enable_record_to_file(str(path))
    pipe = rs.pipeline(_context())
    try:
        profile = pipe.start(cfg)
    except RuntimeError as exc:
        raise CaptureError(f"camera {cam.serial}: cannot start recording: {exc}") from None
    framesets = 0
    try:
        configure_depth_sensor(profile.get_device().first_depth_sensor(), cam)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            ok, _frames = pipe.try_wait_for_frames(int(cam.timeout_s * 1000))
            if not ok:
                raise CaptureError(
                    f"camera {cam.serial}: no frame for {cam.timeout_s:g} s while recording"
                )
            framesets += 1
    except RuntimeError as exc:
        raise CaptureError(f"camera {cam.serial}: recording failed: {exc}") from None
    finally:
        with contextlib.suppress(RuntimeError):
            pipe.stop()
    return framesets


def rgb_image(frame: rs.video_frame) -> np.ndarray | None:
    image = np.asanyarray(frame.get_data())
    fmt = frame.get_profile().format()
    if fmt == rs.format.rgb8:
        return image.copy()
    if fmt == rs.format.bgr8:
        return image[..., ::-1].copy()
    log.warning("colour format not supported, points left uncoloured", format=str(fmt))
    return None


def _colors_at(color: np.ndarray, index: np.ndarray, depth_shape: tuple[int, ...]) -> np.ndarray:
    """Colour of each point; the aligned colour has the undecimated size, so scale the pixel."""
    height, width = depth_shape
    v, u = np.divmod(index, width)
    cv = np.minimum(v * color.shape[0] // height, color.shape[0] - 1)
    cu = np.minimum(u * color.shape[1] // width, color.shape[1] - 1)
    return color[cv, cu].astype(np.uint8)


def _accel_to_depth_rotation(profile: rs.pipeline_profile) -> np.ndarray:
    """Rotation from accelerometer to depth axes (librealsense stores it column-major)."""
    accel = profile.get_stream(rs.stream.accel)
    depth_profiles = [
        p
        for p in profile.get_device().first_depth_sensor().get_stream_profiles()
        if p.stream_type() == rs.stream.depth
    ]
    try:
        extrinsics = accel.get_extrinsics_to(depth_profiles[0])
    except (RuntimeError, IndexError):
        log.debug("no IMU-to-depth extrinsics, assuming aligned axes")
        return np.eye(3)
    return np.asarray(extrinsics.rotation, dtype=float).reshape(3, 3).T
