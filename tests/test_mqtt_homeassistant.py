"""Home Assistant discovery: what HA would build from it, and the republish on HA's birth."""

from __future__ import annotations

import json

import jinja2

from silo_agent.analysis.alarm_types import ALARM_TYPES, AlarmEvent
from silo_agent.config import ScheduleConfig, stale_after_s
from tests.support.mqtt import BASE, SILO, summary, validate_json

CONFIG = f"homeassistant/device/silo_agent_{SILO}/config"


def render(template: str, payload: bytes) -> str:
    """Evaluate a value_template the way HA does (Jinja2 with value_json)."""
    return jinja2.Environment().from_string(template).render(value_json=json.loads(payload))


def test_discovery_config_and_republish_on_ha_online(broker, telemetry_factory, collector_factory):
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
    assert (
        volume["p"],
        volume["device_class"],
        volume["state_class"],
        volume["unit_of_measurement"],
    ) == ("sensor", "volume_storage", "measurement", "m³")
    assert volume["state_topic"] == f"{BASE}/volume"
    assert cmps["mass"]["unit_of_measurement"] == "kg" and cmps["mass"]["device_class"] == "weight"
    assert {f"alarm_{t}" for t in ALARM_TYPES} <= set(cmps)
    assert all(cmps[f"alarm_{t}"]["p"] == "binary_sensor" for t in ALARM_TYPES)
    assert len({c["unique_id"] for c in cmps.values()}) == len(cmps)

    # the templates produce the right states from the payloads the agent really publishes
    tel.publish_result(summary())
    tel.publish_alarm(
        AlarmEvent.from_json(
            {
                "type": "collapse",
                "state": "raised",
                "severity": "critical",
                "scan_id": summary().scan_id,
            }
        )
    )
    vol = col.wait_topic(f"{BASE}/volume")[0].payload
    assert render(volume["value_template"], vol) == "12.345"
    assert render(cmps["mass"]["value_template"], vol) == "9506.0"  # mass_t 9.506 t, in kg
    assert render(cmps["coverage"]["value_template"], vol) == "87.0"
    assert render(cmps["level_max"]["value_template"], vol) == "1.4"
    alarm = col.wait_topic(f"{BASE}/alarm/collapse", 2)[-1].payload  # the state, then the event
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


# Home Assistant's own rules, from homeassistant/components/sensor/const.py (DEVICE_CLASS_UNITS,
# DEVICE_CLASS_STATE_CLASSES, NON_NUMERIC_DEVICE_CLASSES) with the unit enums of
# homeassistant/const.py (UnitOfVolume, UnitOfMass, UnitOfLength), for the classes a silo
# could use. HA drops a discovered sensor whose unit its device class does not know.
HA_SENSOR_UNITS: dict[str | None, set[str | None]] = {
    "volume_storage": {"ft³", "CCF", "MCF", "m³", "L", "mL", "gal", "fl. oz."},
    "volume": {"ft³", "CCF", "MCF", "m³", "L", "mL", "gal", "fl. oz."},
    "weight": {"g", "kg", "mg", "µg", "oz", "lb", "st"},
    "distance": {"mm", "cm", "m", "km", "in", "ft", "yd", "mi", "nmi"},
    "timestamp": {None},
    "date": {None},
    "enum": {None},
}
HA_STATE_CLASSES: dict[str | None, set[str | None]] = {
    "volume_storage": {"measurement", None},
    "volume": {"total", "total_increasing", None},
    "weight": {"measurement", "total", "total_increasing", None},
    "distance": {"measurement", "total", "total_increasing", None},
    "timestamp": {None},
    "date": {None},
    "enum": {None},
    None: {"measurement", "total", "total_increasing", None},
}
HA_BINARY_SENSOR_CLASSES = {
    None,
    "battery",
    "battery_charging",
    "carbon_monoxide",
    "cold",
    "connectivity",
    "door",
    "garage_door",
    "gas",
    "heat",
    "light",
    "lock",
    "moisture",
    "motion",
    "moving",
    "occupancy",
    "opening",
    "plug",
    "power",
    "presence",
    "problem",
    "running",
    "safety",
    "smoke",
    "sound",
    "tamper",
    "update",
    "vibration",
    "window",
}


