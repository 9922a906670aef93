"""Hostile commands and unlucky sites against the MQTT side, each through a real mosquitto:
no command, refused message or damaged outbox may stop telemetry or crash the agent."""

from __future__ import annotations

import json
import socket
import sqlite3
import time

import pytest
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from structlog.testing import capture_logs

from silo_agent.telemetry.client import POISON_STRIKES, Telemetry, reply_topic_problem
from silo_agent.telemetry.outbox import Outbox
from tests.support.mqtt import BASE, SILO, mqtt_config, realistic_heightmap, summary, validate_json
from tests.support.mqtt_broker import Broker

FALLBACK = f"{BASE}/cmd/scan/reply"


@pytest.fixture
def agent(broker, telemetry_factory, collector_factory):
    """A running agent that records accepted scan requests, and a collector on its topics."""
    tel = telemetry_factory(broker)
    accepted: list[str] = []
    tel.on_scan_request(lambda cmd: accepted.append(cmd.request_id))
    col = collector_factory(broker, [f"{BASE}/#", "x/#"])
    col.wait_topic(f"{BASE}/status")
    return tel, col, accepted


def command(col, request_id: str, response_topic: str, correlation: bytes) -> None:
    props = Properties(PacketTypes.PUBLISH)
    props.ResponseTopic = response_topic
    props.CorrelationData = correlation
    col.publish(f"{BASE}/cmd/scan", json.dumps({"request_id": request_id}).encode(), props)


def reply_to(col, correlation: bytes, topic: str = FALLBACK) -> dict:
    col.wait_for(
        lambda ms: any(m.topic == topic and m.properties.CorrelationData == correlation for m in ms)
    )
    (reply,) = [m for m in col.on(topic) if m.properties.CorrelationData == correlation]
    return validate_json(reply.payload)


def barrier(col) -> None:
    """Until the agent answered a bad request sent now: what it sent before has arrived
    (one client's messages arrive in order)."""
    correlation = f"barrier-{time.monotonic_ns()}".encode()
    props = Properties(PacketTypes.PUBLISH)
    props.ResponseTopic = FALLBACK
    props.CorrelationData = correlation
    col.publish(f"{BASE}/cmd/scan", b"{not json", props)
    assert reply_to(col, correlation)["status"] == "error"


def published_after_it(tel: Telemetry, col) -> None:
    """A result queued now still reaches the broker: nothing blocks the outbox."""
    tel.publish_result(summary(f"{SILO}-after"), realistic_heightmap(60, 80))
    col.wait_for(
        lambda ms: any(
            m.topic == f"{BASE}/scan" and json.loads(m.payload)["scan_id"] == f"{SILO}-after"
            for m in ms
        )
    )


@pytest.mark.parametrize("response_topic", ["x/replies/#", "x/+/r", "$SYS/replies"])
def test_unpublishable_response_topic_gets_an_error_on_the_fallback(agent, response_topic):
    tel, col, accepted = agent
    command(col, "r-wild", response_topic, b"c-wild")
    reply = reply_to(col, b"c-wild")
    assert reply["status"] == "error" and reply["request_id"] == "r-wild"
    assert "response topic" in reply["error"] and response_topic in reply["error"]
    assert accepted == []
    published_after_it(tel, col)
    assert tel.outbox.counter("dead_lettered") == 0  # refused on receipt, never queued


@pytest.mark.parametrize("suffix", ["status", "volume", "alarm/collapse", "cmd/scan"])
def test_response_topic_on_the_agents_own_topics_is_refused(agent, suffix):
    _, col, accepted = agent
    own = f"{BASE}/{suffix}"
    command(col, "r-own", own, b"c-own")
    reply = reply_to(col, b"c-own")
    assert reply["status"] == "error" and "under silo/" in reply["error"]
    assert accepted == []
    barrier(col)
    assert not [m for m in col.on(own) if b"silo-cmd-reply/1" in m.payload]


def test_the_documented_reply_topic_and_a_foreign_one_are_accepted(agent):
    _, col, accepted = agent
    command(col, "r-doc", FALLBACK, b"c-doc")
    assert reply_to(col, b"c-doc")["status"] == "accepted"
    command(col, "r-x", "x/replies/r-x", b"c-x")
    assert reply_to(col, b"c-x", "x/replies/r-x")["status"] == "accepted"
    assert accepted == ["r-doc", "r-x"]


