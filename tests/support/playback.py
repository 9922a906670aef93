"""Reading a recording back through real librealsense, the way the tests need it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyrealsense2 as rs


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