def ha_rule_violations(cmps: dict) -> list[str]:
    """What HA's MQTT sensor / binary_sensor validation would reject or warn about."""
    bad = []
    for key, c in cmps.items():
        dc, unit, sc = c.get("device_class"), c.get("unit_of_measurement"), c.get("state_class")
        if c["p"] == "sensor":
            if dc is not None and unit not in HA_SENSOR_UNITS.get(dc, {unit}):
                bad.append(f"{key}: unit {unit!r} is not one of device class {dc!r}")
            if sc not in HA_STATE_CLASSES.get(dc, HA_STATE_CLASSES[None]):
                bad.append(f"{key}: state class {sc!r} not allowed with device class {dc!r}")
        elif c["p"] == "binary_sensor" and (
            dc not in HA_BINARY_SENSOR_CLASSES or unit is not None or sc is not None
        ):
            bad.append(f"{key}: binary_sensor with {dc!r}, {unit!r}, {sc!r}")
        if "expire_after" in c and not (
            isinstance(c["expire_after"], int) and c["expire_after"] > 0
        ):  # cv.positive_int
            bad.append(f"{key}: expire_after {c['expire_after']!r}")
    return bad


def test_every_discovered_entity_passes_home_assistants_unit_and_class_rules(
    broker, telemetry_factory, collector_factory
):
    col = collector_factory(broker, [CONFIG])
    telemetry_factory(broker, homeassistant={"enabled": True}, expire_after_s=7800)
    cmps = json.loads(col.wait_topic(CONFIG)[0].payload)["cmps"]
    assert ha_rule_violations(cmps) == []
    tonne = {"p": "sensor", "device_class": "weight", "unit_of_measurement": "t"}
    stamp = {"p": "sensor", "device_class": "timestamp", "state_class": "measurement"}
    assert len(ha_rule_violations({"mass": tonne, "last_scan": stamp})) == 2  # the table bites
    readings = (
        "volume",
        "mass",
        "coverage",
        "level_min",
        "level_mean",
        "level_max",
        "valid",
        "degraded",
    )
    assert {k: cmps[k].get("expire_after") for k in readings} == dict.fromkeys(readings, 7800)


def test_invalid_or_stale_readings_do_not_show_as_a_normal_volume(
    broker, telemetry_factory, collector_factory
):
    """An invalid scan: volume, mass and levels render as HA's "None" (state unknown), the
    valid entity is off, and every reading carries the scan's identity and validity."""
    col = collector_factory(broker, [CONFIG, f"{BASE}/volume"])
    tel = telemetry_factory(broker, homeassistant={"enabled": True})
    cmps = json.loads(col.wait_topic(CONFIG)[0].payload)["cmps"]
    bad = summary(
        f"{SILO}-20261122T030000Z",
        valid=False,
        degraded=True,
        invalid_reason="coverage 12 % below the minimum",
        coverage=0.12,
    )
    tel.publish_result(summary())
    good_payload = col.wait_topic(f"{BASE}/volume")[0].payload
    tel.publish_result(bad)
    bad_payload = col.wait_topic(f"{BASE}/volume", 2)[1].payload

    def shown(payload: bytes) -> dict[str, str]:
        return {
            k: render(cmps[k]["value_template"], payload)
            for k in ("volume", "mass", "level_max", "coverage", "valid", "degraded", "last_scan")
        }

    assert shown(good_payload) == {
        "volume": "12.345",
        "mass": "9506.0",
        "level_max": "1.4",
        "coverage": "87.0",
        "valid": "ON",
        "degraded": "OFF",
        "last_scan": "2026-11-22T02:00:00.000Z",
    }
    assert shown(bad_payload) == {
        "volume": "None",
        "mass": "None",
        "level_max": "None",
        "coverage": "12.0",
        "valid": "OFF",
        "degraded": "ON",
        "last_scan": "2026-11-22T02:00:00.000Z",
    }
    attributes = json.loads(render(cmps["volume"]["json_attributes_template"], bad_payload))
    assert attributes == {
        "scan_id": f"{SILO}-20261122T030000Z",
        "captured_at": "2026-11-22T02:00:00.000Z",
        "valid": False,
        "degraded": True,
    }
    assert cmps["volume"]["json_attributes_topic"] == f"{BASE}/volume"


def test_expiry_follows_the_schedule_one_missed_scan_tolerated():
    """expire_after outlasts one failed scheduled scan but not two, whatever the schedule."""
    hourly = ScheduleConfig(interval_s=3600, scan_timeout_s=600)
    assert 2 * 3600 <= stale_after_s(hourly, "UTC") < 3 * 3600
    weekdays = ScheduleConfig(cron="0 6,18 * * 1-5")  # longest gap: Friday 18:00 to Monday 06:00
    assert 2 * 60 * 3600 <= stale_after_s(weekdays, "Europe/Berlin") < 3 * 60 * 3600
    assert stale_after_s(ScheduleConfig(), "UTC") is None  # on request only: nothing to expect


