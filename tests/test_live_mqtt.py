"""Live mode in the daemon, end to end: `silo-agent run` on sim cameras watching the moving
robot, the test's own mosquitto. Start/stop over `P/cmd/live`, the rate and duration limits,
`P/heightmap/live` not retained and QoS 0 outside the outbox, and a full scan pre-empting a
live session that resumes after it."""

from __future__ import annotations

import itertools
import json
import signal
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from silo_agent.config import load_config
from silo_agent.grid.grid import Grid
from silo_agent.telemetry.heightmap_codec import (
    HeightMapFormatError,
    decode_heightmap,
    decode_live_heightmap,
)
from tests.support.agent import BASE, Daemon, write_config
from tests.support.mqtt import validate_json

REPLIES = "test/live-replies"
LIVE = f"{BASE}/heightmap/live"
counter = itertools.count()


@dataclass
class Got:
    topic: str
    payload: bytes
    qos: int
    retain: bool
    at: float


class Listener:
    """A subscriber at QoS 1 that keeps what QoS and retain flag each message arrived with
    (a QoS 0 publish reaches a QoS 1 subscriber at QoS 0) and when."""

    def __init__(self, port: int, topics: list[str]) -> None:
        self.messages: list[Got] = []
        self._lock = threading.Lock()
        ready = threading.Event()
        self.client = mqtt.Client(
            CallbackAPIVersion.VERSION2, client_id=f"live-{next(counter)}", protocol=mqtt.MQTTv5
        )
        self.client.on_connect = lambda c, *a: c.subscribe([(t, 1) for t in topics])
        self.client.on_subscribe = lambda *a: ready.set()
        self.client.on_message = self._message
        self.client.connect("127.0.0.1", port, 10)
        self.client.loop_start()
        assert ready.wait(10)

    def _message(self, _client, _userdata, msg) -> None:
        with self._lock:
            self.messages.append(
                Got(msg.topic, bytes(msg.payload), msg.qos, bool(msg.retain), time.monotonic())
            )

    def on(self, topic: str) -> list[Got]:
        with self._lock:
            return [m for m in self.messages if m.topic == topic]

    def wait(self, check, timeout: float = 60.0) -> None:
        end = time.monotonic() + timeout
        while not check():
            assert time.monotonic() < end, f"timed out; got {[m.topic for m in self.messages]}"
            time.sleep(0.05)

    def statuses(self) -> list[str]:
        return [json.loads(m.payload)["state"] for m in self.on(f"{BASE}/status")]

    def online(self) -> None:
        """Until the agent says `online`: it subscribed to its commands before."""
        self.wait(lambda: "online" in self.statuses())

    def command(self, body: bytes) -> bytes:
        correlation = f"live-{next(counter)}".encode()
        props = Properties(PacketTypes.PUBLISH)
        props.ResponseTopic = REPLIES
        props.CorrelationData = correlation
        self.client.publish(f"{BASE}/cmd/live", body, qos=1, properties=props)
        return correlation

    def replies(self, count: int = 1, timeout: float = 30.0) -> list[dict]:
        self.wait(lambda: len(self.on(REPLIES)) >= count, timeout)
        return [validate_json(m.payload) for m in self.on(REPLIES)]

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def live_config(path: Path, port: int, workdir: Path, live: dict, schedule: dict) -> Path:
    """Four wall cameras at 212x120 (the renderer must keep up on a loaded test machine). So
    coarse a camera cannot keep a 0.3 m robot out of the map: the session-start check
    (live/coverage.py) accepts it for a robot twice as tall, which is all these tests need."""
    write_config(
        path,
        port,
        workdir,
        schedule=schedule,
        simulation={"capture_s": 1.0},
        cameras=tuple((f"sim-{v}", v) for v in ("A2", "A4", "A6", "A8")),
    )
    text = (
        path.read_text()
        .replace("width = 424", "width = 212")
        .replace("height = 240", "height = 120")
    )
    live = {"robot_min_height_m": 0.6, **live}
    text += "\n[live]\n" + "\n".join(f"{k} = {v}" for k, v in live.items()) + "\n"
    path.write_text(text)
    return path


