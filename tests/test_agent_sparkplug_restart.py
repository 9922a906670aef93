"""What a Sparkplug host sees of the daemon across a restart: the first NBIRTH carries the last
scan's result, as the retained `P/volume` does, until the next scan (decoded by pysparkplug)."""

from __future__ import annotations

import json
import signal
from datetime import datetime
from pathlib import Path

import pysparkplug as ps
import pytest

from silo_agent.service.daemon import RESTORE_FAILED
from tests.support.agent import BASE, SILO, Daemon, write_config
from tests.support.mqtt import validate_json

NODE = f"spBv1.0/silos/{{}}/{SILO}"

RESULT_METRICS = {  # metric -> where the retained P/volume has the same value
    "Inventory/Volume m3": ("volume_m3",),
    "Inventory/Mass t": ("mass_t",),
    "Inventory/Level Min m": ("level", "min"),
    "Inventory/Level Mean m": ("level", "mean"),
    "Inventory/Level Max m": ("level", "max"),
    "Inventory/Coverage": ("coverage",),
    "Inventory/Valid": ("valid",),
    "Inventory/Degraded": ("degraded",),
    "Scan/Last Id": ("scan_id",),
}


def first_birth_of_a_start(config: Path, tmp_path: Path, spb) -> tuple[ps.NBirth, Daemon]:
    """Start the agent (no scan) and decode its first NBIRTH."""
    seen = len(spb.on(NODE.format("NBIRTH")))
    agent = Daemon(config, tmp_path)
    births = spb.wait_topic(NODE.format("NBIRTH"), seen + 1)
    return ps.NBirth.decode(births[seen].payload), agent


def stop(agent: Daemon) -> None:
    agent.signal(signal.SIGTERM)
    assert agent.wait(20) == 0


@pytest.mark.slow
def test_first_birth_after_a_restart_carries_the_last_scan(tmp_path, broker, collector_factory):
    options = {"sparkplug.enabled": True}
    config = write_config(tmp_path / "agent.toml", broker.port, tmp_path, mqtt=options)
    spb = collector_factory(broker, ["spBv1.0/#"], client_id="host")
    assert Daemon(config, tmp_path, "--scans", "1").wait(120) == 0
    retained = collector_factory(broker, [f"{BASE}/volume"], client_id="dashboard")
    volume = validate_json(retained.wait_topic(f"{BASE}/volume")[0].payload)
    captured = datetime.fromisoformat(volume["captured_at"])
    captured_ms = int(captured.timestamp() * 1000)

    write_config(config, broker.port, tmp_path, schedule={"scan_at_start": False}, mqtt=options)
    birth, agent = first_birth_of_a_start(config, tmp_path, spb)
    try:
        metrics = {m.name: m for m in birth.metrics}
        for name, path in RESULT_METRICS.items():
            expected = volume
            for key in path:
                expected = expected[key]
            assert metrics[name].value == expected, name
            assert metrics[name].timestamp == captured_ms, name
        assert metrics["Scan/Time"].value == captured
        assert metrics["Scan/Time"].timestamp == captured_ms
        assert not any(m.is_historical for m in birth.metrics)
        stop(agent)

        # a damaged result.json (a part of the wrong type, cut short): the agent starts all
        # the same, with nulls and a warning that says what is wrong
        (result,) = (tmp_path / "scans").glob(f"{SILO}-*/result.json")
        text = result.read_text()
        wrong_type = {**json.loads(text), "level": [1, 2]}
        for damaged, says in (
            (json.dumps(wrong_type), "result summary"),
            (text[:-20], str(result)),
        ):
            result.write_text(damaged)
            birth, agent = first_birth_of_a_start(config, tmp_path, spb)
            metrics = {m.name: m for m in birth.metrics}
            assert all(metrics[name].is_null for name in [*RESULT_METRICS, "Scan/Time"])
            (warning,) = [e for e in agent.log() if e["event"] == RESTORE_FAILED]
            assert warning["level"] == "warning" and says in warning["reason"]
            stop(agent)
    finally:
        agent.kill()
