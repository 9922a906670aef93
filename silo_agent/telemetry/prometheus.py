"""Prometheus metrics of the daemon (prometheus-client), served on `[metrics]` host:port.

A private registry, so that the endpoint shows the agent's own figures and tests can build
several agents in one process. Names follow Prometheus' conventions (base units spelled out,
counters end in `_total`); every labelled series an alert may rely on (each scan outcome,
each alarm type) exists from the start at 0, so `absent()` never hides a quiet agent."""

from __future__ import annotations

import threading
from collections.abc import Iterable
from wsgiref.simple_server import WSGIServer

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server

from silo_agent.analysis.alarm_types import ALARM_TYPES
from silo_agent.analysis.summary import ScanSummary
from silo_agent.config import MetricsConfig
from silo_agent.telemetry.sparkplug import iso_to_ms

STAGE_BUCKETS = (0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600)
SCAN_OUTCOMES = ("ok", "invalid", "failed")


class Metrics:
    """The agent's counters and gauges; `serve()` starts the HTTP endpoint when enabled."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.scans = Counter(
            "silo_agent_scans", "Scans by outcome (ok, invalid, failed)", ["outcome"], registry=r
        )
        self.stage_seconds = Histogram(
            "silo_agent_stage_duration_seconds",
            "Duration of each scan stage",
            ["stage"],
            buckets=STAGE_BUCKETS,
            registry=r,
        )
        self.volume = Gauge(
            "silo_agent_last_volume_cubic_meters", "Volume of the last valid scan", registry=r
        )
        self.mass = Gauge(
            "silo_agent_last_mass_kilograms",
            "Mass of the last valid scan (volume x silo.bulk_density_t_m3)",
            registry=r,
        )
        self.fill = Gauge(
            "silo_agent_last_fill_ratio",
            "Volume of the last valid scan over the bin's capacity (silo.bin)",
            registry=r,
        )
        self.headspace = Gauge(
            "silo_agent_last_headspace_meters",
            "Eave (or roof peak) down to the highest grain, last valid scan (silo.bin)",
            registry=r,
        )
        self.coverage = Gauge(
            "silo_agent_last_coverage_ratio",
            "Observed share of the region in the last scan",
            registry=r,
        )
        self.last_scan = Gauge(
            "silo_agent_last_scan_timestamp_seconds",
            "Capture time of the last scan, whatever its outcome",
            registry=r,
        )
        self.last_valid_scan = Gauge(
            "silo_agent_last_valid_scan_timestamp_seconds",
            "Capture time of the last valid scan (the volume's)",
            registry=r,
        )
        self.outbox_pending = Gauge(
            "silo_agent_outbox_pending_messages",
            "Messages waiting for a broker acknowledgement",
            registry=r,
        )
        self.outbox_dropped = Counter(
            "silo_agent_outbox_dropped_messages",
            "Messages dropped by the outbox bounds",
            registry=r,
        )
        self.camera_up = Gauge(
            "silo_agent_camera_up",
            "1 if the camera delivered its last cloud",
            ["serial"],
            registry=r,
        )
        self.alarm_active = Gauge(
            "silo_agent_alarm_active", "1 while the alarm is raised", ["type"], registry=r
        )
        for outcome in SCAN_OUTCOMES:
            self.scans.labels(outcome)
        self.set_alarms(())
        self._dropped_seen = 0
        self._server: WSGIServer | None = None
        self._thread: threading.Thread | None = None
        self._cfg: MetricsConfig | None = None

    def record_result(self, summary: ScanSummary, failed: bool = False) -> None:
        """The last-scan gauges after a scan's result (`failed`: no analysis, no coverage):
        the one path for a scan just finished and for the cached results restored at start."""
        captured = iso_to_ms(summary.captured_at) / 1000.0
        self.last_scan.set(captured)
        if not failed:
            self.coverage.set(summary.coverage)
        if summary.valid and summary.volume_m3 is not None:
            self.volume.set(summary.volume_m3)
            self.last_valid_scan.set(captured)
            if summary.mass_t is not None:
                self.mass.set(summary.mass_t * 1000.0)
            if summary.fill_ratio is not None:
                self.fill.set(summary.fill_ratio)
            if summary.headspace_m is not None:
                self.headspace.set(summary.headspace_m)

    def restore_results(self, newest: ScanSummary, newest_valid: ScanSummary | None) -> None:
        """At start, from the audit cache: the gauges as the last run left them (the newest
        valid result's volume, mass and time; the newest result's time and coverage), not 0,
        which reads as an empty silo and fires the staleness alert at every restart."""
        for summary in (newest_valid, newest):
            if summary is not None:
                self.record_result(summary)

    def set_alarms(self, active: Iterable[str]) -> None:
        """1 for the raised alarm types, 0 for every other one."""
        raised = set(active)
        for kind in raised | set(ALARM_TYPES):
            self.alarm_active.labels(kind).set(1 if kind in raised else 0)

    def set_outbox(self, pending: int, dropped_ever: int) -> None:
        """The outbox's figures; its dropped count is persisted, the counter follows it."""
        self.outbox_pending.set(pending)
        if dropped_ever > self._dropped_seen:
            self.outbox_dropped.inc(dropped_ever - self._dropped_seen)
            self._dropped_seen = dropped_ever

    def serve(self, cfg: MetricsConfig) -> None:
        if cfg.enabled:
            self._cfg = cfg
            self._server, self._thread = start_http_server(
                cfg.port, cfg.host, registry=self.registry
            )

    def alive(self) -> bool:
        """The endpoint's thread runs (or there is none)."""
        return self._thread is None or self._thread.is_alive()

    def restart(self) -> None:
        """A new endpoint after its thread died."""
        server, self._server, self._thread = self._server, None, None
        if server is not None:
            server.server_close()
        if self._cfg is not None:
            self.serve(self._cfg)

    def close(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server = None