def test_reply_topic_rules():
    reserved = ["silo", "spBv1.0", "homeassistant"]
    allowed = "silo/s1/cmd/scan/reply"
    assert reply_topic_problem(allowed, reserved, allowed) is None
    assert reply_topic_problem("ops/replies/7", reserved, allowed) is None
    assert "wildcard" in reply_topic_problem("a/#", reserved, allowed)
    assert "$" in reply_topic_problem("$share/g/a", reserved, allowed)
    assert "NUL" in reply_topic_problem("a\x00b", reserved, allowed)
    assert "UTF-8" in reply_topic_problem("a\udcffb", reserved, allowed)
    assert "65535" in reply_topic_problem("a" * 65536, reserved, allowed)
    assert "empty" in reply_topic_problem("", reserved, allowed)
    assert "spBv1.0/" in reply_topic_problem("spBv1.0/silos/NDATA/s1", reserved, allowed)
    assert "silo/" in reply_topic_problem("silo/s2/volume", reserved, allowed)
    assert reply_topic_problem("silos/x", reserved, allowed) is None  # a prefix, not a level


def test_a_row_paho_refuses_is_dead_lettered_and_the_rest_flows(agent):
    tel, col, _ = agent
    tel.outbox.enqueue("x/replies/#", lambda env: b'{"poison": true}')
    published_after_it(tel, col)
    assert tel.outbox.counter("dead_lettered") == 1
    ((row, reason),) = tel.outbox.dead_letters()
    assert row.topic == "x/replies/#" and row.payload == b'{"poison": true}'
    assert "wildcard" in reason
    col.wait_for(
        lambda ms: any(
            m.topic == f"{BASE}/status" and json.loads(m.payload)["outbox"]["dead_lettered"] == 1
            for m in ms
        )
    )


def test_dead_letters_survive_a_restart_and_are_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr("silo_agent.telemetry.outbox.DEAD_LETTER_KEEP", 3)
    box = Outbox(tmp_path / "outbox.sqlite")
    for i in range(5):
        box.enqueue(f"t/{i}", lambda env: b"x")
    for row in box.pending():
        box.dead_letter(row.id, "test")
    box.close()
    again = Outbox(tmp_path / "outbox.sqlite")
    assert again.pending() == []
    assert [r.topic for r, _ in again.dead_letters()] == ["t/2", "t/3", "t/4"]
    assert again.counter("dead_lettered") == 5


@pytest.mark.broker  # starts its own mosquitto
def test_oversize_message_is_dead_lettered_not_retried(
    tmp_path, telemetry_factory, collector_factory
):
    broker = Broker(tmp_path / "small-broker", extra=("max_packet_size 20000",)).start()
    try:
        tel = telemetry_factory(broker)
        col = collector_factory(broker, [f"{BASE}/#"])
        col.wait_topic(f"{BASE}/status")
        # a 300 x 400 map is ~100 kB, far over 20000 bytes; scan and volume are small
        tel.publish_result(summary(), realistic_heightmap())
        col.wait_topic(f"{BASE}/volume")
        col.wait_for(
            lambda ms: any(
                m.topic == f"{BASE}/status"
                and json.loads(m.payload)["outbox"]["dead_lettered"] == 1
                for m in ms
            )
        )
        published_after_it(tel, col)  # with a small map (~5 kB), which goes through
        (small,) = col.wait_topic(f"{BASE}/heightmap")
        assert f"{SILO}-after".encode() in small.payload
        ((row, reason),) = tel.outbox.dead_letters()
        assert row.topic == f"{BASE}/heightmap" and "20000" in reason
        assert broker.log().count(f"as {tel.client_id} ") == 1  # never reconnected
    finally:
        broker.stop()


@pytest.mark.broker  # starts its own mosquitto
def test_message_the_broker_drops_the_connection_over_is_dead_lettered(
    tmp_path, telemetry_factory, collector_factory
):
    """MQTT 3.1.1 has no Maximum Packet Size in CONNACK: mosquitto closes the connection at
    every attempt. The agent then sends one message at a time; the one in flight when
    POISON_STRIKES such sessions in a row ended goes, not the volume sent before it."""
    broker = Broker(tmp_path / "small-broker", extra=("max_packet_size 20000",)).start()
    try:
        tel = telemetry_factory(broker, protocol="3.1.1")
        col = collector_factory(broker, [f"{BASE}/#"])
        col.wait_topic(f"{BASE}/status")
        tel.publish_result(summary(), realistic_heightmap())
        end = time.monotonic() + 15
        while not tel.outbox.dead_letters() and time.monotonic() < end:
            time.sleep(0.05)
        ((row, reason),) = tel.outbox.dead_letters()
        assert row.topic == f"{BASE}/heightmap" and "closed the connection" in reason
        published_after_it(tel, col)
        # the first session (all three sent at once), the probing ones, the healthy one now
        sessions = broker.log().count(f"as {tel.client_id} ")
        assert sessions == 1 + POISON_STRIKES + 1
        assert col.on(f"{BASE}/volume")  # the volume got through, it was not the culprit
        published_after_it(tel, col)  # the healthy session carries on: no more sessions
        assert broker.log().count(f"as {tel.client_id} ") == sessions
    finally:
        broker.stop()


