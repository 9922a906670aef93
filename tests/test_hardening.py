"""An operator's bad day (issue #26): a broker with a small packet limit, a second instance on
the same state, hostile live requests, odd prefixes and scan files. Each case runs the real
thing (a `silo-agent` subprocess, a private mosquitto) and fails on the agent before #26."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.agent import BASE, Daemon, write_config
from tests.support.mqtt import validate_json
from tests.support.mqtt_broker import Broker, Collector

# two 424x240 cameras fail the session-start check (live/coverage.py): not what is tested here
LIVE_SECTION = "\n[live]\ngrid_step_m = 0.1\nrate_hz = 4.0\ncoverage_check = false\n"
REPLIES = "test/hardening-replies"


def small_cameras(path: Path, extra: str = LIVE_SECTION) -> Path:
    text = path.read_text().replace("width = 424", "width = 212")
    path.write_text(text.replace("height = 240", "height = 120") + extra)
    return path


def command(col: Collector, name: str, body: bytes, correlation: bytes) -> None:
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.properties import Properties

    props = Properties(PacketTypes.PUBLISH)
    props.ResponseTopic = REPLIES
    props.CorrelationData = correlation
    col.publish(f"{BASE}/cmd/{name}", body, props)


def replies_to(col: Collector, correlation: bytes, count: int, timeout: float = 60) -> list[dict]:
    def mine(ms: list) -> list[dict]:
        return [
            validate_json(m.payload)
            for m in ms
            if m.topic == REPLIES and m.properties.CorrelationData == correlation
        ]

    col.wait_for(lambda ms: len(mine(ms)) >= count, timeout)
    return mine(col.messages)


@pytest.mark.broker
def test_live_maps_over_the_brokers_packet_limit_end_the_session_with_why(tmp_path):
    broker = Broker(tmp_path / "broker", extra=("max_packet_size 2000",)).start()
    config = write_config(
        tmp_path / "agent.toml", broker.port, tmp_path, schedule={"scan_at_start": False}
    )
    small_cameras(config)
    col = Collector(broker, [f"{BASE}/#", REPLIES], client_id="packet-limit")
    agent = Daemon(config, tmp_path)
    try:
        col.wait_topic(f"{BASE}/status")
        command(col, "live", b'{"on": true, "duration_s": 30}', b"big")
        accepted, ended = replies_to(col, b"big", 2)
        assert accepted["status"] == "accepted"
        assert ended["status"] == "error" and ended["scan_id"] == accepted["scan_id"]
        assert "Maximum Packet Size (2,000 bytes)" in ended["error"]
        assert not col.on(f"{BASE}/heightmap/live")
        states = [json.loads(m.payload)["state"] for m in col.on(f"{BASE}/status")]
        assert "offline" not in states  # never disconnected over a map
        assert agent.proc.poll() is None
    finally:
        agent.kill()
        col.close()
        broker.stop()


def test_a_second_agent_on_the_same_state_refuses_to_start(tmp_path):
    """No broker needed: the second instance stops before connecting to anything."""
    config = write_config(tmp_path / "agent.toml", 1, tmp_path, schedule={"scan_at_start": False})
    first = Daemon(config, tmp_path)
    try:
        first.wait_log("agent started")
        others = {
            "same config": config,
            "same outbox": write_config(
                tmp_path / "b.toml",
                1,
                tmp_path,
                schedule={"scan_at_start": False},
                audit={"directory": str(tmp_path / "other-scans")},
            ),
            "same audit directory": write_config(
                tmp_path / "c.toml",
                1,
                tmp_path,
                schedule={"scan_at_start": False},
                mqtt={"outbox_path": str(tmp_path / "other" / "outbox.sqlite")},
            ),
        }
        for case, path in others.items():
            second = subprocess.run(
                [sys.executable, "-m", "silo_agent", "run", "--config", str(path)],
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert second.returncode == 1, case
            (line,) = second.stderr.strip().splitlines()
            assert line.startswith("silo-agent: another silo-agent") and "is running" in line
            assert f"pid {first.proc.pid}" in line, case
        assert first.proc.poll() is None
        assert not (tmp_path / "other" / "outbox.sqlite").exists()  # refused before opening
    finally:
        first.kill()
