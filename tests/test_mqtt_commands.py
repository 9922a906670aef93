"""`P/cmd/scan` with hostile input: every request gets exactly one reply, the agent lives on."""

from __future__ import annotations

import itertools
import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from silo_agent.base.limits import MAX_COMMAND_BYTES
from tests.support.mqtt import BASE, validate_json

REPLIES = "fuzz/replies"

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=10,
)
requests = st.one_of(
    st.binary(min_size=1, max_size=200),  # empty: a retained command cleared, no command
    json_values.map(lambda v: json.dumps(v).encode()),
    st.dictionaries(
        st.sampled_from(["request_id", "requestId", "extra", "priority"]),
        json_values | st.text(min_size=0, max_size=200),
        max_size=3,
    ).map(lambda v: json.dumps(v).encode()),
    st.text(min_size=1, max_size=40).map(lambda r: json.dumps({"request_id": r}).encode()),
)


def expected_error(raw: bytes) -> str | None:
    """What the reply must complain about, or None if the request is valid."""
    if len(raw) > MAX_COMMAND_BYTES:
        return "too large"
    try:
        body = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        return "UTF-8"
    except ValueError:
        return "invalid JSON"
    if not isinstance(body, dict):
        return "JSON object"
    unknown = sorted(set(body) - {"request_id"})
    if unknown:
        return unknown[0]
    rid = body.get("request_id")
    if not isinstance(rid, str) or not 1 <= len(rid) <= 128:
        return "request_id"
    return None


@pytest.fixture
def agent(broker, telemetry_factory, collector_factory):
    tel = telemetry_factory(broker)
    accepted: list[str] = []
    tel.on_scan_request(lambda cmd: accepted.append(cmd.request_id))
    col = collector_factory(broker, [REPLIES, f"{BASE}/status"])
    col.wait_topic(f"{BASE}/status")
    return tel, col, accepted


counter = itertools.count()


def ask(col, raw: bytes) -> dict:
    correlation = f"c-{next(counter)}".encode()
    props = Properties(PacketTypes.PUBLISH)
    props.ResponseTopic = REPLIES
    props.CorrelationData = correlation
    col.publish(f"{BASE}/cmd/scan", raw, props)
    col.wait_for(
        lambda ms: any(
            m.topic == REPLIES and m.properties.CorrelationData == correlation for m in ms
        )
    )
    replies = [m for m in col.on(REPLIES) if m.properties.CorrelationData == correlation]
    assert len(replies) == 1
    return validate_json(replies[0].payload)


@settings(
    max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@pytest.mark.slow
@given(raw=requests)
def test_fuzzed_requests_get_one_reply_each(agent, raw):
    tel, col, accepted = agent
    reply = ask(col, raw)
    problem = expected_error(raw)
    if problem is None:
        assert reply["accepted"] and reply["status"] == "accepted"
        assert reply["request_id"] == json.loads(raw)["request_id"] == accepted[-1]
    else:
        assert not reply["accepted"] and reply["status"] == "error"
        assert problem in reply["error"], (raw, reply["error"])
    assert tel._thread.is_alive()


def test_named_problems_and_the_agent_survives(agent):
    tel, col, accepted = agent
    cases = {
        b"{not json": "invalid JSON",
        b'{"request_id": 7}': "request_id: Input should be a valid string",
        b'{"request_id": "a", "scan_now": true}': "scan_now: unknown field",
        b"[1, 2]": "payload must be a JSON object, got list",
        b"\xff\xfe": "not UTF-8",
        json.dumps({"request_id": "x" * (MAX_COMMAND_BYTES + 1)}).encode(): "payload too large",
        b"{}": "request_id: Field required",
        b"[" * 5000 + b"]" * 5000: "nested too deeply",  # it had broken the MQTT loop
    }
    for raw, problem in cases.items():
        reply = ask(col, raw)
        assert not reply["accepted"] and problem in reply["error"], (raw[:40], reply["error"])
    assert ask(col, b'{"request_id": "a", "scan_now": true}')["request_id"] == "a"
    assert ask(col, b'{"request_id": "ok-1"}')["accepted"]
    assert accepted == ["ok-1"]
    assert tel._thread.is_alive()


def test_an_empty_message_clears_a_retained_command_and_gets_no_reply(agent):
    """`mosquitto_pub -r -n` on the command topic (how the docs say to clear a retained
    command) reaches the agent as an empty live message: no command, so no error reply; the
    next request is answered as usual, and only it."""
    tel, col, accepted = agent
    props = Properties(PacketTypes.PUBLISH)
    props.ResponseTopic = REPLIES
    props.CorrelationData = b"the-empty-one"
    col.publish(f"{BASE}/cmd/scan", b"", props)
    assert ask(col, b'{"request_id": "after-empty"}')["accepted"]
    assert [m.properties.CorrelationData for m in col.on(REPLIES)] != []
    assert all(m.properties.CorrelationData != b"the-empty-one" for m in col.on(REPLIES))
    assert accepted == ["after-empty"] and tel._thread.is_alive()
