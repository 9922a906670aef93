"""Soak: does a long-running agent grow? Memory, file descriptors, threads and disk over
hundreds of scans.

`silo-agent run` on simulated cameras (four D455s on the 6 m bay's walls) with everything a
site has switched on around it: its own mosquitto, scans asked for one after another by MQTT
command (`P/cmd/scan`, each waited on as its `P/scan` message: no sleeps) beside a slow
schedule, the operator's page fetched after each scan as an open page fetches it (state, scan
list, the new map's picture, history), the Prometheus endpoint scraped, and an audit cache small
enough that retention evicts a scan for every scan kept. After each scan the agent's resident
memory, open descriptors and threads are read from /proc, and the cache's and outbox's sizes
from disk.

A leak shows as a slope: the table gives each figure at checkpoints and its least-squares
growth per 100 scans over the second half of the run (the first scans fault in the
simulator's world, the reconstruction's arrays and the page's caches).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import paho.mqtt.client as mqtt
from benchlib import header
from mosquitto import HOST, Broker, free_port
from paho.mqtt.enums import CallbackAPIVersion

SILO = "soak-1"
TOKEN = "soak-token"
SCHEDULE_S = 20.0  # a scheduled scan now and then, between the commanded ones
CHECKPOINTS = (1, 10, 25, 50, 100, 200, 300, 400, 500, 750, 1000)

AGENT_TOML = """
[silo]
id = "{silo}"
region = [[-3.0, -3.0], [3.0, -3.0], [3.0, 3.0], [-3.0, 3.0]]
floor_z = 0.0
ceiling_z = 2.8
bulk_density_t_m3 = 0.77

[reconstruction]
grid_step_m = 0.02

{cameras}
[simulation]
sequence = ["piles", "cone", "ridge"]
vary_noise = true
layout = "wall"

[schedule]
interval_s = {interval}
scan_at_start = true

[audit]
directory = "{work}/scans"
max_bytes = {cache_bytes}

[mqtt]
host = "127.0.0.1"
port = {port}
outbox_path = "{work}/outbox.sqlite"

[web]
enabled = true
port = {web_port}
token_file = "{work}/token"

[metrics]
enabled = true
port = {metrics_port}
"""


def _proc(pid: int) -> tuple[float, int, int]:
    """(resident MB, open descriptors, threads) of process `pid`."""
    status = Path(f"/proc/{pid}/status").read_text()
    rss_kb = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS"))
    return rss_kb / 1024, len(os.listdir(f"/proc/{pid}/fd")), len(os.listdir(f"/proc/{pid}/task"))


def _megabytes(path: Path) -> float:
    if path.is_file():
        return path.stat().st_size / 1e6
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 1e6


class _Watcher:
    """Counts the agent's `P/scan` messages and sends its scan commands."""

    def __init__(self, port: int) -> None:
        self.scans: list[dict] = []
        self.replies = 0
        self._changed = threading.Condition()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, protocol=mqtt.MQTTv5)
        self.client.on_message = self._message
        self.client.connect(HOST, port)
        self.client.subscribe([(f"silo/{SILO}/scan", 1), (f"silo/{SILO}/cmd/scan/reply", 1)])
        self.client.loop_start()
        self.requested = 0

    def _message(self, _client: mqtt.Client, _userdata: object, msg: mqtt.MQTTMessage) -> None:
        with self._changed:
            if msg.topic.endswith("/reply"):
                self.replies += 1
            else:
                self.scans.append(json.loads(msg.payload))
            self._changed.notify_all()

    def wait_scans(self, count: int, timeout: float) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: len(self.scans) >= count, timeout)

    def request_scan(self) -> None:
        self.requested += 1
        payload = json.dumps({"request_id": f"soak-{self.requested}"})
        self.client.publish(f"silo/{SILO}/cmd/scan", payload, qos=1)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def _visit(web_port: int, metrics_port: int, scan_id: str) -> None:
    """What an open page fetches after a scan, and a Prometheus scrape."""
    base = f"http://127.0.0.1:{web_port}"
    for path in (
        "/api/state",
        "/api/scans",
        f"/api/map/{scan_id}.png",
        "/api/history.svg",
    ):
        request = urllib.request.Request(base + path, headers={"Authorization": f"Bearer {TOKEN}"})
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                response.read()
        except urllib.error.HTTPError as exc:
            raise RuntimeError(f"GET {path}: {exc.code} {exc.read()[:200]!r}") from exc
    with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=30) as r:
        r.read()