def test_retained_command_does_not_scan_at_start(broker, telemetry_factory, collector_factory):
    col = collector_factory(broker, [f"{BASE}/#"])
    col.client.publish(
        f"{BASE}/cmd/scan", b'{"request_id": "stale"}', qos=1, retain=True
    ).wait_for_publish(5)
    tel = telemetry_factory(broker, start=False)
    accepted: list[str] = []
    tel.on_scan_request(lambda cmd: accepted.append(cmd.request_id))
    tel.start()
    col.wait_for(
        lambda ms: any(
            m.topic == f"{BASE}/status" and json.loads(m.payload)["state"] == "online" for m in ms
        )
    )
    # a live command after it is taken: the subscription works, the retained one was skipped
    col.publish(f"{BASE}/cmd/scan", b'{"request_id": "live"}')
    col.wait_topic(FALLBACK)
    assert accepted == ["live"]
    replies = [json.loads(m.payload) for m in col.on(FALLBACK)]
    assert [r["request_id"] for r in replies] == ["live"]


@pytest.mark.parametrize("response_topic", ["x/replies/#", f"{BASE}/status"])
def test_live_command_response_topic_is_checked_like_the_scan_commands(
    broker, telemetry_factory, collector_factory, response_topic
):
    tel = telemetry_factory(broker)
    started: list[object] = []
    tel.on_live_command(lambda cmd: started.append(cmd) or "live-1")
    col = collector_factory(broker, [f"{BASE}/#", "x/#"])
    col.wait_topic(f"{BASE}/status")
    props = Properties(PacketTypes.PUBLISH)
    props.ResponseTopic = response_topic
    props.CorrelationData = b"c-live"
    col.publish(f"{BASE}/cmd/live", b'{"on": true}', props)
    reply = reply_to(col, b"c-live", f"{BASE}/cmd/live/reply")
    assert reply["status"] == "error" and "response topic" in reply["error"]
    assert started == []
    barrier(col)
    assert not [m for m in col.on(f"{BASE}/status") if b"silo-cmd-reply/1" in m.payload]


def test_retained_live_command_is_ignored_at_start(broker, telemetry_factory, collector_factory):
    col = collector_factory(broker, [f"{BASE}/#"])
    col.client.publish(f"{BASE}/cmd/live", b'{"on": true}', qos=1, retain=True).wait_for_publish(5)
    tel = telemetry_factory(broker, start=False)
    started: list[object] = []
    tel.on_live_command(lambda cmd: started.append(cmd) or "live-1")
    tel.start()
    col.wait_for(
        lambda ms: any(
            m.topic == f"{BASE}/status" and json.loads(m.payload)["state"] == "online" for m in ms
        )
    )
    col.publish(f"{BASE}/cmd/live", b'{"on": true, "request_id": "now"}')
    col.wait_topic(f"{BASE}/cmd/live/reply")
    assert len(started) == 1
    replies = [json.loads(m.payload) for m in col.on(f"{BASE}/cmd/live/reply")]
    assert [r["request_id"] for r in replies] == ["now"]


def statuses(col) -> list[dict]:
    return [json.loads(m.payload) for m in col.on(f"{BASE}/status")]


def cut_the_connection(tel: Telemetry) -> None:
    """Drop the agent's TCP connection without an MQTT DISCONNECT: the broker sends the will."""
    tel._links[0].client.socket().shutdown(socket.SHUT_RDWR)


def assert_offline_sorts_right(col) -> int:
    """Each `offline` (the Last Will) has a seq above every message delivered before it, and
    the `online` of the next session one above it; returns how many offlines there were."""
    delivered = [
        json.loads(m.payload)
        for m in col.messages
        if m.topic.startswith(BASE) and m.payload.startswith(b"{")
    ]
    offlines = [
        i
        for i, d in enumerate(delivered)
        if d["schema"] == "silo-status/1" and d["state"] == "offline"
    ]
    for i in offlines:
        assert delivered[i]["seq"] > max(d["seq"] for d in delivered[:i])
        next_online = next(d for d in delivered[i:] if d.get("state") == "online")
        assert next_online["seq"] > delivered[i]["seq"]
    return len(offlines)


def test_last_will_sorts_after_the_session_and_before_the_next(agent):
    tel, col, _ = agent
    tel.publish_result(summary(f"{SILO}-before"))
    col.wait_topic(f"{BASE}/volume")
    cut_the_connection(tel)
    col.wait_for(lambda ms: [s["state"] for s in statuses(col)][-2:] == ["offline", "online"])
    assert assert_offline_sorts_right(col) == 1


