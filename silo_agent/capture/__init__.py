"""Capture: one raw cloud per configured camera, cameras one after another.

Every source (live D455, .db3 playback, simulator) implements `Camera`; `open_camera` picks the
implementation by `source` and imports it lazily, so pyrealsense2/open3d load only when used.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

from silo_agent.config import CameraConfig, Config
from silo_agent.scan import CameraCloud


class CaptureError(Exception):
    """A camera could not deliver a cloud; the message names the camera and the cause."""


class Camera(Protocol):
    serial: str

    def capture(self) -> CameraCloud:
        """One aggregated depth capture as a raw cloud in the camera frame. Raises CaptureError."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class CameraFailure:
    serial: str
    error: str


@dataclass
class CaptureResult:
    clouds: list[CameraCloud] = field(default_factory=list)
    failures: list[CameraFailure] = field(default_factory=list)

    @property
    def degraded(self) -> bool:
        return bool(self.failures)


def open_camera(camera: CameraConfig, config: Config, scan_number: int = 0) -> Camera:
    """The `Camera` for one `[[cameras]]` entry; `scan_number` (0, 1, ... since the agent
    started) lets a simulated camera play a scene sequence."""
    if camera.source == "sim":
        from silo_agent.capture.sim import SimCamera

        return SimCamera(camera, config, scan_number)
    from silo_agent.capture.realsense import RealSenseCamera

    return RealSenseCamera(camera, config)


def capture_all(config: Config, scan_number: int = 0) -> CaptureResult:
    """Capture every configured camera in turn; a failing camera is recorded, not fatal."""
    result = CaptureResult()
    for camera_config in config.cameras:
        try:
            camera = open_camera(camera_config, config, scan_number)
            try:
                cloud = camera.capture()
            finally:
                camera.close()
            result.clouds.append(_with_points(cloud, camera_config.serial))
        except CaptureError as exc:
            result.failures.append(CameraFailure(camera_config.serial, str(exc)))
    return result


def _with_points(cloud: CameraCloud, serial: str) -> CameraCloud:
    """`cloud`, if it kept a point through the capture's filtering (`scan.measured_only`).

    An empty cloud is a camera that measured nothing (pointed at nothing, blinded, covered),
    and written into the scan its 0-point cloud file would make the whole scan unreadable,
    so it fails the camera like any other capture error. Raises CaptureError."""
    if len(cloud.points):
        return cloud
    dropped = cloud.not_measurements
    why = f" ({dropped} points without a return or out of the depth range)" if dropped else ""
    raise CaptureError(f"camera {serial}: no valid depth pixels{why}")
