"""Settings that only a restart applies, on `silo-agent run` as a real subprocess (the test's own
mosquitto, never 1883): a SIGHUP keeps the running `silo.id`, `[mqtt]`, `[metrics]` and `[web]`
and says so on every reload whose file differs from what runs; a `[metrics] port` in use ends
`run` with 78 and one line before anything starts, as a `[web]` one does."""

from __future__ import annotations

import json
import signal
import socket
from pathlib import Path

from tests.support.agent import BASE, SILO, Daemon, write_config
from tests.support.cli import run_cli
from tests.support.mqtt_broker import free_port
from tests.test_agent import REPLIES, _status, replies, request

KEPT = "config reloaded; these changes need a restart, the running values are kept"


def test_a_reload_keeps_the_running_silo_id_and_says_so_until_the_file_is_reverted(
    tmp_path: Path, broker, collector_factory
) -> None:
    metrics_port = free_port()

    def write(silo_id: str, port: int) -> None:
        write_config(
            config,
            broker.port,
            tmp_path,
            schedule={"scan_at_start": False},
            metrics={"enabled": True, "port": port},
        )
        config.write_text(config.read_text().replace(f'id = "{SILO}"', f'id = "{silo_id}"'))

    config = tmp_path / "agent.toml"
    write(SILO, metrics_port)
    col = collector_factory(broker, [f"{BASE}/#", REPLIES])
    agent = Daemon(config, tmp_path)
    try:
        _status(col, "online")
        write("other", free_port())
        agent.signal(signal.SIGHUP)
        agent.wait_log("config reloaded")
        # the next scan is still this silo's: named, cached and published under the running id
        done = replies(col, request(col, b'{"request_id": "r-1"}'), 2)[1]
        assert done["status"] == "done" and done["scan_id"].startswith(f"{SILO}-")
        col.wait_topic(f"{BASE}/volume")
        assert json.loads(col.on(f"{BASE}/volume")[-1].payload)["scan_id"] == done["scan_id"]
        cached = [p.name for p in (tmp_path / "scans").iterdir() if p.is_dir()]
        assert cached and all(name.startswith(f"{SILO}-") for name in cached), cached
        (kept,) = agent.log_of(KEPT)
        assert kept["kept"] == ["silo.id", "[metrics]"] and kept["level"] == "warning"

        # the same file again: still not what runs, said again
        agent.signal(signal.SIGHUP)
        agent.wait_log("config reloaded", 2)
        assert len(agent.log_of(KEPT)) == 2
        # back to what runs: nothing to say
        write(SILO, metrics_port)
        agent.signal(signal.SIGHUP)
        agent.wait_log("config reloaded", 3)
        assert len(agent.log_of(KEPT)) == 2
        again = replies(col, request(col, b'{"request_id": "r-2"}'), 2)[1]
        assert again["scan_id"].startswith(f"{SILO}-")
    finally:
        agent.kill()


def test_a_metrics_port_in_use_stops_the_agent_before_it_starts(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = write_config(
            tmp_path / "agent.toml",
            free_port(),
            tmp_path,
            metrics={"enabled": True, "port": port},
        )
        done = run_cli("run", "--config", str(config))
    assert done.returncode == 78, done.stderr
    assert done.stderr == (
        f"silo-agent: metrics: cannot listen on 127.0.0.1:{port}: Address already in use; "
        "choose another metrics.port\n"
    )
    assert not (tmp_path / "outbox.sqlite").exists()  # nothing started
    assert not (tmp_path / "scans").exists()
