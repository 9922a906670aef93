"""`silo-agent run`: the service. Scans on schedule and on request, one at a time.

Threads: the main thread owns the loop (signals, watchdog, the schedule, starting and
collecting scans, reloads); the MQTT network thread only hands triggers to it through
`_wake`; a scan runs in its own worker thread so the loop keeps petting the systemd watchdog.
A scan past its deadline is abandoned (reported as failed, its late result dropped); the
cameras stay busy until its thread returns, so no other scan starts before.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Protocol
from zoneinfo import ZoneInfo

import structlog

from silo_agent.analysis.summary import ScanSummary
from silo_agent.base.exits import FAILURE, OK
from silo_agent.base.limits import MAX_WAITING_REQUESTS
from silo_agent.config import Config, ConfigError, config_warnings, load_config, stale_after_s
from silo_agent.grid.heightmap import HeightMap
from silo_agent.service.live_control import LiveControl
from silo_agent.service.pipeline import STATE_FILE, Outcome, Pipeline, ScanAbandoned
from silo_agent.service.scan_path import new_scan_id, no_result_summary
from silo_agent.service.schedule import Schedule
from silo_agent.service.sdnotify import Notifier
from silo_agent.service.state_lock import StateLock
from silo_agent.storage.audit import AuditCache
from silo_agent.telemetry.client import CommandRejected, ScanCommand, Telemetry
from silo_agent.telemetry.payloads import check_summary
from silo_agent.telemetry.prometheus import Metrics

log = structlog.get_logger(__name__)

LOOP_S = 1.0  # longest sleep of the main loop without a watchdog
THREAD_RESTARTS = 3  # restarts of one internal thread within RESTART_WINDOW_S, then exit 1
RESTART_WINDOW_S = 600.0


class Companion(Protocol):
    """Something served beside the agent for its whole run, e.g. the operator's page
    (silo_agent/web): started once MQTT runs, before the first scan; supervised like the
    agent's own threads (`alive`, `restart`); stopped at shutdown."""

    name: str

    def start(self, agent: Agent) -> None: ...

    def alive(self) -> bool: ...

    def restart(self) -> None: ...

    def stop(self) -> None: ...


RESTORE_FAILED = "no scan result restored: Sparkplug and the metrics start with nulls"


@dataclass
class _Running:
    scan_id: str
    thread: threading.Thread
    deadline: float
    abandoned: threading.Event
    requests: list[ScanCommand]
    reason: str
    started: datetime
    outcome: Outcome | None = None
    error: str | None = None
    reported: bool = False


@dataclass
class _Pending:
    scheduled: bool = False
    requests: list[ScanCommand] = field(default_factory=list)

    def __bool__(self) -> bool:
        return self.scheduled or bool(self.requests)