@pytest.fixture
def listener(broker):
    got = Listener(broker.port, [f"{BASE}/#", REPLIES])
    yield got
    got.close()


@pytest.mark.slow
def test_live_session_rate_duration_stop_and_limits(tmp_path: Path, broker, listener):
    config = live_config(
        tmp_path / "agent.toml",
        broker.port,
        tmp_path,
        live={"rate_hz": 2.0, "max_duration_s": 60, "grid_step_m": 0.05},
        schedule={"scan_at_start": False},
    )
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("agent started")
        listener.online()
        # limits of [live] answer with an error naming them, nothing starts
        listener.command(b'{"on": true, "rate_hz": 5}')
        (too_fast,) = listener.replies(1)
        assert too_fast["status"] == "error" and "live.rate_hz" in too_fast["error"]
        listener.command(b'{"on": true, "duration_s": 61}')
        assert "live.max_duration_s" in listener.replies(2)[1]["error"]
        listener.command(b'{"on": true, "speed": 1, "request_id": "bad-1"}')
        unknown = listener.replies(3)[2]  # refused as it was parsed: still names the request
        assert "speed" in unknown["error"] and unknown["request_id"] == "bad-1"
        listener.command(b'{"on": false}')
        assert "no live session" in listener.replies(4)[3]["error"]

        # a 16 s session at 0.5 Hz (the simulated cameras could go faster, so the limit is
        # what spaces the maps): accepted with its id, maps 2 s apart at least, then done
        listener.command(b'{"on": true, "rate_hz": 0.5, "duration_s": 16, "request_id": "r1"}')
        accepted = listener.replies(5)[4]
        assert accepted["status"] == "accepted" and accepted["request_id"] == "r1"
        session = accepted["scan_id"]
        started = time.monotonic()
        done = listener.replies(6, timeout=60)[5]
        assert done["status"] == "done" and done["scan_id"] == session
        assert time.monotonic() - started == pytest.approx(16, abs=2.0)
        maps = listener.on(LIVE)
        assert 2 <= len(maps) <= 9  # the first after the simulated world is loaded
        assert all(m.qos == 0 and not m.retain for m in maps)
        decoded = [decode_live_heightmap(m.payload) for m in maps]
        assert [d.sequence for d in decoded] == list(range(1, len(maps) + 1))
        assert all(d.session_id == session for d in decoded)
        assert all(set(d.layers) == {"changed", "held"} for d in decoded)
        assert decoded[0].heightmap.step == pytest.approx(0.05)
        times = [
            datetime.fromisoformat(d.meta["time"].replace("Z", "+00:00")).timestamp()
            for d in decoded
        ]
        assert min(b - a for a, b in itertools.pairwise(times)) >= 2.0 - 0.02  # captures
        arrivals = [m.at for m in maps]
        assert min(b - a for a, b in itertools.pairwise(arrivals)) >= 2.0 - 0.1  # and sends
        # the retained full-scan topic is untouched by live maps
        assert not listener.on(f"{BASE}/heightmap")

        # {"on": false} ends a running session early
        listener.command(b'{"on": true, "duration_s": 60}')
        second = listener.replies(7)[6]["scan_id"]
        listener.wait(lambda: len(listener.on(LIVE)) >= len(maps) + 2, timeout=40)
        # the first session had stopped: every map after its last is the second session's
        later = [decode_live_heightmap(m.payload) for m in listener.on(LIVE)[len(maps) :]]
        assert {d.session_id for d in later} == {second}
        listener.command(b'{"on": false}')
        replies = listener.replies(9)
        assert {r["status"] for r in replies[7:9]} == {"accepted", "done"}
        assert all(r["scan_id"] == second for r in replies[7:9])
        count = len(listener.on(LIVE))
        agent.signal(signal.SIGTERM)  # `stopped` comes after every map the agent sent
        assert agent.wait(20) == 0
        listener.wait(lambda: "stopped" in listener.statuses())
        assert len(listener.on(LIVE)) <= count + 1  # at most the map being made
    finally:
        agent.kill()


