"""Nothing is lost: the broker SIGKILLed mid-stream, the publishing process SIGKILLed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.support.mqtt import BASE, ROOT, SILO, summary, summary_json, validate_json
from tests.support.mqtt_broker import Broker


def _first_by_msg_id(payloads: list[bytes]) -> list[dict]:
    seen: set[str] = set()
    out = []
    for raw in payloads:
        doc = validate_json(raw)
        if doc["msg_id"] not in seen:
            seen.add(doc["msg_id"])
            out.append(doc)
    return out


def test_broker_killed_while_publishing(broker, telemetry_factory, collector_factory):
    col = collector_factory(broker, [f"{BASE}/scan", f"{BASE}/volume"])
    broker.wait_saved()  # the collector's persistent session survives the kill below
    tel = telemetry_factory(broker, max_inflight=5)
    n = 60
    done = threading.Event()

    def produce() -> None:
        for k in range(n):
            tel.publish_result(summary(f"{SILO}-{k:03d}"))
            time.sleep(0.01)
        done.set()

    threading.Thread(target=produce).start()
    col.wait_topic(f"{BASE}/scan", 5)
    broker.kill()
    end = time.monotonic() + 10
    while not tel.outbox.size()[0]:  # messages wait while the broker is gone
        assert time.monotonic() < end, "the outbox never held a message with the broker gone"
        time.sleep(0.01)
    broker.start()
    assert done.wait(10)
    col.wait_for(
        lambda ms: (
            len({json.loads(m.payload)["msg_id"] for m in ms if m.topic == f"{BASE}/scan"}) >= n
        ),
        timeout=30,
    )
    scans = _first_by_msg_id([m.payload for m in col.on(f"{BASE}/scan")])
    assert [s["scan_id"] for s in scans] == [f"{SILO}-{k:03d}" for k in range(n)]
    assert [s["seq"] for s in scans] == sorted(s["seq"] for s in scans)
    volumes = _first_by_msg_id([m.payload for m in col.on(f"{BASE}/volume")])
    col.wait_for(
        lambda ms: (
            json.loads([m for m in ms if m.topic == f"{BASE}/volume"][-1].payload)["scan_id"]
            == f"{SILO}-059"
        )
    )
    assert [v["seq"] for v in volumes] == sorted(v["seq"] for v in volumes)
    end = time.monotonic() + 5
    while tel.outbox.size()[0] and time.monotonic() < end:
        time.sleep(0.05)
    assert tel.outbox.size() == (0, 0)


def _config(tmp_path: Path, port: int) -> Path:
    cfg = tmp_path / "agent.toml"
    cfg.write_text(f"""
[silo]
id = "{SILO}"
region = [[-2, -2], [2, -2], [2, 2], [-2, 2]]

[[cameras]]
serial = "cam-a"
source = "sim"
view = "A1"

[mqtt]
host = "127.0.0.1"
port = {port}
outbox_path = "{tmp_path / "outbox.sqlite"}"
reconnect_min_s = 0.1
reconnect_max_s = 0.5
keepalive_s = 5
""")
    return cfg


def _cli(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "silo_agent", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        text=True,
    )


@pytest.mark.broker  # starts its own mosquitto
def test_publisher_sigkilled_with_pending_messages(tmp_path, collector_factory):
    broker = Broker(tmp_path / "broker")  # not started yet: the agent cannot deliver
    cfg = _config(tmp_path, broker.port)
    result = tmp_path / "result.json"
    result.write_text(json.dumps(summary_json()))
    proc = _cli(
        "publish",
        "--config",
        str(cfg),
        "--result",
        str(result),
        "--repeat",
        "4",
        "--timeout",
        "120",
    )
    queued = [json.loads(proc.stdout.readline()) for _ in range(8)]  # scan + volume, x4
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    proc.stderr.close()
    broker.start()
    flush = None
    try:
        col = collector_factory(broker, [f"{BASE}/#"])
        flush = _cli("flush", "--config", str(cfg), "--timeout", "30", "--linger", "60")
        assert flush.stdout.readline().strip() == "drained"
        sent_scans = [q for q in queued if q["topic"] == f"{BASE}/scan"]
        col.wait_topic(f"{BASE}/scan", len(sent_scans))
        got = [validate_json(m.payload) for m in col.on(f"{BASE}/scan")]
        assert [(g["msg_id"], g["seq"], g["ts"]) for g in got] == [
            (q["msg_id"], q["seq"], q["ts"]) for q in sent_scans
        ]
        # retained "latest" topic: only the newest pending volume was kept and sent
        volume = validate_json(col.wait_topic(f"{BASE}/volume")[0].payload)
        newest = [q for q in queued if q["topic"] == f"{BASE}/volume"][-1]
        assert (volume["msg_id"], volume["seq"]) == (newest["msg_id"], newest["seq"])
        assert volume["scan_id"] == f"{summary().scan_id}-3"
        assert len(col.on(f"{BASE}/volume")) == 1

        # killed while connected: no Last Will, `P/status` is the agent's, not flush's
        os.kill(flush.pid, signal.SIGKILL)
        flush.wait()
        flush.stdout.close()
        flush.stderr.close()
        time.sleep(1.0)  # a will would have come by now
        assert col.on(f"{BASE}/status") == []
    finally:
        if flush is not None and flush.poll() is None:
            flush.kill()
            flush.wait()
        broker.stop()
