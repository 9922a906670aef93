"""The MQTT side in parts that depend on each other one way: the transport (connections, the
pump, the link state) knows nothing of the commands, the session messages or the `Telemetry`
facade, which hand it callbacks instead; and the command dispatcher answers without any
connection."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import paho.mqtt.client as mqtt

import silo_agent.telemetry
from silo_agent.config import MqttConfig
from silo_agent.telemetry import sparkplug
from silo_agent.telemetry.commands import Commands, ScanCommand, SessionCallbacks
from silo_agent.telemetry.link import JSON_LINK, KIND_JSON, Link
from silo_agent.telemetry.outbox import Outbox
from tests.support.mqtt import BASE, SILO

TELEMETRY = Path(silo_agent.telemetry.__file__).parent
TRANSPORT = {"link", "pump", "transport"}  # the network side, bottom up
ON_TOP = {"commands", "mqtt_session", "client"}


def telemetry_imports(module: str) -> set[str]:
    """The modules of silo_agent.telemetry that `module` of it imports, anywhere in it."""
    tree = ast.parse((TELEMETRY / f"{module}.py").read_text())
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "silo_agent.telemetry":
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith(
            "silo_agent.telemetry."
        ):
            found.add((node.module or "").rpartition(".")[2])
    return found


def test_the_transport_imports_nothing_that_runs_on_top_of_it() -> None:
    for module in sorted(TRANSPORT):
        assert not telemetry_imports(module) & ON_TOP, module
    assert "link" in telemetry_imports("pump") and "pump" in telemetry_imports("transport")


def test_commands_and_session_know_neither_each_other_nor_the_facade() -> None:
    assert not telemetry_imports("commands") & {"mqtt_session", "client", "transport"}
    assert not telemetry_imports("mqtt_session") & {"commands", "client", "transport"}
    assert {"commands", "mqtt_session", "transport"} <= telemetry_imports("client")


def message(topic: str, payload: bytes) -> mqtt.MQTTMessage:
    msg = mqtt.MQTTMessage(topic=topic.encode())
    msg.payload = payload
    return msg


def test_commands_answer_and_route_without_a_connection(tmp_path: Path) -> None:
    cfg = MqttConfig.model_validate(
        {
            "outbox_path": tmp_path / "outbox.sqlite",
            "homeassistant": {"enabled": True},
            "sparkplug": {"enabled": True, "primary_host_id": "scada"},
        }
    )
    outbox = Outbox(cfg.outbox_path)
    events: list[object] = []
    commands = Commands(
        cfg,
        BASE,
        sparkplug.Topics("silos", SILO),
        outbox,
        SessionCallbacks(
            homeassistant_online=lambda: events.append("ha online"),
            rebirth_requested=lambda: events.append("rebirth"),
            host_state=lambda link, online, stamp: events.append((link.name, online, stamp)),
        ),
    )
    accepted: list[ScanCommand] = []
    commands.on_scan_request(accepted.append)
    link = Link(JSON_LINK, (KIND_JSON,))
    commands.dispatch(link, message(f"{BASE}/cmd/scan", b'{"request_id": "r1"}'))
    commands.dispatch(link, message(f"{BASE}/cmd/scan", b"not json"))
    commands.dispatch(link, message(f"{BASE}/cmd/live", b'{"on": true, "request_id": "l1"}'))
    commands.dispatch(link, message("homeassistant/status", b"online"))
    commands.dispatch(link, message("spBv1.0/STATE/scada", b'{"online": true, "timestamp": 7}'))
    commands.dispatch(link, message("spBv1.0/STATE/scada", b"{broken"))

    assert [c.request_id for c in accepted] == ["r1"]
    assert events == ["ha online", (JSON_LINK, True, 7)]
    rows = outbox.pending()
    replies = [(row.topic, json.loads(row.payload)) for row in rows]
    assert [(topic, r["request_id"], r["status"]) for topic, r in replies] == [
        (f"{BASE}/cmd/scan/reply", "r1", "accepted"),
        (f"{BASE}/cmd/scan/reply", None, "error"),
        (f"{BASE}/cmd/live/reply", "l1", "error"),  # no live callback: this agent has none
    ]
    assert replies[1][1]["error"].startswith("invalid JSON")
    assert replies[2][1]["error"] == "this agent does not run live sessions"
    outbox.close()
