"""MQTT benchmark: replay of a backlog after an outage, and what the durable outbox costs.

    python bench/mqtt.py [--messages 10000] [--out bench/results/mqtt.md]

Runs its own mosquitto on a free loopback port (bench/mosquitto.py), never 1883.
1. Replay: N scan results are queued while the broker is unreachable, then the broker starts;
   measured: time until the subscriber has all N (messages/s) and the outbox is empty.
2. Added latency: the outbox commit (SQLite WAL, synchronous=FULL) per message, and the
   end-to-end latency publish -> subscriber through the outbox vs. a bare paho QoS 1 publish.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from silo_agent.analysis.summary import ScanSummary

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import paho.mqtt.client as mqtt  # noqa: E402
from mosquitto import Broker  # noqa: E402
from paho.mqtt.enums import CallbackAPIVersion  # noqa: E402

from silo_agent.base.log import configure_logging  # noqa: E402
from silo_agent.config import MqttConfig  # noqa: E402
from silo_agent.telemetry.client import Telemetry  # noqa: E402
from silo_agent.telemetry.payloads import Envelope  # noqa: E402

SILO = "bench"
# mosquitto's default (Nagle on) lets broker->subscriber traffic wait for delayed ACKs
BROKER_TUNING = ("set_tcp_nodelay true", "max_queued_messages 20000")
BASE = f"silo/{SILO}"


def summary(k: int) -> ScanSummary:
    return ScanSummary.from_json(
        {
            "scan_id": f"{SILO}-{k:06d}",
            "captured_at": "2026-11-22T02:00:00.000Z",
            "volume_m3": 12.3,
            "mass_t": 9.5,
            "coverage": 0.9,
            "grid_step_m": 0.02,
            "surface": {"min_z": 0.1, "mean_z": 0.9, "max_z": 1.4},
            "level": {"min": 0.1, "mean": 0.9, "max": 1.4},
            "valid": True,
            "invalid_reason": None,
            "degraded": False,
            "cameras": {"used": ["a", "b"], "failed": []},
            "piles": [],
            "timings": {"capture_s": 4.2, "reconstruct_s": 1.3},
        }
    )


class Counter:
    """Subscriber that timestamps every arrival on P/scan."""

    def __init__(self, broker: Broker, topic: str) -> None:
        self.arrivals: dict[str, float] = {}
        self.event = threading.Event()
        self.want = 0
        self.client = mqtt.Client(
            CallbackAPIVersion.VERSION2, client_id="bench-counter", protocol=mqtt.MQTTv5
        )
        ready = threading.Event()
        self.client.on_subscribe = lambda *a: ready.set()
        self.client.on_message = self._on_message
        self.client.on_connect = lambda c, *a: c.subscribe(topic, 1)
        self.client.connect("127.0.0.1", broker.port)
        self.client.loop_start()
        ready.wait(10)

    def _on_message(self, client, userdata, msg) -> None:
        key = json.loads(msg.payload)["scan_id"]
        self.arrivals.setdefault(key, time.perf_counter())
        if len(self.arrivals) >= self.want:
            self.event.set()

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def config(port: int, outbox: Path, **extra) -> MqttConfig:
    return MqttConfig.model_validate(
        {
            "port": port,
            "outbox_path": outbox,
            "reconnect_min_s": 0.05,
            "reconnect_max_s": 0.05,
            "outbox_max_messages": 1_000_000,
            **extra,
        }
    )


def bench_replay(work: Path, n: int, max_inflight: int, subscriber: bool) -> dict:
    """The subscriber is mosquitto_sub in its own process, so it does not share our GIL."""
    name = f"{max_inflight}-{subscriber}"
    broker = Broker(work / f"broker-replay-{name}", extra=BROKER_TUNING)
    tel = Telemetry(
        config(broker.port, work / f"replay-{name}.sqlite", max_inflight=max_inflight), SILO, []
    )
    for k in range(n):
        tel.publish_result(summary(k))
    pending = tel.outbox.size()
    broker.start()
    sub = None
    if subscriber:
        sub = subprocess.Popen(
            [
                "mosquitto_sub",
                "-h",
                "127.0.0.1",
                "-p",
                str(broker.port),
                "-q",
                "1",
                "-V",
                "5",
                "-t",
                f"{BASE}/scan",
                "-C",
                str(n),
                "-k",
                "600",
                "-c",
                "-i",
                "bench-sub",
                "-x",
                "3600",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(0.5)  # subscribed
    t0 = time.perf_counter()
    tel.start()
    while tel.outbox.size()[0]:
        time.sleep(0.01)
    emptied = time.perf_counter() - t0
    received, received_s = None, None
    if sub is not None:
        try:
            out, _ = sub.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            sub.kill()
            out, _ = sub.communicate()
        received, received_s = len(out.splitlines()), time.perf_counter() - t0
    tel.stop()
    broker.stop()
    return {
        "max_inflight": max_inflight,
        "pending": pending[0],
        "bytes": pending[1],
        "received": received,
        "received_s": received_s,
        "emptied_s": emptied,
    }


def bench_latency(work: Path, samples: int) -> dict:
    broker = Broker(work / "broker-latency", extra=BROKER_TUNING).start()
    counter = Counter(broker, f"{BASE}/scan")
    tel = Telemetry(config(broker.port, work / "latency.sqlite"), SILO, [])
    tel.start()
    while not tel._links[0].connected:
        time.sleep(0.01)
    enqueue, through_outbox = [], []
    for k in range(samples):
        counter.want = len(counter.arrivals) + 1
        counter.event.clear()
        t0 = time.perf_counter()

        def build(env: Envelope | None, k: int = k) -> bytes:
            assert env is not None  # enqueue makes one unless told not to
            return json.dumps({"scan_id": f"o-{k}", **env.model_dump()}).encode()

        tel.outbox.enqueue(f"{BASE}/scan", build)
        enqueue.append(time.perf_counter() - t0)
        counter.event.wait(5)
        through_outbox.append(counter.arrivals[f"o-{k}"] - t0)
    tel.stop()
    raw = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-raw", protocol=mqtt.MQTTv5)
    raw.connect("127.0.0.1", broker.port)
    raw.loop_start()
    direct = []
    for k in range(samples):
        counter.want = len(counter.arrivals) + 1
        counter.event.clear()
        t0 = time.perf_counter()
        raw.publish(f"{BASE}/scan", json.dumps({"scan_id": f"d-{k}"}), qos=1)
        counter.event.wait(5)
        direct.append(counter.arrivals[f"d-{k}"] - t0)
    raw.loop_stop()
    raw.disconnect()
    counter.close()
    broker.stop()
    return {"enqueue": enqueue, "outbox": through_outbox, "direct": direct}


def ms(values: list[float], q: float) -> str:
    return f"{statistics.quantiles(values, n=100)[int(q) - 1] * 1000:.2f}" if q < 100 else ""


def machine() -> str:
    model = next(
        (
            line.split(":", 1)[1].strip()
            for line in subprocess.run(
                ["lscpu"], capture_output=True, text=True
            ).stdout.splitlines()
            if line.startswith("Model name")
        ),
        platform.processor(),
    )
    cores = subprocess.run(["nproc"], capture_output=True, text=True).stdout.strip()
    disk = (
        "tmpfs"
        if "tmpfs"
        in subprocess.run(
            ["df", "--output=fstype", tempfile.gettempdir()], capture_output=True, text=True
        ).stdout
        else "disk"
    )
    return f"{model}, {cores} cores, Python {platform.python_version()}, outbox on {disk}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=10_000)
    parser.add_argument("--samples", type=int, default=300)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    configure_logging("warning", json_output=True)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        replays = [
            bench_replay(work, args.messages, m, s)
            for m, s in ((20, False), (20, True), (100, True))
        ]
        lat = bench_latency(work, args.samples)
    load_after = os.getloadavg()[0]
    med = statistics.median
    lines = [
        "# MQTT benchmark",
        "",
        f"Command: `python bench/mqtt.py --messages {args.messages} --samples {args.samples}`",
        f"Machine: {machine()}; mosquitto on loopback. Load average (1 min) "
        f"{load_before:.1f} before, {load_after:.1f} after: the gateway-sized VM is shared, "
        "so treat the numbers as a lower bound.",
        "",
        f"## Replay of {args.messages} pending messages after an outage",
        "",
        "P/scan results (~500 B JSON each, plus the one retained P/volume) queued while the broker "
        "was down, then the broker started (`set_tcp_nodelay true`, `max_queued_messages 20000`, "
        "no persistence). "
        "Outbox empty = every message acknowledged by the broker (QoS 1) and deleted from the "
        "outbox. With a subscriber, `mosquitto_sub -q 1` in its own process counts the messages.",
        "",
        "| max_inflight | subscriber | queued | outbox bytes | outbox empty (s) | messages/s "
        "| all received (s) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in replays:
        got = "-" if r["received"] is None else f"{r['received']} in {r['received_s']:.2f}"
        lines.append(
            f"| {r['max_inflight']} | {'yes' if r['received'] is not None else 'no'} "
            f"| {r['pending']} | {r['bytes']} | {r['emptied_s']:.2f} "
            f"| {r['pending'] / r['emptied_s']:.0f} | {got} |"
        )
    lines += [
        "",
        f"## Added latency per message ({args.samples} sequential messages)",
        "",
        "| path | median (ms) | p95 (ms) | p99 (ms) |",
        "| --- | --- | --- | --- |",
        f"| outbox commit only (SQLite WAL, synchronous=FULL) | {med(lat['enqueue']) * 1000:.2f} "
        f"| {ms(lat['enqueue'], 95)} | {ms(lat['enqueue'], 99)} |",
        f"| publish -> subscriber through the outbox | {med(lat['outbox']) * 1000:.2f} "
        f"| {ms(lat['outbox'], 95)} | {ms(lat['outbox'], 99)} |",
        f"| publish -> subscriber, bare paho QoS 1 | {med(lat['direct']) * 1000:.2f} "
        f"| {ms(lat['direct'], 95)} | {ms(lat['direct'], 99)} |",
        "",
        "The difference between the last two rows is what durability costs end to end: the "
        "fsync'ed commit plus the wait for the network thread's next turn (it polls paho with a "
        "10 ms timeout per connection).",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
