"""Every topic of the contract through a real mosquitto, payloads checked against the schemas."""

from __future__ import annotations

import json

import numpy as np
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from silo_agent.analysis.alarm_types import AlarmEvent
from silo_agent.telemetry.client import CommandRejected, ScanCommand
from silo_agent.telemetry.heightmap_codec import decode_heightmap_with_ids, encode_heightmap
from tests.support.mqtt import BASE, realistic_heightmap, summary, validate_json


def test_every_topic_round_trips(broker, telemetry_factory, collector_factory):
    col = collector_factory(broker, [f"{BASE}/#"])
    tel = telemetry_factory(broker)
    commands: list[ScanCommand] = []
    tel.on_scan_request(commands.append)

    status = validate_json(col.wait_topic(f"{BASE}/status")[-1].payload)
    assert status["state"] == "online"
    assert status["version"] == "9.9.9"
    assert [c["serial"] for c in status["cameras"]] == ["cam-a", "cam-b"]

    hm = realistic_heightmap()
    result = summary()
    tel.publish_result(result, hm)
    tel.publish_alarm(
        AlarmEvent.from_json(
            {
                "type": "collapse",
                "state": "raised",
                "severity": "critical",
                "scan_id": result.scan_id,
                "message": "surface dropped",
                "position": [0.4, -1.2],
                "area_m2": 0.35,
                "depth_m": 0.22,
            }
        )
    )
    tel.set_status(cameras={"cam-b": ("failed", "usb timeout")}, last_scan_id=result.scan_id)

    scan = validate_json(col.wait_topic(f"{BASE}/scan")[0].payload)
    assert scan["cameras"]["failed"] == [{"serial": "cam-b", "error": "timeout"}]
    assert scan["timings"] == {"capture_s": 4.2, "reconstruct_s": 1.3}
    volume_msg = col.wait_topic(f"{BASE}/volume")[0]
    volume = validate_json(volume_msg.payload)
    assert (volume["volume_m3"], volume["mass_t"], volume["level"]["max"]) == (12.345, 9.506, 1.4)
    assert volume["scan_id"] == result.scan_id
    assert volume_msg.properties.UserProperty == [
        ("msg_id", volume["msg_id"]),
        ("seq", str(volume["seq"])),
    ]

    blob = col.wait_topic(f"{BASE}/heightmap")[0].payload
    assert blob == encode_heightmap(hm, result.scan_id)
    decoded, scan_id, frame = decode_heightmap_with_ids(blob)
    assert (scan_id, frame) == (result.scan_id, "silo")
    assert np.nanmax(np.abs(decoded.heights - hm.heights)) <= 0.0005 + 1e-9
    assert np.array_equal(np.isnan(decoded.heights), np.isnan(hm.heights))
    assert np.array_equal(decoded.observed, hm.observed)

    event = validate_json(col.wait_topic(f"{BASE}/alarm")[0].payload)
    # the state published at connect (not raised), then the raised one
    current = validate_json(col.wait_topic(f"{BASE}/alarm/collapse", 2)[-1].payload)
    assert event["position"] == [0.4, -1.2] and event["depth_m"] == 0.22
    assert current["state"] == "raised" and current["msg_id"] != event["msg_id"]

    col.wait_for(
        lambda ms: any(
            m.topic == f"{BASE}/status"
            and json.loads(m.payload)["last_scan_id"] == result.scan_id
            and json.loads(m.payload)["cameras"][1]["state"] == "failed"
            for m in ms
        )
    )

    # command with MQTT 5 response topic + correlation data
    props = Properties(PacketTypes.PUBLISH)
    props.ResponseTopic = "test/replies"
    props.CorrelationData = b"corr-1"
    col.client.subscribe("test/replies", 1)
    col.publish(f"{BASE}/cmd/scan", json.dumps({"request_id": "r-1"}).encode(), props)
    reply_msg = col.wait_topic("test/replies")[0]
    reply = validate_json(reply_msg.payload)
    assert reply["request_id"] == "r-1" and reply["accepted"] and reply["status"] == "accepted"
    assert reply_msg.properties.CorrelationData == b"corr-1"
    assert commands == [ScanCommand("r-1", "test/replies", b"corr-1")]
    tel.finish_scan_request(commands[0], scan_id="silo-t-later")
    done = validate_json(col.wait_topic("test/replies", 2)[1].payload)
    assert (done["status"], done["scan_id"], done["request_id"]) == ("done", "silo-t-later", "r-1")

    # without a response topic the reply goes to P/cmd/scan/reply; a refusal is an error reply
    def busy(_cmd: ScanCommand) -> None:
        raise CommandRejected("a scan is already running")

    tel.on_scan_request(busy)
    col.publish(f"{BASE}/cmd/scan", b'{"request_id": "r-2"}')
    refused = validate_json(col.wait_topic(f"{BASE}/cmd/scan/reply")[0].payload)
    assert refused == {
        **refused,
        "request_id": "r-2",
        "accepted": False,
        "error": "a scan is already running",
    }

    seqs = [
        validate_json(m.payload)["seq"]
        for m in col.messages
        if m.topic not in (f"{BASE}/heightmap", f"{BASE}/cmd/scan")
    ]
    assert len(set(seqs)) == len(seqs)

    tel.stop()
    col.wait_for(
        lambda ms: (
            json.loads([m for m in ms if m.topic == f"{BASE}/status"][-1].payload)["state"]
            == "stopped"
        )
    )
    assert tel.outbox.path.exists()


def test_late_joiners_get_the_retained_map_volume_and_status(
    broker, telemetry_factory, collector_factory
):
    tel = telemetry_factory(broker)
    hm = realistic_heightmap(rows=60, cols=80)
    tel.publish_result(summary(), hm)
    first = collector_factory(broker, [f"{BASE}/heightmap"], client_id="first")
    first.wait_topic(f"{BASE}/heightmap")
    tel.stop()
    late = collector_factory(broker, [f"{BASE}/#"], client_id="late")
    retained = late.wait_topic(f"{BASE}/heightmap")[0]
    assert retained.retain and retained.payload == encode_heightmap(hm, summary().scan_id)
    assert late.wait_topic(f"{BASE}/volume")[0].retain
    status = late.wait_topic(f"{BASE}/status")[0]
    assert status.retain and validate_json(status.payload)["state"] == "stopped"
    assert not late.on(f"{BASE}/scan")


def test_mqtt_3_1_1_replies_on_the_reply_topic(broker, telemetry_factory, collector_factory):
    col = collector_factory(broker, [f"{BASE}/#"])
    tel = telemetry_factory(broker, protocol="3.1.1")
    tel.on_scan_request(lambda cmd: None)
    assert validate_json(col.wait_topic(f"{BASE}/status")[-1].payload)["state"] == "online"
    tel.publish_result(summary())
    assert validate_json(col.wait_topic(f"{BASE}/scan")[0].payload)["valid"] is True
    col.publish(f"{BASE}/cmd/scan", b'{"request_id": "v311"}')
    reply = validate_json(col.wait_topic(f"{BASE}/cmd/scan/reply")[0].payload)
    assert (reply["request_id"], reply["accepted"]) == ("v311", True)
