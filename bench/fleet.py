"""Fleet load on one broker: 100-500 agents' telemetry, messages and bytes per silo per day, and
the broker's CPU.

Each agent is the real `Telemetry` (its durable outbox, its network thread, JSON topics,
Sparkplug B and Home Assistant discovery on) publishing simulated results: the summary of a
scan and a 2 cm height map of an 8 x 6 m bin (300 x 400 cells, a cone with ripples and 8 mm
noise, 70 % observed: about what a real scan's map compresses to), not full scans. Agents are
spread over worker processes; one subscriber on `#` stands for the plant's historian (the
broker fans every message out to it, as it would in service). mosquitto without persistence,
on a free loopback port, `max_queued_messages` raised so that the historian drops nothing.

Phases: all agents connect (births, discovery, retained states: counted apart, once per
connection), the broker idles with them connected (keepalives), then every agent publishes
`--rounds` scans as fast as the outboxes send them. Per silo and scan: messages and payload
bytes the historian received, by topic. Per day: that x `--scans-per-day`, plus the keepalive
pings. Broker CPU: its user+system seconds (/proc) per round of N scans, and so its share of
one core at the daily rate; the idle phase gives the connected-but-quiet cost.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import subprocess
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from threading import Barrier as BarrierType
from threading import Event as EventType

import numpy as np
import paho.mqtt.client as mqtt
from benchlib import header
from mosquitto import HOST, MOSQUITTO, Broker
from paho.mqtt.enums import CallbackAPIVersion

from silo_agent.analysis.summary import ScanSummary
from silo_agent.config import MqttConfig
from silo_agent.grid.heightmap import HeightMap
from silo_agent.telemetry.client import Telemetry

KEEPALIVE_S = 30
PING_BYTES = 2  # PINGREQ and PINGRESP: a 2-byte fixed header each


def heightmap(seed: int) -> HeightMap:
    """An 8 x 6 m bin's map at 2 cm: cone, ripples, 8 mm noise, 70 % observed."""
    rows, cols, step = 300, 400, 0.02
    rng = np.random.default_rng(seed)
    ox, oy = -cols * step / 2, -rows * step / 2
    x, y = np.meshgrid(ox + (np.arange(cols) + 0.5) * step, oy + (np.arange(rows) + 0.5) * step)
    heights = 3.0 - 0.45 * np.hypot(x, y) + 0.1 * np.sin(3 * x) * np.cos(2 * y)
    heights += rng.normal(0, 0.008, x.shape)
    inside = ((x / (-ox * 0.98)) ** 2 + (y / (-oy * 0.98)) ** 2 <= 1).astype(float)
    heights[inside == 0] = np.nan
    observed = (rng.random(x.shape) < 0.7) & (inside > 0)
    return HeightMap((ox, oy), step, heights, observed, inside)


