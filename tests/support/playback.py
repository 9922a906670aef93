"""Reading a recording back through real librealsense, the way the tests need it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyrealsense2 as rs

from silo_agent.capture.recording import write_recording

PLAYBACK_INTRINSICS = {"width": 160, "height": 96, "fx": 80.0, "fy": 80.0, "ppx": 79.5, "ppy": 47.5}


def play_stream(path: Path, stream: rs.stream = rs.stream.depth) -> tuple[Any, list[np.ndarray]]:
    """Every frame of one stream; one stream per pipeline, so no syncer can pair or drop."""
    config = rs.config()
    config.enable_device_from_file(str(path), repeat_playback=False)
    config.enable_stream(stream)
    pipe = rs.pipeline()
    config.resolve(pipe).get_device().as_playback().set_real_time(False)  # before any frame
    profile = pipe.start(config)
    images = []
    try:
        while True:
            ok, frames = pipe.try_wait_for_frames(1000)
            if not ok:
                break
            images.append(np.asanyarray(frames.first(stream).get_data()).copy())
    finally:
        pipe.stop()
    return profile, images


def playback_config(tmp_path: Path, cameras: str) -> Path:
    """A config for playback cameras (`playback_camera` entries), its audit cache in `tmp_path`."""
    path = tmp_path / "silo.toml"
    path.write_text(
        f"""
[silo]
id = "silo-cli"
region = [[-1.5, -1.5], [1.5, -1.5], [1.5, 1.5], [-1.5, 1.5]]
floor_z = 0.0
bulk_density_t_m3 = 0.77

[reconstruction]
grid_step_m = 0.05

[audit]
directory = "{tmp_path / "audit"}"
{cameras}
"""
    )
    return path


def playback_camera(serial: str, playback: Path, **keys: object) -> str:
    """A `[[cameras]]` table playing `playback` back, looking straight down from 2 m."""
    extra = "".join(f"{k} = {json.dumps(v)}\n" for k, v in keys.items())
    return f"""
[[cameras]]
serial = "{serial}"
source = "playback"
playback = "{playback}"
# looking straight down from 2 m
extrinsic = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 2.0], [0, 0, 0, 1]]
warmup_frames = 2
frames = 3
timeout_s = 1.0
{extra}"""


def grain_layer(tmp_path: Path, serial: str, frames: int = 5) -> Path:
    """A flat grain surface 0.5 m above the floor, seen from 2 m: 1.5 m away, with D455-like
    depth noise (a few mm at 1.5 m)."""
    path = tmp_path / f"{serial}.db3"
    rng = np.random.default_rng(len(serial))
    depth = [
        np.round(1500 + rng.normal(0, 4.0, (96, 160))).astype(np.uint16) for _ in range(frames)
    ]
    write_recording(path, serial, PLAYBACK_INTRINSICS, depth, 0.001, 30)
    return path
