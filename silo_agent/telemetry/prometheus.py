"""Prometheus metrics of the daemon (prometheus-client), served on `[metrics]` host:port.

A private registry, so that the endpoint shows the agent's own figures and tests can build
several agents in one process. Names follow Prometheus' conventions (base units spelled out,
counters end in `_total`); every labelled series an alert may rely on (each scan outcome,
each alarm type) exists from the start at 0, so `absent()` never hides a quiet agent. A bin's
figures (fill, headspace) are exported only while the last valid result has them: a silo
without `[silo.bin]` has no sample of them, not a 0 that reads as an empty silo."""

from __future__ import annotations

import errno
import socket
import threading
from collections.abc import Iterable
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, make_wsgi_app
from prometheus_client.exposition import ThreadingWSGIServer

from silo_agent.analysis.alarm_types import ALARM_TYPES
from silo_agent.analysis.summary import ScanSummary
from silo_agent.config import ConfigError, MetricsConfig
from silo_agent.telemetry.sparkplug import iso_to_ms

STAGE_BUCKETS = (0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600)
SCAN_OUTCOMES = ("ok", "invalid", "failed")


class Metrics:
    """The agent's counters and gauges; `bind()` binds the HTTP endpoint's port (`run`, before
    anything starts), `serve()` serves it when enabled (binding it then if not bound yet)."""

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
        self.fill = Gauge(  # registered by _bin_figure, with a value
            "silo_agent_last_fill_ratio",
            "Volume of the last valid scan over the bin's capacity (silo.bin)",
            registry=None,
        )
        self.headspace = Gauge(
            "silo_agent_last_headspace_meters",
            "Eave (or roof peak) down to the highest grain, last valid scan (silo.bin)",
            registry=None,
        )
        self._bin_shown: set[Gauge] = set()
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
            self._bin_figure(self.fill, summary.fill_ratio)
            self._bin_figure(self.headspace, summary.headspace_m)

    def _bin_figure(self, gauge: Gauge, value: float | None) -> None:
        """A bin's figure in the registry while the last valid result has it, out of it when
        that result has none (no `[silo.bin]`, or one a reload removed)."""
        if value is None:
            if gauge in self._bin_shown:
                self.registry.unregister(gauge)
                self._bin_shown.discard(gauge)
            return
        gauge.set(value)
        if gauge not in self._bin_shown:
            self.registry.register(gauge)
            self._bin_shown.add(gauge)

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

    def bind(self, cfg: MetricsConfig) -> None:
        """The endpoint's port bound now, served later by `serve`: one in use is a ConfigError
        naming the key (`run` exits 78 before anything starts), not a traceback at start."""
        try:
            self._server = _listen(cfg, self.registry)
        except OSError as exc:
            raise ConfigError(
                f"metrics: cannot listen on {cfg.host}:{cfg.port}: {exc.strerror or exc}"
                + ("; choose another metrics.port" if exc.errno == errno.EADDRINUSE else "")
            ) from None

    def serve(self, cfg: MetricsConfig) -> None:
        if cfg.enabled:
            self._cfg = cfg
            if self._server is None:
                self._server = _listen(cfg, self.registry)
            self._thread = threading.Thread(
                target=self._server.serve_forever, name="metrics", daemon=True
            )
            self._thread.start()

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
            if self._thread is not None:
                self._server.shutdown()
            self._server.server_close()
            self._server = None


class _QuietHandler(WSGIRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:
        """No line on stderr per scrape (the log is JSON lines)."""


def _listen(cfg: MetricsConfig, registry: CollectorRegistry) -> WSGIServer:
    """prometheus-client's `start_http_server` without its thread: the port bound now."""
    family, _, _, _, address = socket.getaddrinfo(
        cfg.host, cfg.port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
    )[0]

    class Server(ThreadingWSGIServer):
        address_family = family

    return make_server(
        str(address[0]), cfg.port, make_wsgi_app(registry), Server, handler_class=_QuietHandler
    )
