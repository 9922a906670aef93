"""Prometheus metrics of the daemon (prometheus-client), served on `[metrics]` host:port.

A private registry, so that the endpoint shows the agent's own figures and tests can build
several agents in one process."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server

from silo_agent.config import MetricsConfig

STAGE_BUCKETS = (0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600)


class Metrics:
    """The agent's counters and gauges; `serve()` starts the HTTP endpoint when enabled."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.scans = Counter("silo_agent_scans", "Scans by outcome (ok, invalid, failed)",
                             ["outcome"], registry=r)
        self.stage_seconds = Histogram("silo_agent_stage_duration_seconds",
                                       "Duration of each scan stage", ["stage"],
                                       buckets=STAGE_BUCKETS, registry=r)
        self.volume = Gauge("silo_agent_last_volume_m3", "Volume of the last valid scan",
                            registry=r)
        self.coverage = Gauge("silo_agent_last_coverage_ratio",
                              "Observed share of the region in the last scan", registry=r)
        self.outbox_pending = Gauge("silo_agent_outbox_pending",
                                    "Messages waiting for a broker acknowledgement", registry=r)
        self.outbox_dropped = Gauge("silo_agent_outbox_dropped",
                                    "Messages dropped by the outbox bounds, ever", registry=r)
        self.camera_up = Gauge("silo_agent_camera_up", "1 if the camera delivered its last cloud",
                               ["serial"], registry=r)
        self.alarm_active = Gauge("silo_agent_alarm_active", "1 while the alarm is raised",
                                  ["type"], registry=r)
        self._server = None

    def serve(self, cfg: MetricsConfig) -> None:
        if cfg.enabled:
            self._server, _thread = start_http_server(cfg.port, cfg.host, registry=self.registry)

    def close(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server = None
