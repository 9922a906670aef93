"""Live frames from D455s and `.db3` recordings, through capture/realsense.py's own pipeline.

Each camera streams for the whole session (a full scan opens and closes its pipeline per
capture; a live map wants a frame twice a second). Every map takes the newest depth frame of
each camera through the configured post-processing chain without librealsense's temporal
filter: it blends successive frames, which over a moving robot smears it into the grain; the
live map's per-cell running value does the temporal part and knows when a cell really changed.

A camera configured with `color = true` streams colour too; a map the YOLO model is due for
aligns it to the depth frame (librealsense's align, only then: it costs a pass over the image).

The rays assume no lens distortion, as the D455's depth stream reports none (capture/realsense
undistorts for the full scan all the same).
"""

from __future__ import annotations

import contextlib
import time

import numpy as np
import pyrealsense2 as rs

from silo_agent.capture import CaptureError
from silo_agent.capture.realsense import (
    DeviceFault,
    RealSenseCamera,
    configure_depth_sensor,
    rgb_image,
)
from silo_agent.config import Config
from silo_agent.live.map import DepthFrame


class RealSenseFrameSource:
    """`source = "realsense"` and `"playback"` cameras, streaming while the session runs."""

    def __init__(self, config: Config, serials: list[str]) -> None:
        self._stack = contextlib.ExitStack()
        self._streams: list[
            tuple[RealSenseCamera, rs.pipeline, list[rs.filter], rs.align | None]
        ] = []
        try:
            for cam in (c for c in config.cameras if c.serial in serials):
                camera = RealSenseCamera(cam, config)  # CaptureError: no extrinsic, no file
                try:
                    pipe, profile = self._stack.enter_context(
                        camera._streaming(camera._depth_config())
                    )
                    if cam.source == "realsense":
                        configure_depth_sensor(profile.get_device().first_depth_sensor(), cam)
                except (RuntimeError, DeviceFault) as exc:
                    raise CaptureError(f"camera {cam.serial}: {exc}") from None
                chain = [f for f in camera._filters() if not f.is_temporal_filter()]
                align = rs.align(rs.stream.depth) if cam.color else None
                self._streams.append((camera, pipe, chain, align))
        except BaseException:
            self._stack.close()
            raise

    def frames(self, elapsed_s: float, color: bool = False) -> list[DepthFrame]:
        """The newest depth frame of every camera, filtered, with its colour aligned to it when
        `color` and the camera streams colour. CaptureError names a camera that gave none
        within its timeout_s (unplugged, or its recording ended)."""
        return [
            self._newest(camera, pipe, chain, align if color else None)
            for camera, pipe, chain, align in self._streams
        ]

    @staticmethod
    def _newest(
        camera: RealSenseCamera, pipe: rs.pipeline, chain: list[rs.filter], align: rs.align | None
    ) -> DepthFrame:
        timeout_s = camera._camera.timeout_s
        deadline = time.monotonic() + timeout_s
        try:
            depth = None
            while not depth:
                remaining_ms = int((deadline - time.monotonic()) * 1000)
                ok, frameset = pipe.try_wait_for_frames(max(remaining_ms, 0))
                if not ok:
                    raise CaptureError(
                        f"camera {camera.serial}: no depth frame within "
                        f"{timeout_s:g} s (unplugged, or the recording ended)"
                    )
                depth = frameset.get_depth_frame()  # the syncer may hand over colour alone
            rgb = None
            if align is not None:
                colour = align.process(frameset).get_color_frame()
                rgb = rgb_image(colour) if colour else None
            for step in chain:
                depth = step.process(depth)
            intr = depth.get_profile().as_video_stream_profile().get_intrinsics()
            return DepthFrame(
                camera.serial,
                np.asanyarray(depth.get_data()).copy(),
                depth.as_depth_frame().get_units(),
                intr.fx,
                intr.fy,
                intr.ppx,
                intr.ppy,
                camera._extrinsic,
                rgb,
            )
        except RuntimeError as exc:  # librealsense reports USB trouble from any call
            raise CaptureError(f"camera {camera.serial}: {exc}") from None

    def close(self) -> None:
        """Stop every pipeline (and unload every recording)."""
        self._stack.close()
