"""What real clients see of the daemon's alarms across a SIGKILL, a restart and a reload: the
retained JSON state of every alarm type (Home Assistant's source), the Sparkplug NBIRTH and a
rebirth decoded by pysparkplug, and /metrics parsed by prometheus_client's own parser."""

from __future__ import annotations

import json
import signal
import time
import urllib.request
from pathlib import Path

import pysparkplug as ps
import pytest
from prometheus_client.parser import text_string_to_metric_families

from silo_agent.analysis.alarm_types import ALARM_TYPES
from tests.support.agent import BASE, SILO, Daemon, write_config
from tests.support.mqtt import validate_json
from tests.support.mqtt_broker import free_port
from tests.support.sparkplug import rebirth_request

NODE = f"spBv1.0/silos/{{}}/{SILO}"
LOW = 100.0  # m³: the simulated flat bay holds ~43 m³, so level_low is raised at once
DENSITY_T_M3 = 0.77  # silo.bulk_density_t_m3 of agent_support's config


def metric_families(port: int) -> dict[str, object]:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    return {f.name: f for f in text_string_to_metric_families(text)}


def samples(family) -> dict[tuple, float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value for s in family.samples}


def alarm_metrics(births: list, index: int) -> dict[str, bool]:
    birth = ps.NBirth.decode(births[index].payload)
    return {m.name: m.value for m in birth.metrics if m.name.startswith("Alarms/")}


ALARM_TOPICS = {f"{BASE}/alarm/{t}" for t in ALARM_TYPES}


def wait_snapshot(watcher, since: int, check=lambda states: True) -> None:
    """Until the agent has published a state for every alarm type after message `since`."""

    def done(ms) -> bool:
        latest = {
            m.topic: json.loads(m.payload)
            for m in ms[since:]
            if m.topic in ALARM_TOPICS and m.payload
        }
        return set(latest) == ALARM_TOPICS and check(latest)

    watcher.wait_for(done, timeout=30)


def retained_alarm_states(broker, collector_factory, client_id: str) -> dict[str, dict]:
    """What a client subscribing now (HA after its own restart) gets for `P/alarm/<type>`:
    only the broker's retained messages count."""
    fresh = collector_factory(broker, [f"{BASE}/alarm/+"], client_id=client_id)
    fresh.wait_for(lambda ms: {m.topic for m in ms if m.retain} >= ALARM_TOPICS)
    return {m.topic.rsplit("/", 1)[1]: validate_json(m.payload) for m in fresh.messages if m.retain}