def test_every_alarm_state_is_retained_at_start_and_sent_again_when_ha_comes_online(
    broker, telemetry_factory, collector_factory
):
    topics = {f"{BASE}/alarm/{t}" for t in ALARM_TYPES}
    col = collector_factory(broker, [f"{BASE}/alarm/+"])
    tel = telemetry_factory(broker, homeassistant={"enabled": True}, start=False)
    raised = {
        "type": "collapse",
        "state": "raised",
        "severity": "critical",
        "scan_id": summary().scan_id,
        "message": "surface dropped",
        "depth_m": 0.4,
    }
    tel.restore_alarms(
        {"collapse": AlarmEvent.from_json(raised)}
    )  # what the agent persisted before a restart
    tel.start()
    col.wait_for(lambda ms: {m.topic for m in ms} >= topics)
    fresh = collector_factory(broker, [f"{BASE}/alarm/+"], client_id="fresh-ha")
    fresh.wait_for(lambda ms: {m.topic for m in ms if m.retain} >= topics)
    states = {m.topic.rsplit("/", 1)[1]: validate_json(m.payload) for m in fresh.messages}
    assert {t: s["state"] for t, s in states.items()} == {
        t: "raised" if t == "collapse" else "cleared" for t in ALARM_TYPES
    }
    assert states["collapse"]["depth_m"] == 0.4
    for t in ALARM_TYPES:  # HA's binary_sensor template on each
        on = render(
            "{{ 'ON' if value_json.state == 'raised' else 'OFF' }}", json.dumps(states[t]).encode()
        )
        assert on == ("ON" if t == "collapse" else "OFF")

    col.client.publish("homeassistant/status", b"online", qos=1)
    col.wait_for(lambda ms: all(sum(m.topic == t for m in ms) >= 2 for t in topics))


def test_no_discovery_without_home_assistant_even_for_a_new_alarm_type(
    broker, telemetry_factory, collector_factory
):
    col = collector_factory(broker, ["homeassistant/#", f"{BASE}/#"])
    tel = telemetry_factory(broker)
    tel.restore_alarms(
        {
            "silo_door": AlarmEvent(
                type="silo_door", state="raised", severity="warning", scan_id=None
            )
        }
    )
    tel.publish_alarm(
        AlarmEvent.from_json(
            {"type": "hopper", "state": "raised", "severity": "warning", "scan_id": None}
        )
    )
    col.wait_topic(f"{BASE}/alarm/hopper")
    col.wait_topic(f"{BASE}/alarm/silo_door")
    col.publish(f"{BASE}/cmd/scan", b"{}")  # a round trip through the agent, then look
    col.wait_topic(f"{BASE}/cmd/scan/reply")
    assert not [m for m in col.messages if m.topic.startswith("homeassistant/")]


def test_every_reading_carries_the_documented_attributes() -> None:
    """docs/mqtt.md: every reading from `P/volume` (Degraded and Last scan too) has the scan's
    `scan_id`, `captured_at`, `valid` and `degraded` as attributes, rendered as HA does."""
    from silo_agent.telemetry.homeassistant import discovery_config
    from silo_agent.telemetry.payloads import Envelope, volume_payload

    _topic, payload = discovery_config(
        discovery_prefix="homeassistant",
        base_topic=BASE,
        silo_id=SILO,
        version="9.9.9",
        alarm_types=ALARM_TYPES,
    )
    cmps = json.loads(payload)["cmps"]
    degraded = summary(degraded=True)
    volume = volume_payload(Envelope.new(5), degraded).to_bytes()
    readings = {k for k, c in cmps.items() if c["state_topic"] == f"{BASE}/volume"}
    assert {"volume", "mass", "coverage", "valid", "degraded", "last_scan"} <= readings
    for key in readings:
        assert cmps[key]["json_attributes_topic"] == f"{BASE}/volume", key
        attributes = json.loads(render(cmps[key]["json_attributes_template"], volume))
        assert attributes == {
            "scan_id": degraded.scan_id,
            "captured_at": degraded.captured_at,
            "valid": True,
            "degraded": True,
        }, key
