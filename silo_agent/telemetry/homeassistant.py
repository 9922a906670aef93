"""Home Assistant MQTT discovery, device-based (one config message for the whole silo).

Entities read the JSON topics the agent publishes anyway (`P/volume`, `P/alarm/<type>`),
so HA needs no extra state topics; availability follows the retained `P/status`. The config
is retained and republished whenever HA announces `online` on `<prefix>/status`, so a
restarted HA or a broker without persistence gets it back. Units and device classes are
ones HA accepts together (HA drops a sensor whose unit its device class does not know).
"""

from __future__ import annotations

import json
from collections.abc import Iterable

AVAILABILITY_TEMPLATE = "{{ 'online' if value_json.state == 'online' else 'offline' }}"


def status_topic(discovery_prefix: str) -> str:
    return f"{discovery_prefix}/status"


def discovery_topic(discovery_prefix: str, silo_id: str) -> str:
    return f"{discovery_prefix}/device/silo_agent_{silo_id}/config"


# a reading of an invalid scan renders as "None", which HA's MQTT sensor takes for unknown
# (PAYLOAD_NONE): the entity shows no number instead of a wrong one
def _when_valid(expression: str) -> str:
    return f"{{{{ ({expression}) if value_json.valid else None }}}}"


# scan identity and validity, as attributes of every reading from P/volume
READING_ATTRIBUTES = (
    '{{ {"scan_id": value_json.scan_id, "captured_at": value_json.captured_at, '
    '"valid": value_json.valid, "degraded": value_json.degraded} | tojson }}'
)


def _reading(
    uid: str,
    name: str,
    template: str,
    unit: str | None,
    device_class: str | None,
    state: str,
    expire_after_s: int | None,
) -> dict:
    """A measurement sensor on P/volume (`discovery_config` adds the scan's identity as
    attributes, as to every reading)."""
    component: dict = {
        "p": "sensor",
        "name": name,
        "unique_id": uid,
        "state_topic": state,
        "value_template": template,
        "state_class": "measurement",
    }
    if unit:
        component["unit_of_measurement"] = unit
    if device_class:
        component["device_class"] = device_class
    if expire_after_s:
        component["expire_after"] = expire_after_s
    return component


def discovery_config(
    *,
    discovery_prefix: str,
    base_topic: str,
    silo_id: str,
    version: str,
    alarm_types: Iterable[str],
    expire_after_s: int | None = None,
) -> tuple[str, bytes]:
    """(topic, retained payload) of the device discovery message. `expire_after_s`: readings
    turn unavailable in HA when no new one came for that long."""
    volume = f"{base_topic}/volume"
    uid = f"silo_agent_{silo_id}"
    components = {
        "volume": _reading(
            f"{uid}_volume",
            "Volume",
            _when_valid("value_json.volume_m3"),
            "m³",
            "volume_storage",
            volume,
            expire_after_s,
        ),
        # HA's weight class has no tonne: kilograms, from the payload's mass_t
        "mass": _reading(
            f"{uid}_mass",
            "Mass",
            _when_valid(
                "(value_json.mass_t * 1000) | round(1) if value_json.mass_t is not none else None"
            ),
            "kg",
            "weight",
            volume,
            expire_after_s,
        ),
        "coverage": _reading(
            f"{uid}_coverage",
            "Coverage",
            "{{ (value_json.coverage * 100) | round(1) }}",
            "%",
            None,
            volume,
            expire_after_s,
        ),
        "valid": {
            "p": "binary_sensor",
            "name": "Reading valid",
            "unique_id": f"{uid}_valid",
            "state_topic": volume,
            "value_template": "{{ 'ON' if value_json.valid else 'OFF' }}",
            "entity_category": "diagnostic",
        },
        "degraded": {
            "p": "binary_sensor",
            "name": "Degraded",
            "unique_id": f"{uid}_degraded",
            "device_class": "problem",
            "state_topic": volume,
            "value_template": "{{ 'ON' if value_json.degraded else 'OFF' }}",
            "entity_category": "diagnostic",
        },
        "last_scan": {
            "p": "sensor",
            "name": "Last scan",
            "unique_id": f"{uid}_last_scan",
            "device_class": "timestamp",
            "state_topic": volume,
            "value_template": "{{ value_json.captured_at }}",
            "entity_category": "diagnostic",
        },
    }
    if expire_after_s:
        for key in ("valid", "degraded"):
            components[key]["expire_after"] = expire_after_s
    components["fill"] = _reading(
        f"{uid}_fill",
        "Fill",
        _when_valid(
            "(value_json.fill_ratio * 100) | round(1) "
            "if value_json.fill_ratio is not none else None"
        ),
        "%",
        None,
        volume,
        expire_after_s,
    )
    components["headspace"] = _reading(
        f"{uid}_headspace",
        "Headspace",
        _when_valid("value_json.headspace_m"),
        "m",
        "distance",
        volume,
        expire_after_s,
    )
    for key in ("min", "mean", "max"):
        components[f"level_{key}"] = _reading(
            f"{uid}_level_{key}",
            f"Level {key}",
            _when_valid(f"value_json.level.{key}"),
            "m",
            "distance",
            volume,
            expire_after_s,
        )
    for component in components.values():  # every reading says which scan it is from
        if component["state_topic"] == volume:
            component["json_attributes_topic"] = volume
            component["json_attributes_template"] = READING_ATTRIBUTES
    for alarm_type in alarm_types:
        components[f"alarm_{alarm_type}"] = {
            "p": "binary_sensor",
            "name": f"Alarm {alarm_type.replace('_', ' ')}",
            "unique_id": f"{uid}_alarm_{alarm_type}",
            "device_class": "problem",
            "state_topic": f"{base_topic}/alarm/{alarm_type}",
            "value_template": "{{ 'ON' if value_json.state == 'raised' else 'OFF' }}",
        }
    config = {
        "dev": {
            "ids": [uid],
            "name": f"Silo {silo_id}",
            "mf": "silo-agent",
            "mdl": "RealSense grain silo scanner",
            "sw": version,
        },
        "o": {"name": "silo-agent", "sw": version},
        "availability": [
            {
                "topic": f"{base_topic}/status",
                "value_template": AVAILABILITY_TEMPLATE,
                "payload_available": "online",
                "payload_not_available": "offline",
            }
        ],
        "qos": 1,
        "cmps": components,
    }
    return discovery_topic(discovery_prefix, silo_id), json.dumps(config).encode()