@pytest.mark.slow
def test_a_full_scan_pre_empts_live_and_live_resumes(tmp_path: Path, broker, listener):
    config = live_config(
        tmp_path / "agent.toml",
        broker.port,
        tmp_path,
        live={"rate_hz": 2.0, "grid_step_m": 0.05},
        schedule={"scan_at_start": False, "interval_s": 12},
    )
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("agent started")
        listener.online()
        listener.command(b'{"on": true, "rate_hz": 2, "duration_s": 60}')
        (accepted,) = listener.replies(1)
        assert accepted["status"] == "accepted"
        agent.wait_log("scan started", timeout=40)
        listener.wait(lambda: listener.on(f"{BASE}/scan"), timeout=60)
        scan_done = listener.on(f"{BASE}/scan")[0].at
        suspended = agent.wait_log("live session suspended for a full scan")
        assert suspended
        listener.wait(lambda: any(m.at > scan_done + 0.1 for m in listener.on(LIVE)), 30)
        maps = listener.on(LIVE)
        before = [m for m in maps if m.at < scan_done]
        after = [m for m in maps if m.at > scan_done]
        assert before and after
        # the scan (4 cameras x capture_s = 1 s) had the cameras: a gap of its length
        gap = after[0].at - before[-1].at
        assert gap >= 4.0
        sequences = [decode_live_heightmap(m.payload).sequence for m in maps]
        # the same session carries on; a map made as the scan took over is dropped, a gap
        assert sequences[0] == 1 and all(b > a for a, b in itertools.pairwise(sequences))
        assert sequences[-1] - len(maps) <= 1
        # the retained P/heightmap is the full scan's map (a late subscriber gets it), not live
        late = Listener(broker.port, [f"{BASE}/heightmap"])
        try:
            late.wait(lambda: late.on(f"{BASE}/heightmap"), timeout=10)
            (full,) = late.on(f"{BASE}/heightmap")
            assert full.retain and decode_heightmap(full.payload).step == 0.05
            with pytest.raises(HeightMapFormatError, match="not a live height map"):
                decode_live_heightmap(full.payload)
        finally:
            late.close()
    finally:
        agent.kill()


@pytest.mark.slow
def test_live_session_in_a_bin_without_a_region(tmp_path: Path, broker, listener):
    """A `[silo.bin]` config gives no `[silo] region`: its wall is the region. The live path
    read `region` itself (None), and every `{"on": true}` was refused with numpy's `cannot
    reshape array of size 1 into shape (2)`; a 6 m bin inside the moving-robot bay runs."""
    config = live_config(
        tmp_path / "agent.toml",
        broker.port,
        tmp_path,
        live={"rate_hz": 1.0, "grid_step_m": 0.05},
        schedule={"scan_at_start": False},
    )
    text = config.read_text()
    square = "region = [[-3.0, -3.0], [3.0, -3.0], [3.0, 3.0], [-3.0, 3.0]]\n"
    assert square in text
    bin_table = "[silo.bin]\ndiameter_m = 6.0\ncentre = [0.0, 0.0]\neave_height_m = 2.8\n\n"
    text = text.replace(square, "").replace("[reconstruction]", bin_table + "[reconstruction]", 1)
    config.write_text(text)
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("agent started")
        listener.online()
        listener.command(b'{"on": true, "duration_s": 6, "request_id": "bin-1"}')
        (accepted,) = listener.replies(1)
        assert accepted["status"] == "accepted", accepted.get("error")
        done = listener.replies(2, timeout=60)[1]
        assert done["status"] == "done" and done["scan_id"] == accepted["scan_id"], done.get(
            "error"
        )
        maps = [decode_live_heightmap(m.payload) for m in listener.on(LIVE)]
        assert maps
        heights = maps[-1].heightmap.heights
        wall = Grid.over(load_config(config).silo.region_polygon(), 0.05)
        assert heights.shape == wall.shape and wall.shape[0] >= 120  # the bin's 6 m wall
        assert np.isnan(heights[0, 0]) and np.isnan(heights[-1, -1])  # outside the wall
        rows, cols = heights.shape
        assert np.isfinite(heights[rows // 2, cols // 2])  # the bin's centre is mapped
    finally:
        agent.kill()