def summary(silo: str, index: int) -> ScanSummary:
    """A scan result as the pipeline publishes it."""
    stamp = f"2026-11-22T{index % 24:02d}:00:00.000Z"
    return ScanSummary.from_json(
        {
            "scan_id": f"{silo}-20261122T{index % 24:02d}0000Z-{index}",
            "captured_at": stamp,
            "volume_m3": 12.345 + index * 0.01,
            "mass_t": 9.506,
            "coverage": 0.87,
            "grid_step_m": 0.02,
            "surface": {"min_z": 0.1, "mean_z": 0.9, "max_z": 1.4},
            "level": {"min": 0.1, "mean": 0.9, "max": 1.4},
            "valid": True,
            "invalid_reason": None,
            "degraded": False,
            "cameras": {"used": ["cam-a", "cam-b", "cam-c", "cam-d"], "failed": []},
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
    )


def worker(
    silos: list[str],
    port: int,
    rounds: int,
    workdir: str,
    ready: BarrierType,
    go: EventType,
    done: BarrierType,
    stop: EventType,
) -> None:
    """Run `silos` agents in this process: connect, wait for `go`, publish `rounds` scans each,
    wait for their outboxes to drain, then for `stop`."""
    cfg = {
        "host": HOST,
        "port": port,
        "keepalive_s": KEEPALIVE_S,
        "sparkplug": {"enabled": True},
        "homeassistant": {"enabled": True},
        "shutdown_timeout_s": 5.0,
    }
    agents = [
        Telemetry(
            MqttConfig.model_validate({**cfg, "outbox_path": Path(workdir) / f"{silo}.sqlite"}),
            silo,
            ["cam-a", "cam-b", "cam-c", "cam-d"],
        )
        for silo in silos
    ]
    for agent in agents:
        agent.start()
    maps = [heightmap(seed) for seed in range(rounds)]
    ready.wait()
    go.wait()
    for index in range(rounds):
        for agent in agents:
            agent.publish_result(summary(agent.silo_id, index), maps[index])
    while any(agent.outbox.size()[0] for agent in agents):
        stop.wait(0.2)
    done.wait()
    stop.wait()
    for agent in agents:
        agent.stop()


class Historian:
    """A subscriber on `#` counting messages and payload bytes by topic kind."""

    def __init__(self, port: int) -> None:
        self.messages: Counter[str] = Counter()
        self.bytes: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        ready = threading.Event()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="historian")
        self.client.max_queued_messages_set(0)
        self.client.on_connect = lambda c, *a: c.subscribe("#", qos=1)
        self.client.on_subscribe = lambda *a: ready.set()
        self.client.on_message = self._message
        self.client.connect(HOST, port, 60)
        self.client.loop_start()
        if not ready.wait(10):
            raise RuntimeError("the historian could not subscribe")

    @staticmethod
    def kind(topic: str) -> str:
        parts = topic.split("/")
        if parts[0] == "spBv1.0":
            return f"spBv1.0 {parts[2]}"
        if parts[0] == "homeassistant":
            return "homeassistant discovery"
        return "P/" + "/".join(parts[2:3] + (["<type>"] if len(parts) > 3 else []))

    def _message(self, _client, _userdata, msg) -> None:
        kind = self.kind(msg.topic)
        with self._cond:
            self.messages[kind] += 1
            self.bytes[kind] += len(msg.payload) + len(msg.topic)
            self._cond.notify_all()

    def snapshot(self) -> tuple[Counter[str], Counter[str]]:
        with self._lock:
            return Counter(self.messages), Counter(self.bytes)

    def wait_count(self, kind: str, count: int, timeout: float) -> bool:
        end = time.monotonic() + timeout
        with self._cond:
            while self.messages[kind] < count:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def mosquitto_version() -> str:
    out = subprocess.run([MOSQUITTO, "-h"], capture_output=True, text=True, check=False).stdout
    return out.splitlines()[0] if out else "mosquitto"


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(agents: int, workers: int, rounds: int, idle_s: float, workdir: Path) -> dict:
    broker = Broker(
        workdir / "broker",
        extra=("max_queued_messages 1000000", "max_inflight_messages 100", "sys_interval 0"),
    ).start()
    assert broker.proc is not None
    historian = Historian(broker.port)
    silos = [f"silo-{k:04d}" for k in range(agents)]
    ctx = mp.get_context("spawn")
    ready, done = ctx.Barrier(workers + 1), ctx.Barrier(workers + 1)
    go, stop = ctx.Event(), ctx.Event()
    procs = [
        ctx.Process(
            target=worker,
            args=(silos[w::workers], broker.port, rounds, str(workdir), ready, go, done, stop),
        )
        for w in range(workers)
    ]
    try:
        for proc in procs:
            proc.start()
        ready.wait(600)
        if not historian.wait_count("spBv1.0 NBIRTH", agents, 600):
            raise RuntimeError("not every agent was born")
        threading.Event().wait(3.0)  # the last connections' retained states settle
        connect_msgs, connect_bytes = historian.snapshot()
        cpu0 = cpu_seconds(broker.proc.pid)
        threading.Event().wait(idle_s)  # connected, quiet: keepalives only
        idle_cpu = cpu_seconds(broker.proc.pid) - cpu0
        before_msgs, before_bytes = historian.snapshot()
        cpu1, started = cpu_seconds(broker.proc.pid), time.monotonic()
        go.set()
        done.wait(3600)
        if not historian.wait_count("P/scan", agents * rounds, 600):
            raise RuntimeError("the historian did not get every scan")
        threading.Event().wait(1.0)
        wall = time.monotonic() - started
        busy_cpu = cpu_seconds(broker.proc.pid) - cpu1
        after_msgs, after_bytes = historian.snapshot()
    finally:
        stop.set()
        for proc in procs:
            proc.join(120)
        historian.close()
        broker.stop()
    return {
        "agents": agents,
        "rounds": rounds,
        "connect_msgs": connect_msgs,
        "connect_bytes": connect_bytes,
        "scan_msgs": after_msgs - before_msgs,
        "scan_bytes": after_bytes - before_bytes,
        "idle_cpu": idle_cpu,
        "idle_s": idle_s,
        "busy_cpu": busy_cpu,
        "wall": wall,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[100, 500])
    parser.add_argument("--workers", type=int, default=4, help="processes hosting the agents")
    parser.add_argument("--rounds", type=int, default=3, help="scans per agent")
    parser.add_argument("--scans-per-day", type=int, default=25, help="e.g. hourly + 06:00")
    parser.add_argument("--idle-s", type=float, default=20.0)
    parser.add_argument("--note", default="", help="a provenance line, e.g. machine load")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    per_day = args.scans_per_day
    lines = header("Fleet load on one broker", args.note)
    lines += [
        "",
        f"Real `Telemetry` per agent (JSON, Sparkplug B, HA discovery), simulated results with a "
        f"300 x 400 cell map; {args.rounds} scans per agent; one historian subscribed to `#`; "
        f"{mosquitto_version()}, no persistence. Per day: {per_day} scans plus keepalive "
        f"pings every {KEEPALIVE_S} s on two connections (JSON, Sparkplug).",
        "",
    ]
    results = []
    with tempfile.TemporaryDirectory(prefix="fleet-") as tmp:
        for count in args.agents:
            workdir = Path(tmp) / f"n{count}"
            workdir.mkdir()
            results.append(run(count, args.workers, args.rounds, args.idle_s, workdir))
    lines += [
        "| agents | msgs/silo/scan | kB/silo/scan | msgs/silo/day | MB/silo/day "
        "| connect msgs/silo | broker CPU s per round | broker CPU % of a core at the daily "
        "rate | idle broker CPU % | round wall s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    pings_per_day = 2 * 2 * 86400 / KEEPALIVE_S  # request + response, two connections
    for r in results:
        n, rounds = r["agents"], r["rounds"]
        msgs = sum(r["scan_msgs"].values()) / (n * rounds)
        kbytes = sum(r["scan_bytes"].values()) / (n * rounds) / 1000
        day_msgs = msgs * per_day + pings_per_day
        day_mb = (kbytes * 1000 * per_day + pings_per_day * PING_BYTES) / 1e6
        per_round = r["busy_cpu"] / rounds
        daily = per_round * per_day / 86400 * 100 + r["idle_cpu"] / r["idle_s"] * 100
        lines.append(
            f"| {n} | {msgs:.1f} | {kbytes:.1f} | {day_msgs:,.0f} | {day_mb:.2f} "
            f"| {sum(r['connect_msgs'].values()) / n:.1f} | {per_round:.2f} | {daily:.3f} "
            f"| {r['idle_cpu'] / r['idle_s'] * 100:.2f} | {r['wall'] / rounds:.1f} |"
        )
    last = results[-1]
    lines += ["", f"Per scan and silo, by topic ({last['agents']} agents):", ""]
    lines += ["| topic | msgs | payload + topic bytes |", "|---|---|---|"]
    scale = last["agents"] * last["rounds"]
    for kind in sorted(last["scan_msgs"]):
        lines.append(
            f"| `{kind}` | {last['scan_msgs'][kind] / scale:.2f} "
            f"| {last['scan_bytes'][kind] / scale:,.0f} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
