"""Home Assistant discovery: what HA would build from it, and the republish on HA's birth."""

from __future__ import annotations

import json

import jinja2

from silo_agent.telemetry.payloads import ALARM_TYPES
from tests.support.mqtt import BASE, SILO, summary

CONFIG = f"homeassistant/device/silo_agent_{SILO}/config"


def render(template: str, payload: bytes) -> str:
    """Evaluate a value_template the way HA does (Jinja2 with value_json)."""
    return jinja2.Environment().from_string(template).render(value_json=json.loads(payload))


def test_discovery_config_and_republish_on_ha_online(broker, telemetry_factory,
                                                     collector_factory):
    col = collector_factory(broker, ["homeassistant/#", f"{BASE}/#"])
    tel = telemetry_factory(broker, homeassistant={"enabled": True})
    msg = col.wait_topic(CONFIG)[0]
    late = collector_factory(broker, [CONFIG], client_id="late")
    assert late.wait_topic(CONFIG)[0].retain
    config = json.loads(msg.payload)
    assert config["dev"]["ids"] == [f"silo_agent_{SILO}"] and config["dev"]["sw"] == "9.9.9"
    assert config["o"]["name"] == "silo-agent"
    cmps = config["cmps"]
    volume = cmps["volume"]
    assert (volume["p"], volume["device_class"], volume["state_class"],
            volume["unit_of_measurement"]) == ("sensor", "volume_storage", "measurement", "m³")
    assert volume["state_topic"] == f"{BASE}/volume"
    assert cmps["mass"]["unit_of_measurement"] == "t" and cmps["mass"]["device_class"] == "weight"
    assert {f"alarm_{t}" for t in ALARM_TYPES} <= set(cmps)
    assert all(cmps[f"alarm_{t}"]["p"] == "binary_sensor" for t in ALARM_TYPES)
    assert len({c["unique_id"] for c in cmps.values()}) == len(cmps)

    # the templates produce the right states from the payloads the agent really publishes
    tel.publish_result(summary())
    tel.publish_alarm({"type": "collapse", "state": "raised", "severity": "critical",
                       "scan_id": summary()["scan_id"]})
    vol = col.wait_topic(f"{BASE}/volume")[0].payload
    assert render(volume["value_template"], vol) == "12.345"
    assert render(cmps["coverage"]["value_template"], vol) == "87.0"
    assert render(cmps["level_max"]["value_template"], vol) == "1.4"
    alarm = col.wait_topic(f"{BASE}/alarm/collapse")[0].payload
    assert render(cmps["alarm_collapse"]["value_template"], alarm) == "ON"
    avail = config["availability"][0]
    assert avail["topic"] == f"{BASE}/status"
    status = col.wait_topic(f"{BASE}/status")[-1].payload
    assert render(avail["value_template"], status) == avail["payload_available"]
    stopped = json.dumps({**json.loads(status), "state": "stopped"}).encode()
    assert render(avail["value_template"], stopped) == avail["payload_not_available"]

    # HA restarts and announces itself: the config comes again
    col.client.publish("homeassistant/status", b"online", qos=1)
    col.wait_topic(CONFIG, 2)
    col.client.publish("homeassistant/status", b"offline", qos=1)
    col.publish(f"{BASE}/cmd/scan", b"{}")  # a round trip through the agent, then count
    col.wait_topic(f"{BASE}/cmd/scan/reply")
    assert len(col.on(CONFIG)) == 2
