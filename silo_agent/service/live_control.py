"""The agent's side of live mode: `P/cmd/live` requests in, one session at a time, the full
scan first.

The MQTT thread only records what was asked (`requested`); the agent's main loop calls `tend`
every turn, which starts, stops, suspends (a full scan is due or running: it needs the cameras)
and resumes the session, so no network callback ever waits for a capture.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

import structlog

from silo_agent.config import Config
from silo_agent.grid.heightmap import HeightMap
from silo_agent.live.coverage import session_problem
from silo_agent.live.session import LiveSession
from silo_agent.telemetry.client import CommandRejected, Telemetry
from silo_agent.telemetry.live_command import LiveCommand, session_limits

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class _Start:
    """An accepted `{"on": true}`: the session it starts."""

    command: LiveCommand
    session_id: str
    rate: float
    duration: float


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
        # requests accepted but not yet applied by `tend`, in order: a start, or None for a
        # stop. What a new request is checked against is the state once they are applied, so
        # an `off` right after an accepted `on` stops that session, and an `on` right after an
        # accepted `off` starts a new one
        self._queue: list[_Start | None] = []
        self._count = 0

    def _expected(self) -> str | None:
        """Id of the session that runs once the queued requests are applied (lock held)."""
        if self._queue:
            last = self._queue[-1]
            return last.session_id if last is not None else None
        if self.session is not None and self.session.active:
            return self.session.session_id
        return None

    def requested(self, command: LiveCommand) -> str:
        """MQTT thread: check the request and leave it for `tend`; the session id."""
        request = command.request
        with self._lock:
            active = self._expected()
            if not request.on:
                if active is None:
                    raise CommandRejected("no live session is running")
                self._queue.append(None)
                session_id = active
            else:
                if active is not None:
                    raise CommandRejected(
                        f'busy: live session {active} is running; send {{"on": false}} first',
                        scan_id=active,
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
                self._queue.append(_Start(command, session_id, rate, duration))
        self._wake.set()
        return session_id

    def tend(self, scan_due: bool) -> None:
        """Main loop, every turn: apply requests, give the cameras to a due scan, resume."""
        with self._lock:
            queued = list(self._queue)
        for item in queued:  # still queued while applied: `requested` sees where they lead
            if item is None:
                if self.session is not None:
                    self.session.stop("stopped by request")
            else:
                self._begin(item)
        with self._lock:
            del self._queue[: len(queued)]
        session = self.session
        if session is None:
            return
        if not session.active:
            self.session = None
            return
        if scan_due and session.running:
            log.info("live session suspended for a full scan", session=session.session_id)
            session.suspend()
        elif not scan_due and not session.running:
            session.resume()

    def _begin(self, start: _Start) -> None:
        command, session_id, rate, duration = (
            start.command,
            start.session_id,
            start.rate,
            start.duration,
        )

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
