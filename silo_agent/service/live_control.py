"""The agent's side of live mode: `P/cmd/live` requests in, one session at a time, the full
scan first.

The MQTT thread only records what was asked (`requested`); the agent's main loop calls `tend`
every turn, which starts, stops, suspends (a full scan is due or running: it needs the cameras)
and resumes the session, so no network callback ever waits for a capture.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from datetime import UTC, datetime

import structlog

from silo_agent.config import Config
from silo_agent.grid.heightmap import HeightMap
from silo_agent.live.coverage import session_problem
from silo_agent.live.session import LiveSession
from silo_agent.telemetry.client import CommandRejected, Telemetry
from silo_agent.telemetry.live_command import LiveCommand, session_limits

log = structlog.get_logger(__name__)


class LiveControl:
    def __init__(
        self,
        config: Config,
        telemetry: Telemetry,
        wake: threading.Event,
        last_map: Callable[[], HeightMap | None] = lambda: None,
    ) -> None:
        """`last_map` gives the last full scan's height map: cells a session has not seen yet
        start from it."""
        self.config = config
        self.telemetry = telemetry
        self.session: LiveSession | None = None
        self._last_map = last_map
        self._wake = wake
        self._lock = threading.Lock()
        self._start: tuple[LiveCommand, str, float, float] | None = None
        self._stop_asked = False
        self._command: LiveCommand | None = None
        self._count = 0

    def _active_session_id(self) -> str:
        """Id of the session asked for or running; the caller holds the lock and knows one is."""
        if self._start is not None:
            return self._start[1]
        assert self.session is not None
        return self.session.session_id

    def requested(self, command: LiveCommand) -> str:
        """MQTT thread: check the request and leave it for `tend`; the session id."""
        request = command.request
        with self._lock:
            active = self._start is not None or (self.session is not None and self.session.active)
            if not request.on:
                if not active:
                    raise CommandRejected("no live session is running")
                self._stop_asked = True
                session_id = self._active_session_id()
            else:
                if active:
                    running = self._active_session_id()
                    raise CommandRejected(
                        f'busy: live session {running} is running; send {{"on": false}} first',
                        scan_id=running,
                    )
                try:
                    rate, duration = session_limits(self.config.live, request)
                except ValueError as exc:
                    raise CommandRejected(str(exc)) from None
                serials = self.config.live.cameras or [c.serial for c in self.config.cameras]
                problem = session_problem(self.config, serials, self._last_map())
                if problem is not None and self.config.live.coverage_check:
                    raise CommandRejected(problem)
                if problem is not None:
                    log.warning("live session started against the check", problem=problem)
                self._count += 1
                session_id = f"{self.config.silo.id}-live-{datetime.now(UTC):%Y%m%dT%H%M%SZ}"
                session_id += f"-{self._count}"
                self._start = (command, session_id, rate, duration)
        self._wake.set()
        return session_id

    def tend(self, scan_due: bool) -> None:
        """Main loop, every turn: apply requests, give the cameras to a due scan, resume."""
        with self._lock:
            start, self._start = self._start, None
            stop, self._stop_asked = self._stop_asked, False
        if start is not None:
            self._begin(*start)
        session = self.session
        if session is None:
            return
        if stop:
            session.stop("stopped by request")
        if not session.active:
            self.session = None
            return
        if scan_due and session.running:
            log.info("live session suspended for a full scan", session=session.session_id)
            session.suspend()
        elif not scan_due and not session.running:
            session.resume()

    def _begin(self, command: LiveCommand, session_id: str, rate: float, duration: float) -> None:
        def ended(reason: str) -> None:
            error = None if reason in ("duration reached", "stopped by request") else reason
            self.telemetry.finish_live(command, session_id, error)
            self._wake.set()

        def publish(payload: bytes, period: float) -> None:
            self.telemetry.publish_live(payload, period, qos=self.config.live.qos)

        self.session = LiveSession(
            self.config, session_id, rate, duration, publish, ended, start_map=self._last_map()
        )
        log.info("live session started", session=session_id, rate_hz=rate, duration_s=duration)

    def close(self) -> None:
        """Agent shutdown: end the session, its final reply says so."""
        if self.session is not None and self.session.active:
            self.session.stop("the agent stopped")
        self.session = None
