"""A live session: capture the newest frames, update the live map, publish, at most `rate_hz`.

Pacing: captures are a period apart, and timed so that a map goes out as soon as it is built
(the capture leads the send by the median of the recent build times); sends are never closer
than a period. A map's age at sending is its build time, not the slowest build of the session.

The session runs in its own thread. With a YOLO model configured (`[detection.onnx]`), the maps
it is due for bring colour frames, and its robot sightings are held with the depth ones
(live/model.py). The agent suspends it while a full scan has the cameras
and resumes it afterwards; the map's state, the sequence numbers and the deadline carry over
(the deadline is wall time: a scan in between counts against `duration_s`).
"""

from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Protocol

import numpy as np
import structlog

from silo_agent.capture import CaptureError
from silo_agent.config import Config
from silo_agent.detect.piles import ModelError
from silo_agent.grid.grid import Grid
from silo_agent.grid.heightmap import HeightMap
from silo_agent.live.map import DepthFrame, LiveMap
from silo_agent.live.model import LiveRobotModel
from silo_agent.telemetry.client import LiveMapTooLarge
from silo_agent.telemetry.heightmap_codec import encode_live_heightmap

log = structlog.get_logger(__name__)

SIM_MESH_STEP_M = 0.03  # the moving world is rebuilt every frame: coarse enough for 2 Hz
BUILD_WINDOW = 5  # recent maps whose median build time paces the captures


class FrameSource(Protocol):
    def frames(self, elapsed_s: float, color: bool = False) -> list[DepthFrame]:
        """The newest depth frame of every camera, with its aligned colour image when `color`
        and the camera streams colour. Raises CaptureError."""
        ...

    def close(self) -> None: ...


class SimFrameSource:
    """`source = "sim"` cameras watching the moving-robot scene (sim/robot.py), at their
    configured views and resolution; the scene's clock is the session's."""

    def __init__(self, config: Config, serials: list[str]) -> None:
        from silo_agent.sim.robot import RobotRig

        cameras = [c for c in config.cameras if c.serial in serials]
        missing = [c.serial for c in cameras if c.source != "sim" or c.view is None]
        if missing:
            raise CaptureError(
                f"live mode runs on sim cameras with a view; not on {', '.join(missing)}"
            )
        self._rig = RobotRig(
            views=tuple(c.view for c in cameras if c.view is not None),
            seed=config.simulation.seed,
            width=cameras[0].width,
            height=cameras[0].height,
            mesh_step=SIM_MESH_STEP_M,
        )
        self._serials = [c.serial for c in cameras]
        self._colored = [c.color for c in cameras]
        self._count = 0

    def frames(self, elapsed_s: float, color: bool = False) -> list[DepthFrame]:
        self._count += 1
        rendered = self._rig.frames(elapsed_s, self._count, color and any(self._colored))
        return [
            DepthFrame.rendered(serial, f, view.nominal, f.color if colored else None)
            for serial, colored, view, f in zip(
                self._serials, self._colored, self._rig.views, rendered, strict=True
            )
        ]

    def close(self) -> None:
        """Nothing to release."""


def open_source(config: Config) -> FrameSource:
    """The live cameras: all simulated, or all D455s and recordings. Raises CaptureError."""
    serials = config.live.cameras or [c.serial for c in config.cameras]
    sources = {c.source for c in config.cameras if c.serial in serials}
    if sources == {"sim"}:
        return SimFrameSource(config, serials)
    if "sim" in sources:
        raise CaptureError(
            "live mode cannot mix sim cameras with D455s or recordings; "
            "choose them with [live] cameras"
        )
    from silo_agent.live.realsense_frames import RealSenseFrameSource

    return RealSenseFrameSource(config, serials)


@dataclass
class LiveStats:
    maps: int = 0
    last_map_s: float = 0.0