def soak(scans: int, cache_mb: float, cpu: int, work: Path) -> list[dict]:
    """Run the agent until it has published `scans` scans, then stop it as a service
    manager does; one row of readings after each scan."""
    broker = Broker(work / "broker").start()
    (work / "token").write_text(TOKEN)
    web_port, metrics_port = free_port(), free_port()
    cameras = "".join(
        f'[[cameras]]\nserial = "sim-{v}"\nsource = "sim"\nview = "{v}"\n'
        "width = 424\nheight = 240\n\n"
        for v in ("A1", "A3", "A5", "A7")
    )
    config = work / "agent.toml"
    config.write_text(
        AGENT_TOML.format(
            silo=SILO,
            cameras=cameras,
            interval=SCHEDULE_S,
            work=work,
            cache_bytes=int(cache_mb * 1e6),
            port=broker.port,
            web_port=web_port,
            metrics_port=metrics_port,
        )
    )
    watcher = _Watcher(broker.port)
    log = open(work / "agent.log", "w")  # noqa: SIM115 - closed below
    agent = subprocess.Popen(
        [
            "taskset",
            "-c",
            str(cpu),
            sys.executable,
            "-m",
            "silo_agent",
            "run",
            "--config",
            str(config),
        ],
        stdout=subprocess.DEVNULL,
        stderr=log,
    )
    rows = []
    try:
        start = time.monotonic()
        for n in range(1, scans + 1):
            if n > 1:  # the first is the schedule's scan_at_start
                watcher.request_scan()
            if not watcher.wait_scans(n, 300):
                raise RuntimeError(f"no P/scan for scan {n} in 300 s; see {work / 'agent.log'}")
            scan = watcher.scans[n - 1]
            if not scan["valid"]:
                raise RuntimeError(f"scan {scan['scan_id']} invalid: {scan['invalid_reason']}")
            _visit(web_port, metrics_port, scan["scan_id"])
            rss, fds, threads = _proc(agent.pid)
            rows.append(
                {
                    "scan": n,
                    "minutes": (time.monotonic() - start) / 60,
                    "rss_mb": rss,
                    "fds": fds,
                    "threads": threads,
                    "cache_mb": _megabytes(work / "scans"),
                    "kept": len(list((work / "scans").glob(f"{SILO}-*"))),
                    "outbox_mb": _megabytes(work / "outbox.sqlite"),
                }
            )
        agent.send_signal(signal.SIGTERM)  # the way a service manager stops it
        status = agent.wait(120)
        if status != 0:
            raise RuntimeError(f"the agent exited {status}; see {work / 'agent.log'}")
        rows[-1]["replies"] = watcher.replies
        return rows
    finally:
        if agent.poll() is None:
            agent.kill()
        log.close()
        watcher.close()
        broker.stop()


def _slope(rows: list[dict], key: str) -> float:
    """Least-squares growth of `key` per 100 scans over the second half of the run."""
    half = rows[len(rows) // 2 :]
    x = np.array([r["scan"] for r in half], dtype=float)
    y = np.array([r[key] for r in half], dtype=float)
    return float(np.polyfit(x, y, 1)[0] * 100) if len(half) > 1 else 0.0


def report(rows: list[dict], cache_mb: float) -> list[str]:
    at = [r for r in rows if r["scan"] in CHECKPOINTS or r is rows[-1]]
    lines = [
        "| scans | minutes | agent RSS MB | open fds | threads | audit cache MB | scans kept |"
        " outbox MB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in at:
        lines.append(
            f"| {r['scan']} | {r['minutes']:.1f} | {r['rss_mb']:.1f} | {r['fds']} |"
            f" {r['threads']} | {r['cache_mb']:.1f} | {r['kept']} | {r['outbox_mb']:.2f} |"
        )
    lines += [
        "",
        f"Growth per 100 scans over the second half (scans {rows[len(rows) // 2]['scan']}-"
        f"{rows[-1]['scan']}, least squares): RSS {_slope(rows, 'rss_mb'):+.2f} MB, open fds"
        f" {_slope(rows, 'fds'):+.2f}, threads {_slope(rows, 'threads'):+.2f}, audit cache"
        f" {_slope(rows, 'cache_mb'):+.2f} MB (max_bytes {cache_mb:g} MB), outbox"
        f" {_slope(rows, 'outbox_mb'):+.3f} MB. Peak RSS over the run"
        f" {max(r['rss_mb'] for r in rows):.1f} MB; {rows[-1].get('replies', 0)} scan commands"
        " answered.",
    ]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=300)
    parser.add_argument("--cache-mb", type=float, default=60.0, help="audit.max_bytes in MB")
    parser.add_argument("--cpu", type=int, default=0, help="the CPU the agent runs on")
    parser.add_argument("--note", default="", help="a provenance line, e.g. machine load")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.scans < 20:  # the growth is fitted over the second half, after the warm-up
        parser.error(f"--scans: at least 20, not {args.scans}")
    work = Path(tempfile.mkdtemp(prefix="silo-soak-"))
    try:
        rows = soak(args.scans, args.cache_mb, args.cpu, work)
    except Exception:
        log = work / "agent.log"
        print(f"the agent's last log lines ({log}):", file=sys.stderr)
        print("\n".join(log.read_text().splitlines()[-15:]), file=sys.stderr)
        raise
    shutil.rmtree(work, ignore_errors=True)
    lines = header("Soak: a long-running agent's memory, descriptors, threads and disk", args.note)
    lines += [
        f"`silo-agent run` on four simulated 424x240 D455s over a 6 m square (2 cm grid),"
        f" {args.scans} scans, each asked for by an MQTT command once the one before was"
        f" published, beside a schedule every {SCHEDULE_S:g} s; its own mosquitto, the"
        " operator's page fetched as an open page fetches it after each scan (state, scan list,"
        " the map's picture, history), Prometheus scraped, the audit cache capped at"
        f" {args.cache_mb:g} MB so that retention evicts as it keeps. Readings after each scan's"
        " `P/scan` message, from /proc and the disk. The simulated cameras load open3d's ray"
        " caster (a process that imports it is about 257 MB resident before any scan); an agent"
        " on real D455s does not.",
        "",
        *report(rows, args.cache_mb),
        "",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
