"""`[metrics]` and `[audit]`: the Prometheus endpoint and the audit cache."""

from __future__ import annotations

from pathlib import Path

from pydantic import (
    Field,
)

from silo_agent.config.base import HostName, Strict


class MetricsConfig(Strict):
    """Prometheus exposition (prometheus-client); off by default."""

    enabled: bool = False
    host: HostName = Field(default="127.0.0.1", description="listen address")
    port: int = Field(default=9464, ge=1, le=65535)


class AuditConfig(Strict):
    directory: Path = Path("/var/lib/silo-agent/scans")
    max_bytes: int = Field(default=20_000_000_000, gt=0)
    max_age_days: float = Field(default=90, gt=0)