def test_last_will_seq_is_re_armed_before_the_session_reaches_it(
    broker, telemetry_factory, collector_factory, monkeypatch
):
    monkeypatch.setattr("silo_agent.telemetry.client.WILL_SEQ_HEADROOM", 40)
    monkeypatch.setattr("silo_agent.telemetry.outbox.WILL_SEQ_HEADROOM", 40)
    tel = telemetry_factory(broker)
    col = collector_factory(broker, [f"{BASE}/#"])
    col.wait_topic(f"{BASE}/status")
    for i in range(30):  # 60 seq values from a will at seq 40: the session must re-arm
        tel.publish_result(summary(f"{SILO}-{i:02d}"))
    every_scan = {f"{SILO}-{i:02d}" for i in range(30)}
    col.wait_for(
        lambda ms: (
            every_scan
            == {json.loads(m.payload)["scan_id"] for m in ms if m.topic == f"{BASE}/scan"}
        )
    )
    cut_the_connection(tel)
    col.wait_for(lambda ms: [s["state"] for s in statuses(col)][-2:] == ["offline", "online"])
    # without the re-arm the last offline would carry the first will's seq (40) and sort
    # before the scans (up to ~70); a re-arm may itself leave an offline, or disconnect cleanly
    assert assert_offline_sorts_right(col) >= 1


# ---------------------------------------------------------------- a damaged outbox


def fill(path, count: int) -> list[int]:
    box = Outbox(path)
    seqs = [box.enqueue("t/a", lambda env: b"x").seq for _ in range(count)]
    box.advance_bd_seq()
    box.advance_bd_seq()
    box.close()
    return seqs


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty"])
def test_corrupt_outbox_is_moved_aside_and_seq_continues(tmp_path, damage):
    path = tmp_path / "outbox.sqlite"
    seqs = fill(path, 5)
    if damage == "garbage":
        path.write_bytes(b"\xde\xad\xbe\xef not a database " * 200)
    elif damage == "truncated":
        with sqlite3.connect(path) as db:  # enough pages that a cut loses some of them
            db.execute("CREATE TABLE filler (x BLOB)")
            db.executemany("INSERT INTO filler VALUES (?)", [(b"f" * 3000,)] * 50)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        path.write_bytes(b"")
    with capture_logs() as logs:
        box = Outbox(path)
    assert box.next_envelope().seq > seqs[-1]
    assert box.bd_seq() == 2
    if damage != "empty":  # an empty file is a valid (empty) database
        aside = box.moved_aside
        assert aside is not None and aside.exists()
        assert aside.name.startswith("outbox.sqlite.corrupt-")
        (entry,) = [e for e in logs if e["log_level"] == "error"]
        assert entry["path"] == str(path) and entry["moved_to"] == str(aside)
    box.enqueue("t/b", lambda env: b"y")
    assert [r.topic for r in box.pending()] == ["t/b"]


def test_corrupt_outbox_starts_the_agent_with_an_alarm(broker, tmp_path, collector_factory):
    cfg = mqtt_config(broker, tmp_path)
    seqs = fill(cfg.outbox_path, 3)
    cfg.outbox_path.write_bytes(b"garbage" * 100)
    col = collector_factory(broker, [f"{BASE}/#"])
    tel = Telemetry(cfg, SILO, ["cam-a"])
    tel.start()
    try:
        # the event's retained state, and the state every connection announces: both raised
        topic = f"{BASE}/alarm/outbox"
        col.wait_for(lambda ms: any(m.topic == topic for m in ms))
        docs = [validate_json(m.payload) for m in col.on(topic)]
        for doc in docs:
            assert doc["state"] == "raised" and "corrupt" in doc["message"]
            assert tel.outbox.moved_aside.name in doc["message"]
        online = [json.loads(m.payload) for m in col.on(f"{BASE}/status")]
        assert min(s["seq"] for s in online) > seqs[-1]
    finally:
        tel.stop()


def test_outbox_alarm_clears_once_the_corrupt_copy_is_removed(tmp_path):
    path = tmp_path / "outbox.sqlite"
    fill(path, 2)
    path.write_bytes(b"garbage" * 100)
    box = Outbox(path)
    assert box.corrupt_alarm_change() == "raised"
    box.close()
    again = Outbox(path)  # the copy is still there: the alarm stays, nothing new is said
    assert again.corrupt_alarm_change() is None
    again.close()
    box.moved_aside.unlink()
    cleared = Outbox(path)
    assert cleared.corrupt_alarm_change() == "cleared"
    cleared.close()
    assert Outbox(path).corrupt_alarm_change() is None
