"""One scan of the daemon: capture -> audit -> reconstruct + detect -> alarms -> publish.

The pipeline publishes through a `telemetry.publisher.Publisher`: the daemon's MQTT
`Telemetry`, or in tests a `MemoryPublisher`.

Each stage is timed; a stage that fails is reported (log, `P/scan` with the reason, status,
metrics) and the scan ends there, the agent carries on. Stage boundaries check the scan's
deadline and whether the agent gave up on it (shutdown, deadline), so an abandoned scan never
publishes.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Any

import structlog

from silo_agent.analysis.alarm_types import AlarmEvent
from silo_agent.analysis.alarms import AlarmState, Inputs, clear_switched_off, evaluate
from silo_agent.analysis.summary import ScanSummary
from silo_agent.base.atomic import write_atomic
from silo_agent.capture import CaptureResult
from silo_agent.config import Config
from silo_agent.reconstruct import Reconstruction
from silo_agent.scan import gravity_angles
from silo_agent.service.scan_once import Stages, scan_once
from silo_agent.storage.audit import AuditCache, dump_json, is_disk_full
from silo_agent.telemetry.prometheus import Metrics
from silo_agent.telemetry.publisher import Publisher

log = structlog.get_logger(__name__)

STATE_FILE = "alarm-state.json"  # in audit.directory, next to the scans it refers to


class ScanAbandoned(Exception):
    """The deadline passed or the agent is stopping: the scan must not publish."""


@dataclass
class Outcome:
    scan_id: str
    outcome: str  # ok | invalid | failed
    error: str | None = None
    summary: ScanSummary | None = None
    directory: Path | None = None
    events: list[AlarmEvent] = field(default_factory=list)


class Pipeline:
    """Runs scans for the agent; holds what carries from scan to scan (alarm state, piles)."""

    def __init__(
        self, config: Config, publisher: Publisher, cache: AuditCache, metrics: Metrics
    ) -> None:
        self.config = config
        self.publisher = publisher
        self.cache = cache
        self.metrics = metrics
        self.state_path = cache.directory / STATE_FILE
        self.state = self._load_state()
        self._baseline_map: tuple[str, Any] | None = None
        self.count = 0  # scans started since the agent started (drives sim sequences)

    def _load_state(self) -> AlarmState:
        try:
            return AlarmState.from_json(json.loads(self.state_path.read_text(encoding="utf-8")))
        except FileNotFoundError:
            return AlarmState()
        except (OSError, ValueError, TypeError, AttributeError) as exc:
            log.warning(
                "alarm state unreadable, starting afresh", path=str(self.state_path), error=str(exc)
            )
            return AlarmState()

    def _save_state(self) -> None:
        """The alarm state into the audit directory; on a full disk evict older scans (never
        the baseline) and retry once, as a scan's write does: a disk that stayed full had kept
        the state from ever being saved, and after a restart the baseline it names was gone."""
        for attempt in range(2):
            try:
                self.cache.directory.mkdir(parents=True, exist_ok=True)
                write_atomic(self.state_path, dump_json(self.state.to_json()))
                return
            except OSError as exc:
                error = exc
            if attempt or not is_disk_full(error):
                break
            removed = self.cache.evict_for_space(self.protected())
            log.warning("disk full, evicted scans", removed=removed, to="save the alarm state")
        log.error("cannot save the alarm state", path=str(self.state_path), error=str(error))

    def protected(self) -> set[str]:
        """Scans retention must keep: the collapse baseline."""
        ids = {self.state.baseline_scan_id, self.config.alarms.baseline_scan_id}
        return {i for i in ids if i}

    def _baseline(self) -> Any:
        scan_id = self.config.alarms.baseline_scan_id or self.state.baseline_scan_id
        if scan_id is None:
            return None
        if self._baseline_map is None or self._baseline_map[0] != scan_id:
            self._baseline_map = (scan_id, self.cache.heightmap(scan_id))
        return self._baseline_map[1]

    # ------------------------------------------------------------ one scan

    def run(
        self, scan_id: str, started: datetime, deadline: float, abandoned: threading.Event
    ) -> Outcome:
        """One scan; never raises except ScanAbandoned."""
        config = self.config
        scan_number = self.count
        self.count += 1

        def check() -> None:
            if abandoned.is_set():
                raise ScanAbandoned("the agent gave up on this scan")
            if time.monotonic() > deadline:
                raise ScanAbandoned(f"deadline of {config.schedule.scan_timeout_s} s exceeded")

        stages = Stages(
            timed=lambda stage, seconds: self.metrics.stage_seconds.labels(stage).observe(seconds),
            captured=lambda capture: self._captured(scan_id, capture),
            check=check,
        )
        log.info("scan started", scan_id=scan_id)
        run = scan_once(config, self.cache, scan_id, started, stages, self.protected, scan_number)
        failed = tuple((f.serial, f.error) for f in run.capture.failures)
        analysed = run.analysed
        if analysed is None or run.scan is None:
            if run.error is not None:
                log.error("processing failed", scan_id=scan_id, exc_info=run.error)
            return self._failed(run.summary, failed, run.cache_full)

        summary, result = run.summary, analysed.reconstruction
        inputs = Inputs(
            scan_id=scan_id,
            heightmap=result.heightmap,
            volume_m3=result.volume_m3,
            coverage=result.coverage,
            valid=result.valid,
            floor_z=config.silo.floor_z,
            ceiling_z=config.silo.ceiling_z,
            max_z=summary.surface.max_z if summary.surface is not None else None,
            failed_cameras=failed,
            cache_full=run.cache_full,
            baseline=self._baseline(),
            information=result.information,
            baseline_scan_id=self.config.alarms.baseline_scan_id or self.state.baseline_scan_id,
            registration_residual_m={k: r.median_m for k, r in result.registration.items()},
            gravity_deg=gravity_angles(run.scan.cameras),
            gravity_tolerance_deg={c.serial: c.gravity_tolerance_deg for c in config.cameras},
        )
        events, state = evaluate(self.state, inputs, config.alarms, calibration=config.calibration)
        stages.lap("alarms")
        check()

        summary = replace(summary, timings={k: round(v, 4) for k, v in stages.timings.items()})
        self.state = state
        self._save_state()
        self._publish(summary, result, events)
        stages.lap("publish")
        self.cache.enforce(self.protected())
        outcome = "ok" if result.valid else "invalid"
        self._count(outcome, summary)
        log.info(
            "scan finished",
            scan_id=scan_id,
            outcome=outcome,
            volume_m3=result.volume_m3,
            coverage=round(result.coverage, 4),
            alarms=[f"{e.type}:{e.state}" for e in events],
        )
        return Outcome(scan_id, outcome, result.invalid_reason, summary, run.directory, events)

    def _captured(self, scan_id: str, capture: CaptureResult) -> None:
        """The cameras' states into the metrics and `P/status`; a failed one is logged."""
        cameras: dict[str, tuple[str, str | None]] = {
            c.serial: ("ok", None) for c in capture.clouds
        }
        cameras.update({f.serial: ("failed", f.error) for f in capture.failures})
        for serial, (camera_state, _error) in cameras.items():
            self.metrics.camera_up.labels(serial).set(1 if camera_state == "ok" else 0)
        self.publisher.set_status(cameras=cameras)
        for failure in capture.failures:
            log.warning(
                "camera failed", scan_id=scan_id, serial=failure.serial, error=failure.error
            )

    def _failed(
        self, summary: ScanSummary, failed: tuple[tuple[str, str], ...], cache_full: bool
    ) -> Outcome:
        """Report a scan without a result: `P/scan` with its reason, the alarms."""
        scan_id, reason = summary.scan_id, summary.invalid_reason
        inputs = Inputs(
            scan_id=scan_id,
            heightmap=None,
            volume_m3=None,
            coverage=0.0,
            valid=False,
            failed_cameras=failed,
            cache_full=cache_full,
            reconstructed=False,
        )
        events, self.state = evaluate(self.state, inputs, self.config.alarms)
        self._save_state()
        try:
            self.publisher.publish_scan_failure(summary)
            for event in events:
                self.publisher.publish_alarm(event)
        except Exception:
            log.exception("cannot queue the failure report", scan_id=scan_id)
        self._count("failed", summary)
        log.error("scan failed", scan_id=scan_id, reason=reason)
        return Outcome(scan_id, "failed", reason, summary, None, events)

    def _publish(
        self, summary: ScanSummary, result: Reconstruction, events: list[AlarmEvent]
    ) -> None:
        self.publisher.publish_result(summary, result.heightmap)
        for event in events:
            self.publisher.publish_alarm(event)
            details = {k: v for k, v in event.to_json().items() if k != "message"}
            log.warning("alarm", **details, text=event.message)

    def _count(self, outcome: str, summary: ScanSummary) -> None:
        self.metrics.scans.labels(outcome).inc()
        self.metrics.record_result(summary, failed=outcome == "failed")
        self.metrics.set_alarms(self.publisher.raised_alarms())

    def clear_switched_off_alarms(self) -> None:
        """At start and after a reload: clear, with the usual `cleared` event, every raised
        alarm whose detector the config now switches off; it would never judge again."""
        events, self.state = clear_switched_off(self.state, self.config.alarms, None)
        if not events:
            return
        self._save_state()
        for event in events:
            self.publisher.publish_alarm(event)
            log.info(
                "alarm cleared, its detector is switched off",
                type=event.type,
                reason=event.message,
            )
        self.metrics.set_alarms(self.publisher.raised_alarms())
