"""The daemon as the tests run it: a real `silo-agent run` subprocess on simulated cameras
(two virtual D455s at 424x240 on the walls of the 6 m bay, 5 cm grid: fast), the test's own
mosquitto, and a unix datagram socket standing in for systemd's $NOTIFY_SOCKET."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

SILO = "silo-d"
# a sim camera 4 m up looking straight at the sky (its optical axis along the silo's +z): it
# measures no point, so its capture fails ("no valid depth pixels") as a real camera's would
SKY_EXTRINSIC = "[[1, 0, 0, 0], [0, 1, 0, -2.5], [0, 0, 1, 4.0], [0, 0, 0, 1]]"
BASE = f"silo/{SILO}"


def toml_value(value: object) -> str:
    return json.dumps(value) if not isinstance(value, bool) else str(value).lower()


def write_config(
    path: Path,
    port: int,
    workdir: Path,
    *,
    schedule: dict | None = None,
    simulation: dict | None = None,
    audit: dict | None = None,
    alarms: dict | None = None,
    metrics: dict | None = None,
    mqtt: dict | None = None,
    web: dict | None = None,
    cameras: tuple[tuple[str, str | None], ...] = (("sim-A2", "A2"), ("sim-A6", "A6")),
) -> Path:
    """A config for the test daemon; sections given replace the defaults here (`mqtt` adds
    keys, dotted for its sub-tables: `{"sparkplug.enabled": True}`)."""
    sections = {
        "schedule": schedule if schedule is not None else {"scan_at_start": True},
        "simulation": {
            "sequence": ["flat"],
            "vary_noise": True,
            "layout": "wall",
            **(simulation or {}),
        },
        "audit": {
            "directory": str(workdir / "scans"),
            "max_bytes": 200_000_000,
            "max_age_days": 30,
            **(audit or {}),
        },
        "mqtt": {
            "host": "127.0.0.1",
            "port": port,
            "outbox_path": str(workdir / "outbox.sqlite"),
            "reconnect_min_s": 0.1,
            "reconnect_max_s": 0.5,
            "keepalive_s": 5,
            "shutdown_timeout_s": 2.0,
            **(mqtt or {}),
        },
        "alarms": alarms or {},
        "metrics": metrics or {},
        "web": web or {},
    }
    lines = [
        "[silo]",
        f'id = "{SILO}"',
        "region = [[-3.0, -3.0], [3.0, -3.0], [3.0, 3.0], [-3.0, 3.0]]",
        "floor_z = 0.0",
        "ceiling_z = 2.8",
        "bulk_density_t_m3 = 0.77",
        "",
        "[reconstruction]",
        "grid_step_m = 0.05",
        "",
    ]
    for serial, view in cameras:  # without a view: a sim camera that fails, seeing nothing
        lines += [
            "[[cameras]]",
            f'serial = "{serial}"',
            'source = "sim"',
            f'view = "{view}"' if view else f"extrinsic = {SKY_EXTRINSIC}",
            "width = 424",
            "height = 240",
            "",
        ]
    for name, values in sections.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {toml_value(v)}" for k, v in values.items()]
        lines.append("")
    path.write_text("\n".join(lines))
    return path


class Daemon:
    """`silo-agent run` in a subprocess; its stderr (JSON log lines) goes to a file."""

    def __init__(
        self, config: Path, workdir: Path, *args: str, env: dict[str, str] | None = None
    ) -> None:
        self.log_path = workdir / f"agent-{time.monotonic_ns()}.log"
        self.out_path = self.log_path.with_suffix(".out")
        self._err = open(self.log_path, "w")  # noqa: SIM115 - closed in wait()
        self._out = open(self.out_path, "w")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "silo_agent", "run", "--config", str(config), *args],
            stdout=self._out,
            stderr=self._err,
            env={**os.environ, **(env or {})},
        )

    def signal(self, signum: int) -> None:
        os.kill(self.proc.pid, signum)

    def wait(self, timeout: float = 30) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            self._err.close()
            self._out.close()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.signal(signal.SIGKILL)
        self.wait()

    def log(self) -> list[dict]:
        out = []
        for line in self.log_path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                out.append({"event": line})
        return out

    def log_of(self, event: str) -> list[dict]:
        """The log entries of one event so far."""
        return [e for e in self.log() if e.get("event") == event]

    def wait_log(self, event: str, count: int = 1, timeout: float = 30) -> list[dict]:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            found = [e for e in self.log() if e.get("event") == event]
            if len(found) >= count:
                return found
            assert self.proc.poll() is None, f"agent exited: {self.log_path.read_text()[-3000:]}"
            time.sleep(0.05)
        raise AssertionError(f"no {count} x {event!r} in the log: {self.log_path.read_text()}")


class NotifySocket:
    """What systemd listens on: collects every datagram the agent sends."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._recv, daemon=True)
        self._thread.start()

    def _recv(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            self.messages.append((time.monotonic(), data.decode()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()

    def wait_for(self, message: str, count: int = 1, timeout: float = 30) -> None:
        """Until `message` has come `count` times."""
        end = time.monotonic() + timeout
        while sum(m == message for _, m in self.messages) < count:
            assert time.monotonic() < end, f"no {count} x {message!r}: {self.messages}"
            time.sleep(0.05)

    def fields(self) -> list[str]:
        return [f for _, m in self.messages for f in m.split("\n")]