@pytest.mark.slow
def test_alarm_state_survives_sigkill_in_births_retained_states_and_metrics_and_a_switched_off_detector_clears(  # noqa: E501
    tmp_path: Path, broker, collector_factory
):
    port = free_port()
    options = dict(
        mqtt={"sparkplug.enabled": True, "homeassistant.enabled": True},
        metrics={"enabled": True, "port": port},
    )
    config = write_config(
        tmp_path / "agent.toml", broker.port, tmp_path, alarms={"low_volume_m3": LOW}, **options
    )
    spb = collector_factory(broker, ["spBv1.0/#"], client_id="host")
    watcher = collector_factory(broker, [f"{BASE}/alarm/+"], client_id="watcher")
    agent = Daemon(config, tmp_path)
    try:
        # --- a fresh agent: every alarm type has a retained state before any scan ends
        wait_snapshot(watcher, 0)
        before = retained_alarm_states(broker, collector_factory, "ha-1")
        assert {t: s["state"] for t, s in before.items()} == dict.fromkeys(ALARM_TYPES, "cleared")

        # --- the first scan raises level_low; the metrics say so, with mass and capture time
        (finished,) = agent.wait_log("scan finished", timeout=60)
        watcher.wait_for(
            lambda ms: any(
                m.topic == f"{BASE}/alarm/level_low" and b'"raised"' in m.payload for m in ms
            )
        )
        raised = retained_alarm_states(broker, collector_factory, "ha-2")["level_low"]
        assert raised["state"] == "raised" and raised["scan_id"] == finished["scan_id"]
        families = metric_families(port)
        volume = families["silo_agent_last_volume_cubic_meters"].samples[0].value
        assert 30 < volume < LOW
        mass = families["silo_agent_last_mass_kilograms"].samples[0].value
        assert abs(mass - volume * DENSITY_T_M3 * 1000) < 1e-6 * mass
        captured = families["silo_agent_last_scan_timestamp_seconds"].samples[0].value
        assert abs(captured - time.time()) < 120
        assert families["silo_agent_last_valid_scan_timestamp_seconds"].samples[0].value == captured

        # --- SIGKILL, restart without a scan: the persisted alarm is raised everywhere. The
        # broker forgets the retained states (as one without persistence would after its own
        # restart), so only the new process can bring them back.
        agent.signal(signal.SIGKILL)
        agent.wait()
        for topic in ALARM_TOPICS:
            watcher.client.publish(topic, b"", qos=1, retain=True).wait_for_publish(5)
        since = len(watcher.messages)
        write_config(
            config,
            broker.port,
            tmp_path,
            schedule={"scan_at_start": False},
            alarms={"low_volume_m3": LOW},
            **options,
        )
        births_before = len(spb.on(NODE.format("NBIRTH")))
        agent = Daemon(config, tmp_path)
        agent.wait_log("agent started")
        births = spb.wait_topic(NODE.format("NBIRTH"), births_before + 1)
        alarms = alarm_metrics(births, births_before)
        assert alarms == {f"Alarms/{t}": t == "level_low" for t in ALARM_TYPES}
        wait_snapshot(watcher, since)
        after = retained_alarm_states(broker, collector_factory, "ha-3")
        assert {t for t, s in after.items() if s["state"] == "raised"} == {"level_low"}
        assert after["level_low"]["scan_id"] == finished["scan_id"]

        spb.publish(NODE.format("NCMD"), rebirth_request())
        births = spb.wait_topic(NODE.format("NBIRTH"), births_before + 2)
        assert alarm_metrics(births, births_before + 1)["Alarms/level_low"] is True

        # --- /metrics before any scan of this process: every outcome and alarm type is there
        families = metric_families(port)
        assert families["silo_agent_scans"].type == "counter"
        assert samples(families["silo_agent_scans"]) == {
            ("silo_agent_scans_total", (("outcome", o),)): 0.0 for o in ("ok", "invalid", "failed")
        }
        assert samples(families["silo_agent_alarm_active"]) == {
            ("silo_agent_alarm_active", (("type", t),)): float(t == "level_low")
            for t in ALARM_TYPES
        }
        assert families["silo_agent_outbox_dropped_messages"].type == "counter"
        for name in (
            "silo_agent_outbox_pending_messages",
            "silo_agent_last_volume_cubic_meters",
            "silo_agent_last_mass_kilograms",
            "silo_agent_last_scan_timestamp_seconds",
        ):
            assert families[name].type == "gauge", name
        counters = [f for f in families.values() if f.type == "counter"]
        assert all(s.name.endswith(("_total", "_created")) for f in counters for s in f.samples)

        # --- low_volume_m3 removed, SIGHUP: level_low clears with an event, everywhere
        events = collector_factory(broker, [f"{BASE}/alarm"], client_id="events")
        write_config(config, broker.port, tmp_path, schedule={"scan_at_start": False}, **options)
        agent.signal(signal.SIGHUP)
        agent.wait_log("config reloaded")
        cleared = validate_json(events.wait_topic(f"{BASE}/alarm")[0].payload)
        assert (cleared["type"], cleared["state"]) == ("level_low", "cleared")
        assert "low_volume_m3" in cleared["message"]
        assert (
            retained_alarm_states(broker, collector_factory, "ha-4")["level_low"]["state"]
            == "cleared"
        )
        spb.wait_for(
            lambda ms: any(
                m.topic == NODE.format("NDATA")
                and any(
                    x.name == "Alarms/level_low" and x.value is False
                    for x in ps.NData.decode(m.payload).metrics
                )
                for m in ms
            )
        )
        assert (
            samples(metric_families(port)["silo_agent_alarm_active"])[
                ("silo_agent_alarm_active", (("type", "level_low"),))
            ]
            == 0.0
        )
        state = json.loads((tmp_path / "scans" / "alarm-state.json").read_text())
        assert "level_low" not in state["active"]
        agent.signal(signal.SIGTERM)
        assert agent.wait(20) == 0
    finally:
        agent.kill()