class LiveSession:
    """One `P/cmd/live` session. `start()`, `suspend()`, `resume()`, `stop()`; `on_end` is
    called once, from the session's thread or `stop()`, with why it ended."""

    def __init__(
        self,
        config: Config,
        session_id: str,
        rate_hz: float,
        duration_s: float,
        publish: Callable[[bytes, float], None],
        on_end: Callable[[str], None],
        start_map: HeightMap | None = None,
        open_frames: Callable[[Config], FrameSource] = open_source,
    ) -> None:
        """`open_frames` opens the cameras (at each start and resume)."""
        self.config = config
        self._open_frames = open_frames
        self.session_id = session_id
        self.rate_hz = rate_hz
        self.deadline = time.monotonic() + duration_s
        self.started = time.monotonic()
        site = config.silo
        # `region`, or a bin's wall (a bin config may give no `region`)
        grid = Grid.over(site.region_polygon(), config.live.grid_step_m)
        self.map = LiveMap(
            grid,
            config.live,
            site.ceiling_z,
            start_map,
            site.bin_shape(),
            config.reconstruction.depth_noise_factor,
        )
        self.stats = LiveStats()
        self._publish = publish
        self._on_end = on_end
        self._source: FrameSource | None = None  # open while capturing
        self._model: LiveRobotModel | None = None  # loaded at the first start
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ended = False
        self._lock = threading.Lock()
        self._sent = -np.inf  # when the last map went out (across suspend and resume)

    @property
    def active(self) -> bool:
        return not self._ended

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._loop, name=f"live-{self.session_id}", daemon=True
        )
        self._thread.start()

    resume = start

    def suspend(self) -> None:
        """Stop capturing and release the cameras (a full scan needs them); `resume` opens
        them again."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._thread = None
        if self._source is not None:
            self._source.close()
            self._source = None

    def stop(self, reason: str) -> None:
        self.suspend()
        self._end(reason)

    def _end(self, reason: str) -> None:
        with self._lock:
            if self._ended:
                return
            self._ended = True
        if self._source is not None:
            self._source.close()
            self._source = None
        log.info("live session ended", session=self.session_id, reason=reason, maps=self.stats.maps)
        self._on_end(reason)

    def _loop(self) -> None:
        """The session's thread; whatever ends it ends the session with a reply (a thread
        that died silently would be resumed by the agent, and fail again, for ever)."""
        try:
            self._capture()
        except BaseException as exc:
            log.exception("live session failed", session=self.session_id)
            self._end(f"internal error: {exc!r}")

    def _capture(self) -> None:
        period = 1.0 / self.rate_hz
        try:
            self._source = self._open_frames(self.config)  # here, not in the agent's loop: seconds
        except CaptureError as exc:
            self._end(f"cannot capture: {exc}")
            return
        if self._model is None and LiveRobotModel.wanted(self.config):
            try:
                self._model = LiveRobotModel(self.config)
            except ModelError as exc:
                self._end(f"cannot load the robot model: {exc}")
                return
        source, model = self._source, self._model
        builds: deque[float] = deque(maxlen=BUILD_WINDOW)
        next_capture = time.monotonic()
        while not self._stop.wait(max(0.0, next_capture - time.monotonic())):
            began = time.monotonic()
            taken = datetime.now(UTC)
            if began >= self.deadline:
                self._end("duration reached")
                return
            try:
                payload = self._build(source, model, began, taken)
            except CaptureError as exc:
                log.error("live capture failed", session=self.session_id, error=str(exc))
                self._end(f"capture failed: {exc}")
                return
            except Exception as exc:  # a bug must not leave a dead session marked active
                log.exception("live map failed", session=self.session_id)
                self._end(f"internal error: {exc}")
                return
            built = time.monotonic()
            self.stats.last_map_s = built - began
            builds.append(built - began)
            # out as soon as it is built, but never closer than a period to the last map
            if self._stop.wait(max(0.0, self._sent + period - built)):
                return
            try:
                self._publish(payload, period)
            except LiveMapTooLarge as exc:
                log.error("live map too large for the broker", session=self.session_id)
                self._end(str(exc))
                return
            self._sent = time.monotonic()
            self.stats.maps += 1
            # the next capture a period after this one, and no earlier than lets its map
            # (built in the usual time) go out as soon as it is built: a slow map shifts the
            # captures once, it does not leave every later map waiting, as old as it was
            next_capture = max(began + period, self._sent + period - statistics.median(builds))

    def _build(
        self, source: FrameSource, model: LiveRobotModel | None, began: float, taken: datetime
    ) -> bytes:
        """Capture the newest frames at `began` and make the encoded map."""
        color = model is not None and model.due(began)
        frames = source.frames(began - self.started, color)
        seen = model.robots(frames, self.map, began) if model is not None else []
        update = self.map.update(frames, began, seen)
        meta = {
            "time": taken.strftime("%Y-%m-%dT%H:%M:%S.%fZ"),  # of the frames
            "rate_hz": self.rate_hz,
            "robots": [r.to_json() for r in update.robots],
            "changed_cells": int(update.changed.sum()),
        }
        return encode_live_heightmap(
            update.heightmap,
            self.session_id,
            update.sequence,
            meta,
            {"changed": update.changed, "held": update.held},
        )
