"""Home Assistant MQTT discovery, device-based (one config message for the whole silo).

Entities read the JSON topics the agent publishes anyway (`P/volume`, `P/alarm/<type>`),
so HA needs no extra state topics; availability follows the retained `P/status`. The config
is retained and republished whenever HA announces `online` on `<prefix>/status`, so a
restarted HA or a broker without persistence gets it back.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

AVAILABILITY_TEMPLATE = "{{ 'online' if value_json.state == 'online' else 'offline' }}"


def status_topic(discovery_prefix: str) -> str:
    return f"{discovery_prefix}/status"


def discovery_topic(discovery_prefix: str, silo_id: str) -> str:
    return f"{discovery_prefix}/device/silo_agent_{silo_id}/config"


def _sensor(
    uid: str, name: str, template: str, unit: str | None, device_class: str | None, state: str
) -> dict:
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
    return component


def discovery_config(
    *,
    discovery_prefix: str,
    base_topic: str,
    silo_id: str,
    version: str,
    alarm_types: Iterable[str],
) -> tuple[str, bytes]:
    """(topic, retained payload) of the device discovery message."""
    volume = f"{base_topic}/volume"
    uid = f"silo_agent_{silo_id}"
    components = {
        "volume": _sensor(
            f"{uid}_volume", "Volume", "{{ value_json.volume_m3 }}", "m³", "volume_storage", volume
        ),
        "mass": _sensor(
            f"{uid}_mass", "Mass", "{{ value_json.mass_t }}", "t", "weight", volume
        ),
        "coverage": _sensor(
            f"{uid}_coverage", "Coverage", "{{ (value_json.coverage * 100) | round(1) }}", "%",
            None, volume,
        ),
    }
    for key in ("min", "mean", "max"):
        components[f"level_{key}"] = _sensor(
            f"{uid}_level_{key}", f"Level {key}", f"{{{{ value_json.level.{key} }}}}", "m",
            "distance", volume,
        )
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
