"""Simulated cameras as rosbag2 `.db3` recordings, written by librealsense itself
(`silo_agent.capture.recording`), so they play back through the same pipeline as a field
recording: what the playback camera's tests and a hardware-free `source = "playback"` use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from silo_agent.capture.recording import write_recording
from silo_agent.sim.simulate import SimRig, SimView

GRAVITY_M_S2 = 9.80665


def accelerometer(view: SimView) -> list[float]:
    """What the camera's accelerometer reads at rest in its true pose: the reaction to
    gravity (silo +z) in depth-camera axes, so a tilted-by-calibration-error camera shows it."""
    return (GRAVITY_M_S2 * view.true[:3, :3].T @ np.array([0.0, 0.0, 1.0])).tolist()


def record_views(
    rig: SimRig,
    views: list[SimView],
    seed: int,
    directory: Path,
    frames: int,
    color: bool = False,
    fps: int = 30,
) -> list[Path]:
    """One `<serial>.db3` per camera with `frames` depth frames (and colour, accelerometer)."""
    paths = []
    for view in views:
        rendered = rig.frames(view, seed, frames, color)
        colors = [f.color for f in rendered if f.color is not None] if color else None
        path = Path(directory) / f"{view.serial}.db3"
        write_recording(
            path,
            view.serial,
            view.intrinsics.to_json(),
            [f.depth for f in rendered],
            rig.noise.depth_unit_m,
            fps,
            color_frames=colors,
            accel=accelerometer(view),
        )
        paths.append(path)
    return paths
