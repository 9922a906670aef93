"""Fixtures and helpers of the MQTT tests: a private mosquitto per test (mqtt_broker.py, never
1883), Telemetry instances on it, realistic results and height maps, schema checks.

The fixtures are registered by tests/conftest.py; test modules import the helpers."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from silo_agent.analysis.summary import ScanSummary
from silo_agent.config import MqttConfig
from silo_agent.grid.heightmap import HeightMap
from silo_agent.telemetry.client import Telemetry
from tests.support.mqtt_broker import Broker, Collector

ROOT = Path(__file__).resolve().parents[2]
SCHEMAS = ROOT / "config" / "schemas"
SILO = "silo-t"
BASE = f"silo/{SILO}"


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    b = Broker(tmp_path / "broker").start()
    yield b
    b.stop()


@pytest.fixture
def collector_factory() -> Iterator[Callable[..., Collector]]:
    made: list[Collector] = []

    def make(broker: Broker, topics: list[str], **kwargs) -> Collector:
        c = Collector(broker, topics, **kwargs)
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()


def mqtt_config(broker: Broker, tmp_path: Path, **overrides) -> MqttConfig:
    """Fast reconnects so that outage tests stay short."""
    values = {
        "host": "127.0.0.1",
        "port": broker.port,
        "outbox_path": tmp_path / "outbox.sqlite",
        "reconnect_min_s": 0.1,
        "reconnect_max_s": 0.5,
        "keepalive_s": 5,
        "shutdown_timeout_s": 3.0,
    }
    values.update(overrides)
    return MqttConfig.model_validate(values)


@pytest.fixture
def telemetry_factory(tmp_path: Path) -> Iterator[Callable[..., Telemetry]]:
    made: list[Telemetry] = []

    def make(
        broker: Broker,
        *,
        cameras=("cam-a", "cam-b"),
        start=True,
        expire_after_s: int | None = None,
        **overrides,
    ) -> Telemetry:
        t = Telemetry(
            mqtt_config(broker, tmp_path, **overrides),
            SILO,
            list(cameras),
            version="9.9.9",
            expire_after_s=expire_after_s,
        )
        if start:
            t.start()
        made.append(t)
        return t

    yield make
    for t in made:
        if t._thread is not None and t._thread.is_alive():
            t.stop()


def summary_json(scan_id: str = f"{SILO}-20261122T020000Z", **changes) -> dict:
    """A result summary's JSON, the keys every output reads (no engine details)."""
    out = {
        "scan_id": scan_id,
        "captured_at": "2026-11-22T02:00:00.000Z",
        "volume_m3": 12.345,
        "mass_t": 9.506,
        "coverage": 0.87,
        "grid_step_m": 0.02,
        "surface": {"min_z": 0.1, "mean_z": 0.9, "max_z": 1.4},
        "level": {"min": 0.1, "mean": 0.9, "max": 1.4},
        "valid": True,
        "invalid_reason": None,
        "degraded": False,
        "cameras": {"used": ["cam-a"], "failed": [{"serial": "cam-b", "error": "timeout"}]},
        "piles": [
            {
                "id": 1,
                "detector": "geometric",
                "centroid": {"x": 0.5, "y": -0.2},
                "peak": {"x": 0.5, "y": -0.2},
                "peak_height_m": 1.1,
                "footprint_m2": 0.6,
                "volume_m3": 0.2,
                "confidence": None,
            }
        ],
        "timings": {"capture_s": 4.2, "reconstruct_s": 1.3},
    }
    out.update(changes)
    return out


def summary(scan_id: str = f"{SILO}-20261122T020000Z", **changes) -> ScanSummary:
    """A result summary as the pipeline publishes it (`summary_json`'s keys)."""
    return ScanSummary.from_json(summary_json(scan_id, **changes))


def realistic_heightmap(
    rows: int = 300, cols: int = 400, step: float = 0.02, seed: int = 0
) -> HeightMap:
    """A cone with ripples and D455-like noise on an elliptic region, 70 % observed."""
    rng = np.random.default_rng(seed)
    ox, oy = -cols * step / 2, -rows * step / 2
    xs = ox + (np.arange(cols) + 0.5) * step
    ys = oy + (np.arange(rows) + 0.5) * step
    x, y = np.meshgrid(xs, ys)
    heights = 3.0 - 0.45 * np.hypot(x, y) + 0.1 * np.sin(3 * x) * np.cos(2 * y)
    heights += rng.normal(0, 0.008, x.shape)
    inside = ((x / (-ox * 0.98)) ** 2 + (y / (-oy * 0.98)) ** 2 <= 1).astype(float)
    heights[inside == 0] = np.nan
    observed = (rng.random(x.shape) < 0.7) & (inside > 0)
    return HeightMap((ox, oy), step, heights, observed, inside)


def _schema_by_name() -> dict[str, dict]:
    out = {}
    for path in SCHEMAS.glob("*.json"):
        schema = json.loads(path.read_text())
        const = schema.get("properties", {}).get("schema", {}).get("const")
        if const:
            out[const] = schema
    return out


SCHEMA_BY_NAME = _schema_by_name()


def validate_json(payload: bytes) -> dict:
    """Parse a published JSON payload and validate it against its committed schema."""
    doc = json.loads(payload)
    schema = SCHEMA_BY_NAME[doc["schema"]]
    jsonschema.validate(doc, schema, format_checker=jsonschema.FormatChecker())
    return doc
