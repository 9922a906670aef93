"""`silo-agent publish` and `flush` beside a running agent, through the real CLI, the test's own
mosquitto and a real `silo-agent run`: they never take the agent's client id, never say
`P/status`, the alarm states or Sparkplug births of their own, and never run on the outbox of an
agent that runs (the lock `run` holds)."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

from silo_agent.analysis.alarm_types import ALARM_TYPES
from silo_agent.telemetry.outbox import Outbox
from tests.support.agent import BASE, SILO, Daemon, write_config
from tests.support.cli import run_cli
from tests.support.mqtt import summary_json, validate_json

SPB = "spBv1.0/#"
NO_SCAN = {"scan_at_start": False}


def _settled(col) -> int:
    """Until the agent's session messages are in (`P/status` online, every alarm state, and
    a moment for the rest); how many messages the collector has then."""
    col.wait_for(
        lambda ms: any(
            m.topic == f"{BASE}/status"
            and json.loads(m.payload)["state"] == "online"
            and json.loads(m.payload)["client_id"] == f"silo-agent-{SILO}"
            for m in ms
        )
    )
    col.wait_for(lambda ms: sum("/alarm/" in m.topic for m in ms) >= len(ALARM_TYPES))
    time.sleep(0.5)
    return len(col.messages)


def _stop(agent: Daemon) -> None:
    if agent.proc.poll() is None:
        agent.signal(signal.SIGTERM)
    agent.wait()


def test_flush_and_publish_refuse_to_run_on_the_running_agents_outbox(
    broker, tmp_path: Path, collector_factory
):
    """`flush --config <the running agent's file>` ran beside the agent on its outbox (rc 0):
    now one line naming the lock `run` holds, exit 1, and the agent is left alone; `publish`
    queues into that outbox, so it refuses the same way, before queueing anything."""
    config = write_config(tmp_path / "agent.toml", broker.port, tmp_path, schedule=NO_SCAN)
    col = collector_factory(broker, [f"{BASE}/#"])
    agent = Daemon(config, tmp_path)
    try:
        before = _settled(col)
        held = f"another silo-agent (pid {agent.proc.pid}) is running on {tmp_path / 'scans'}"

        flushed = run_cli("flush", "--config", str(config), "--timeout", "5")
        assert flushed.returncode == 1, flushed
        assert flushed.stdout == ""
        assert flushed.stderr.splitlines() == [
            f"silo-agent: {held}: one agent per outbox and audit directory;"
            " the running agent sends the outbox itself"
        ]

        result = tmp_path / "result.json"
        result.write_text(json.dumps(summary_json(f"{SILO}-by-hand")))
        published = run_cli(
            "publish", "--config", str(config), "--result", str(result), "--timeout", "5"
        )
        assert published.returncode == 1, published
        assert published.stdout == ""  # nothing queued
        assert published.stderr.splitlines() == [
            f"silo-agent: {held}: one agent per outbox and audit directory;"
            " the running agent sends the outbox itself: stop it to publish by hand"
        ]

        time.sleep(1.0)  # what a takeover would have set off has come by now
        assert [m.topic for m in col.messages[before:]] == []
        assert agent.log_of("connection to the broker lost") == []
        assert agent.proc.poll() is None
    finally:
        _stop(agent)


def test_publish_and_flush_leave_the_agents_session_alone(
    broker, tmp_path: Path, collector_factory
):
    """An agent runs for the silo; `publish` and `flush` run for the same silo on a state of
    their own (another outbox, e.g. a copy of the config on a laptop). They connected as the
    agent's client id (the broker pushed the agent off: its Last Will `offline`, a new session),
    sent `P/status` online and `stopped`, every retained `P/alarm/<type>` and a Sparkplug
    NBIRTH / NDEATH of their own. Now they send only what they were asked to, as
    `<client_id>-publish` / `-flush`; the Sparkplug NDATA waits in their outbox for an agent."""
    spb = {"sparkplug.enabled": True}
    agent_dir, hand_dir = tmp_path / "agent", tmp_path / "hand"
    agent_dir.mkdir()
    hand_dir.mkdir()
    agent_config = write_config(
        agent_dir / "agent.toml", broker.port, agent_dir, schedule=NO_SCAN, mqtt=spb
    )
    hand_config = write_config(
        hand_dir / "agent.toml", broker.port, hand_dir, schedule=NO_SCAN, mqtt=spb
    )
    col = collector_factory(broker, [f"{BASE}/#", SPB])
    agent = Daemon(agent_config, agent_dir)
    try:
        col.wait_topic(f"spBv1.0/silos/NBIRTH/{SILO}")
        before = _settled(col)

        result = hand_dir / "result.json"
        result.write_text(json.dumps(summary_json(f"{SILO}-by-hand")))
        event = hand_dir / "event.json"
        event.write_text(
            json.dumps(
                {
                    "type": "level_high",
                    "state": "raised",
                    "severity": "warning",
                    "scan_id": f"{SILO}-by-hand",
                    "message": "by hand",
                }
            )
        )
        published = run_cli(
            "publish",
            "--config",
            str(hand_config),
            "--result",
            str(result),
            "--alarm",
            str(event),
            "--timeout",
            "10",
        )
        assert published.returncode == 0, published
        queued = [json.loads(line)["topic"] for line in published.stdout.splitlines()]
        assert queued == [f"{BASE}/scan", f"{BASE}/volume", f"{BASE}/alarm"]
        # nothing left to send: connected (--linger), it sends nothing at all
        flushed = run_cli("flush", "--config", str(hand_config), "--timeout", "5", "--linger", "1")
        assert (flushed.returncode, flushed.stdout) == (0, "drained\n"), flushed

        asked = {f"{BASE}/{t}" for t in ("scan", "volume", "alarm", "alarm/level_high")}
        col.wait_for(lambda ms: asked <= {m.topic for m in ms[before:]})
        time.sleep(1.0)  # a Last Will or a `stopped` would have come by now
        sent = col.messages[before:]
        assert sorted(m.topic for m in sent) == sorted(asked), [m.topic for m in sent]
        state = validate_json(col.on(f"{BASE}/alarm/level_high")[-1].payload)
        assert (state["state"], state["message"]) == ("raised", "by hand")

        assert agent.log_of("connection to the broker lost") == []
        log = broker.log()
        assert f"as silo-agent-{SILO}-publish" in log and f"as silo-agent-{SILO}-flush" in log
        left = Outbox(hand_dir / "outbox.sqlite")  # for the agent on this state to send
        assert [row.kind for row in left.pending()] == ["sparkplug"] * 2  # result, alarm
        left.close()
    finally:
        _stop(agent)