class Agent:
    """The daemon. `run()` returns the exit status."""

    def __init__(
        self,
        config_path: Path,
        config: Config,
        max_scans: int | None = None,
        notifier: Notifier | None = None,
        companions: Sequence[Companion] = (),
        metrics: Metrics | None = None,
    ) -> None:
        """`companions`: served beside the agent (ready to start: ports bound, files read);
        `metrics`: its port bound by `run` (`Metrics.bind`), or bound when the agent starts."""
        self.config_path = config_path
        self.config = config
        self.max_scans = max_scans
        self.notifier = notifier or Notifier.from_env()
        self.state_lock = StateLock.of(config)
        self.state_lock.acquire()  # StateLocked: another agent runs on this state
        self.metrics = metrics if metrics is not None else Metrics()
        self.telemetry = Telemetry.from_config(config)
        self.cache = AuditCache(config.audit, config.silo.id)
        self.pipeline = Pipeline(config, self.telemetry, self.cache, self.metrics)
        self.telemetry.restore_alarms(self.pipeline.state.active)
        self._restored_id = self._restore_result()  # the newest cached scan's id
        self.metrics.set_alarms(self.telemetry.raised_alarms())
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._pending = _Pending()
        self._running: _Running | None = None
        self._done = 0
        self.failed_scans = 0  # scans that gave no result (`run --scans N` exits 1 on any)
        self._last: Outcome | None = None
        self._scheduler: Schedule | None = None
        self._deaths: dict[str, list[float]] = {}  # internal thread -> when it died
        self._status = OK
        self.live = LiveControl(config, self.telemetry, self._wake, self._last_map)
        self.companions = list(companions)

    def _restore_result(self) -> str | None:
        """The last results in the audit cache into what reports them between scans: the
        Sparkplug node (a host applies the NDATA the outbox replays after a restart as
        history, not as the current value) and the Prometheus gauges. Without this both
        would show nulls or zeros (an empty silo, a stale scan) until the next scan. Returns
        the newest cached scan's id (None: none readable)."""
        try:
            newest = ScanSummary.from_json(self.cache.latest_result())
            self.telemetry.restore_result(newest)  # validated as for publishing
        except ValueError as exc:
            log.warning(RESTORE_FAILED, reason=str(exc), cache=str(self.cache.directory))
            return None
        newest_valid: ScanSummary | None = newest
        if not newest.valid:
            try:
                newest_valid = ScanSummary.from_json(self.cache.latest_result(valid=True))
                check_summary(newest_valid)
            except ValueError as exc:
                log.info("no valid scan result restored", reason=str(exc))
                newest_valid = None
        self.metrics.restore_results(newest, newest_valid)
        return newest.scan_id

    @property
    def scans_done(self) -> int:
        """Scans finished (a result or a failure) since the agent started."""
        return self._done

    @property
    def last_outcome(self) -> Outcome | None:
        """The last scan's outcome (for `run --scans N` to print)."""
        return self._last

    def _last_map(self) -> HeightMap | None:
        """The last full scan's height map, for a live session to start from and to be
        checked at; before this run's first scan, the newest cached one's: a restart does not
        change what a session starts from or whether it is accepted."""
        last = self._last.scan_id if self._last is not None else self._restored_id
        return self.cache.heightmap(last) if last is not None else None

    # ------------------------------------------------------------ triggers

    def _scheduled(self) -> None:
        """A scheduled job fell due: ask the loop for a scan. One that falls during a scan
        runs right after it (the 06:00 report scan is not lost to an hourly one still
        running); several waiting coalesce into one."""
        with self._lock:
            if self._pending.scheduled:
                log.info("scheduled scan coalesced with the one already waiting")
                return
            self._pending.scheduled = True
        self._wake.set()

    def _requested(self, command: ScanCommand) -> None:
        """MQTT network thread: accept, or answer busy with the running scan's id. Requests
        that arrive before the scan starts (e.g. while a live session gives the cameras
        back) share that one scan; past MAX_WAITING_REQUESTS they are answered busy."""
        with self._lock:
            running = self._running
            if running is not None:
                raise CommandRejected(
                    f"busy: scan {running.scan_id} is running", scan_id=running.scan_id
                )
            if self._stop.is_set():
                raise CommandRejected("the agent is stopping")
            if len(self._pending.requests) >= MAX_WAITING_REQUESTS:
                raise CommandRejected(
                    f"busy: {MAX_WAITING_REQUESTS} requests already wait for the next scan"
                )
            self._pending.requests.append(command)
        self._wake.set()

    def _signal(self, signum: int, _frame: FrameType | None) -> None:
        if signum == signal.SIGHUP:
            self._reload.set()
        else:
            self._stop.set()
        self._wake.set()

    # ------------------------------------------------------------ scheduling

    def _start_scheduler(self) -> None:
        zone = ZoneInfo(self.config.silo.timezone)
        wall, mono = datetime.now(UTC), time.monotonic()
        self._scheduler = Schedule(self.config.schedule, zone, wall, mono)
        for job, at in self._scheduler.next_runs(wall, mono).items():
            log.info("scan scheduled", job=job, next_run=str(at.astimezone(zone)))

    def _stop_scheduler(self) -> None:
        self._scheduler = None

    def _tick_schedule(self) -> float | None:
        """Main loop, every turn: the scheduled jobs due now ask for a scan; how long until
        the next one is due."""
        if self._scheduler is None:
            return None
        wall, mono = datetime.now(UTC), time.monotonic()
        for _job in self._scheduler.due(wall, mono):
            self._scheduled()
        return self._scheduler.seconds_to_next(wall, mono)

    # ------------------------------------------------------------ scans

    def _start_scan(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, _Pending()
            started = datetime.now(UTC)
            taken = self.cache.names()
            if self._last is not None:
                taken.add(self._last.scan_id)
            scan_id = new_scan_id(self.config, started, taken)
            deadline = time.monotonic() + self.config.schedule.scan_timeout_s
            running = _Running(
                scan_id,
                threading.Thread(),
                deadline,
                threading.Event(),
                pending.requests,
                "request" if pending.requests else "schedule",
                started,
            )

            def work() -> None:
                try:
                    running.outcome = self.pipeline.run(
                        scan_id, started, deadline, running.abandoned
                    )
                except ScanAbandoned as exc:
                    running.error = str(exc)
                except Exception as exc:  # a bug in one scan must not end the service
                    log.exception("scan crashed", scan_id=scan_id)
                    running.error = f"internal error: {exc}"
                finally:
                    self._wake.set()

            running.thread = threading.Thread(target=work, name=f"scan-{scan_id}", daemon=True)
            self._running = running
        self.notifier.status(f"scanning {scan_id}")
        running.thread.start()

    def _collect(self) -> None:
        """Finish a scan whose thread returned, or give up on one past its deadline."""
        running = self._running
        if running is None:
            return
        if running.thread.is_alive():
            if time.monotonic() > running.deadline and not running.reported:
                running.abandoned.set()
                self._report(
                    running,
                    f"deadline of {self.config.schedule.scan_timeout_s} s exceeded; scan abandoned",
                )
            return
        with self._lock:
            self._running = None
        if not running.reported:
            if running.outcome is not None:
                self._finish(running, running.outcome)
            else:
                self._report(running, running.error or "scan ended without a result")

    def _report(self, running: _Running, error: str) -> None:
        """A scan that ended without a result of its own (deadline, crash)."""
        running.reported = True
        log.error("scan failed", scan_id=running.scan_id, reason=error)
        summary = no_result_summary(
            self.config, running.scan_id, f"{running.started:%Y-%m-%dT%H:%M:%SZ}", error, [], {}
        )
        try:
            self.telemetry.publish_scan_failure(summary)
        except Exception:
            log.exception("cannot queue the failure report", scan_id=running.scan_id)
        self.metrics.scans.labels("failed").inc()
        self._finish(running, Outcome(running.scan_id, "failed", error, summary))

    def _finish(self, running: _Running, outcome: Outcome) -> None:
        running.reported = True
        self._last = outcome
        self._done += 1
        self.failed_scans += outcome.outcome == "failed"
        for command in running.requests:
            self.telemetry.finish_scan_request(
                command,
                scan_id=outcome.scan_id,
                error=outcome.error if outcome.outcome == "failed" else None,
            )
        volume = outcome.summary.volume_m3 if outcome.summary is not None else None
        status = f"last scan {outcome.scan_id}: {outcome.outcome}"
        if volume is not None:
            status += f", {volume:.3f} m³"
        self.notifier.status(status)
        if self.max_scans is not None and self._done >= self.max_scans:
            log.info("scan count reached, stopping", scans=self._done)
            self._stop.set()

    # ------------------------------------------------------------ reload

    def _do_reload(self) -> None:
        """SIGHUP: take a new config if it is valid; a bad one is logged and ignored. What
        needs a restart ([mqtt], silo.id, [metrics], [web]) keeps its running value, and each
        reload whose file differs there from what runs says so: a scan named and cached under
        a new silo.id while the topics keep the old one would mix two silos."""
        try:
            new = load_config(self.config_path, service=True)
        except ConfigError as exc:
            log.error(
                "config reload rejected, keeping the running config",
                path=str(self.config_path),
                error=str(exc),
            )
            return
        running = self.config
        kept = [
            name
            for name, changed in (
                ("[mqtt]", new.mqtt != running.mqtt),
                ("silo.id", new.silo.id != running.silo.id),
                ("[metrics]", new.metrics != running.metrics),
                ("[web]", new.web != running.web),
            )
            if changed
        ]
        if kept:
            log.warning(
                "config reloaded; these changes need a restart, the running values are kept",
                kept=kept,
                path=str(self.config_path),
            )
            new = new.model_copy(
                update={
                    "mqtt": running.mqtt,
                    "silo": new.silo.model_copy(update={"id": running.silo.id}),
                    "metrics": running.metrics,
                    "web": running.web,
                }
            )
        for warning in config_warnings(new):
            log.warning("config", path=str(self.config_path), warning=warning)
        with self._lock:
            self.config = new
            self.live.config = new
            self.pipeline.config = new
            self.cache.cfg = new.audit
            self.cache.directory = Path(new.audit.directory)
            self.pipeline.state_path = self.cache.directory / STATE_FILE
        self.pipeline.clear_switched_off_alarms()
        self.telemetry.set_expire_after(stale_after_s(new.schedule, new.silo.timezone))
        self._stop_scheduler()
        self._start_scheduler()
        log.info("config reloaded", path=str(self.config_path))

    # ------------------------------------------------------------ main loop

    def run(self) -> int:
        """Serve until stopped; the exit status. Signals are handled when run in the main
        thread (the service); elsewhere (embedded, tests) `stop()` ends it."""
        if threading.current_thread() is not threading.main_thread():
            return self._serve()
        handlers = {
            s: signal.signal(s, self._signal)
            for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
        }
        try:
            return self._serve()
        finally:
            for s, previous in handlers.items():
                signal.signal(s, previous)

    def stop(self) -> None:
        """Stop as SIGTERM does."""
        self._stop.set()
        self._wake.set()

    def _serve(self) -> int:
        config = self.config
        for warning in config_warnings(config):
            log.warning("config", path=str(self.config_path), warning=warning)
        self.cache.directory.mkdir(parents=True, exist_ok=True)
        self.cache.enforce(self.pipeline.protected())  # bounds may have changed while stopped
        self.metrics.serve(config.metrics)  # on the port `run` bound, if it did
        self.telemetry.on_scan_request(self._requested)
        self.pipeline.clear_switched_off_alarms()  # e.g. low_volume_m3 removed while stopped
        self.telemetry.on_live_command(self.live.requested)
        self.telemetry.start()
        for companion in self.companions:
            companion.start(self)
        self._start_scheduler()
        if config.schedule.scan_at_start:
            with self._lock:
                self._pending.scheduled = True
        log.info(
            "agent started",
            silo=config.silo.id,
            config=str(self.config_path),
            cache=str(self.cache.directory),
            max_scans=self.max_scans,
        )
        self.notifier.ready(f"started; silo {config.silo.id}")
        # a third of WATCHDOG_USEC, not systemd's minimum of a half: a ping that a busy machine or
        # a GIL-holding C call in the scan thread delays still lands well before the deadline
        watchdog_every = (self.notifier.watchdog_s / 3) if self.notifier.watchdog_s else None
        next_ping = 0.0
        while True:
            now = time.monotonic()
            if watchdog_every is not None and now >= next_ping:
                self.notifier.watchdog()
                next_ping = now + watchdog_every
            self._collect()
            self._outbox_metrics()
            self._supervise()
            if self._stop.is_set():
                break
            if self._reload.is_set() and self._running is None:  # never mid-scan
                self._reload.clear()
                self._do_reload()
            with self._lock:
                ready = bool(self._pending) and self._running is None
            self.live.tend(scan_due=ready or self._running is not None)  # a full scan wins
            if ready:
                self._start_scan()
            timeout = LOOP_S  # sleep no later than the next watchdog ping or job is due
            if watchdog_every is not None:
                timeout = min(timeout, max(0.0, next_ping - time.monotonic()))
            due_in = self._tick_schedule()
            if due_in is not None:
                timeout = min(timeout, due_in)
            self._wake.wait(timeout)
            self._wake.clear()
        return self._shutdown()

    def _supervise(self) -> None:
        """An internal thread that died (an error nobody caught) is restarted. One that died
        more than THREAD_RESTARTS times in RESTART_WINDOW_S stops the agent with status 1:
        the process must not look alive while it cannot publish; systemd restarts it."""
        threads = (
            ("mqtt", self.telemetry.alive, self.telemetry.restart),
            ("metrics", self.metrics.alive, self.metrics.restart),
            *((c.name, c.alive, c.restart) for c in self.companions),
        )
        for name, alive, restart in threads:
            if alive():
                continue
            now = time.monotonic()
            deaths = [t for t in self._deaths.get(name, []) if now - t < RESTART_WINDOW_S]
            deaths.append(now)
            self._deaths[name] = deaths
            if len(deaths) > THREAD_RESTARTS:
                log.critical(
                    "internal thread keeps dying: the agent stops, to be restarted",
                    thread=name,
                    deaths=len(deaths),
                    window_s=RESTART_WINDOW_S,
                )
                self._status = FAILURE
                self._stop.set()
                return
            log.error("internal thread died: restarting it", thread=name)
            restart()

    def _outbox_metrics(self) -> None:
        pending, _ = self.telemetry.outbox.size()
        self.metrics.set_outbox(pending, self.telemetry.outbox.counter("dropped"))

    def _shutdown(self) -> int:
        self.notifier.stopping()
        log.info("agent stopping")
        self._stop_scheduler()
        self.live.close()
        running = self._running
        if running is not None and running.thread.is_alive():
            log.info(
                "waiting for the running scan",
                scan_id=running.scan_id,
                timeout_s=self.config.schedule.stop_timeout_s,
            )
            running.thread.join(self.config.schedule.stop_timeout_s)
            if running.thread.is_alive():
                running.abandoned.set()
                if not running.reported:
                    self._report(running, "agent stopped during the scan; scan abandoned")
        self._collect()
        for command in self._pending.requests:
            self.telemetry.finish_scan_request(command, error="the agent stopped")
        self.telemetry.stop()  # flushes what it can within mqtt.shutdown_timeout_s, `stopped`
        self.metrics.close()
        for companion in self.companions:
            companion.stop()
        self.notifier.close()
        self.state_lock.release()
        log.info("agent stopped", scans=self._done, status=self._status)
        return self._status
