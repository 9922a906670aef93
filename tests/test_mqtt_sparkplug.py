"""Sparkplug B, decoded by an independent implementation (pysparkplug), never by our encoder."""

from __future__ import annotations

import json
import socket
import time

import pysparkplug as ps
from structlog.testing import capture_logs

from silo_agent.analysis.alarm_types import AlarmEvent
from tests.support.mqtt import SILO, summary
from tests.support.mqtt_broker import Broker
from tests.support.sparkplug import rebirth_request

NODE = f"spBv1.0/silos/{{}}/{SILO}"


def births(col) -> list[ps.NBirth]:
    return [ps.NBirth.decode(m.payload) for m in col.on(NODE.format("NBIRTH"))]


def metric_map(payload) -> dict[str, ps.Metric]:
    return {m.name: m for m in payload.metrics}


def wait_until(check, timeout: float = 15) -> None:
    end = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)


def failed_attempts(logs: list[dict]) -> int:
    return sum(
        e["event"] == "MQTT connection failed, retrying" and e["link"] == "sparkplug" for e in logs
    )


def test_birth_data_rebirth_death_and_bd_seq_across_restarts(
    broker, telemetry_factory, collector_factory
):
    col = collector_factory(broker, ["spBv1.0/#"])
    tel = telemetry_factory(broker, sparkplug={"enabled": True})
    col.wait_topic(NODE.format("NBIRTH"))
    birth = births(col)[0]
    assert birth.seq == 0
    metrics = metric_map(birth)
    assert metrics["bdSeq"].value == 0 and metrics["bdSeq"].datatype == ps.DataType.UINT64
    assert metrics["Node Control/Rebirth"].datatype == ps.DataType.BOOLEAN
    expected = {
        "Inventory/Volume m3": ps.DataType.DOUBLE,
        "Inventory/Mass t": ps.DataType.DOUBLE,
        "Inventory/Level Min m": ps.DataType.DOUBLE,
        "Inventory/Level Mean m": ps.DataType.DOUBLE,
        "Inventory/Level Max m": ps.DataType.DOUBLE,
        "Inventory/Coverage": ps.DataType.DOUBLE,
        "Scan/Time": ps.DataType.DATETIME,
        "Scan/Last Id": ps.DataType.STRING,
        "Alarms/collapse": ps.DataType.BOOLEAN,
        "Alarms/level_high": ps.DataType.BOOLEAN,
        "Cameras/cam-a/State": ps.DataType.STRING,
        "Cameras/cam-b/State": ps.DataType.STRING,
    }
    assert {k: metrics[k].datatype for k in expected} == expected
    assert metrics["Inventory/Volume m3"].is_null  # nothing measured yet
    assert metrics["Cameras/cam-a/State"].value == "unknown"

    tel.publish_result(summary())
    tel.publish_alarm(
        AlarmEvent.from_json(
            {
                "type": "level_high",
                "state": "raised",
                "severity": "warning",
                "scan_id": summary().scan_id,
                "value": 1.4,
                "threshold": 1.3,
            }
        )
    )
    col.wait_topic(NODE.format("NDATA"), 2)
    data = [ps.NData.decode(m.payload, birth=birth) for m in col.on(NODE.format("NDATA"))]
    assert [d.seq for d in data] == [1, 2]
    values = metric_map(data[0])
    assert values["Inventory/Volume m3"].value == 12.345
    assert values["Inventory/Level Max m"].value == 1.4
    assert values["Scan/Last Id"].value == summary().scan_id
    assert values["Scan/Time"].timestamp == 1795312800000  # captured_at, ms
    assert not values["Inventory/Volume m3"].is_historical
    assert metric_map(data[1])["Alarms/level_high"].value is True

    # rebirth on NCMD: a new NBIRTH (seq 0, same bdSeq) carrying the current values
    col.publish(NODE.format("NCMD"), rebirth_request())
    col.wait_topic(NODE.format("NBIRTH"), 2)
    rebirth = metric_map(births(col)[1])
    assert births(col)[1].seq == 0 and rebirth["bdSeq"].value == 0
    assert rebirth["Inventory/Volume m3"].value == 12.345
    assert rebirth["Alarms/level_high"].value is True
    tel.set_status(cameras={"cam-a": ("ok", None)})
    col.wait_topic(NODE.format("NDATA"), 3)
    after = ps.NData.decode(col.on(NODE.format("NDATA"))[2].payload)
    assert after.seq == 1 and metric_map(after)["Cameras/cam-a/State"].value == "ok"

    # clean stop: NDEATH with this session's bdSeq; the next process uses bdSeq + 1
    tel.stop()
    death = ps.NDeath.decode(col.wait_topic(NODE.format("NDEATH"))[0].payload)
    assert death.bd_seq_metric.value == 0
    telemetry_factory(broker, sparkplug={"enabled": True})
    col.wait_topic(NODE.format("NBIRTH"), 3)
    assert metric_map(births(col)[2])["bdSeq"].value == 1


def test_ndeath_is_the_will_and_replayed_data_is_historical(
    broker, telemetry_factory, collector_factory
):
    col = collector_factory(broker, ["spBv1.0/#"])
    tel = telemetry_factory(broker, sparkplug={"enabled": True}, start=False)
    tel.publish_result(summary())  # queued before any connection: replayed later
    time.sleep(0.01)
    tel.start()
    col.wait_topic(NODE.format("NDATA"))
    replayed = ps.NData.decode(col.on(NODE.format("NDATA"))[0].payload)
    assert all(m.is_historical for m in replayed.metrics)

    # the Sparkplug connection dies without DISCONNECT: the broker sends the will NDEATH,
    # the agent reconnects with the next bdSeq
    spb_link = tel._links[1]
    spb_link.client.socket().shutdown(socket.SHUT_RDWR)
    death = ps.NDeath.decode(col.wait_topic(NODE.format("NDEATH"))[0].payload)
    assert death.bd_seq_metric.value == 0
    col.wait_topic(NODE.format("NBIRTH"), 2)
    assert [metric_map(b)["bdSeq"].value for b in births(col)] == [0, 1]
    tel.publish_result(summary("silo-t-live"))
    col.wait_topic(NODE.format("NDATA"), 2)
    live = ps.NData.decode(col.on(NODE.format("NDATA"))[1].payload)
    assert live.seq == 1 and not any(m.is_historical for m in live.metrics)


def host_waits(logs: list[dict]) -> int:
    """Sessions that found the primary host offline and held their NBIRTH."""
    return sum(e["event"].startswith("Sparkplug waiting for the primary host") for e in logs)


def test_waits_for_the_primary_host(broker, telemetry_factory, collector_factory):
    col = collector_factory(broker, ["spBv1.0/#"])

    def host_state(online: bool, stamp: int) -> None:
        payload = json.dumps({"online": online, "timestamp": stamp})
        col.client.publish("spBv1.0/STATE/scada", payload, qos=1, retain=True)

    with capture_logs() as logs:
        tel = telemetry_factory(broker, sparkplug={"enabled": True, "primary_host_id": "scada"})
        tel.publish_result(summary())
        # the barrier: the session's first turn decided not to birth (a birth would be instead)
        wait_until(lambda: host_waits(logs) == 1)
        assert not col.on(NODE.format("NBIRTH")) and not col.on(NODE.format("NDATA"))
        now = int(time.time() * 1000)
        host_state(True, now)
        col.wait_topic(NODE.format("NBIRTH"))
        col.wait_topic(NODE.format("NDATA"))
        # host goes offline: NDEATH, new session, no birth until the host is back
        host_state(False, now + 1)
        death = ps.NDeath.decode(col.wait_topic(NODE.format("NDEATH"))[0].payload)
        assert death.bd_seq_metric.value == 0
        wait_until(lambda: host_waits(logs) == 2)  # the next session holds its birth too
    assert len(col.on(NODE.format("NBIRTH"))) == 1
    host_state(True, now + 2)
    col.wait_topic(NODE.format("NBIRTH"), 2)
    assert metric_map(births(col)[1])["bdSeq"].value == 1
    assert tel._thread.is_alive()


def test_bd_seq_goes_up_once_per_session_not_per_connection_attempt(
    tmp_path, telemetry_factory, collector_factory
):
    """Attempts that never get a session (broker down at start, then an outage) reuse the
    bdSeq their Last Will carried: the sessions a host sees are numbered 0, 1, 2."""
    broker = Broker(tmp_path / "late-broker")  # not listening yet
    try:
        with capture_logs() as logs:
            tel = telemetry_factory(broker, sparkplug={"enabled": True})
            wait_until(lambda: failed_attempts(logs) >= 3)  # back-off 0.1, 0.2, 0.4, 0.5 s
        broker.start()
        col = collector_factory(broker, ["spBv1.0/#"])
        col.publish(NODE.format("NCMD"), rebirth_request())  # the NBIRTH may precede `col`
        col.wait_topic(NODE.format("NBIRTH"))
        assert {metric_map(b)["bdSeq"].value for b in births(col)} == {0}

        # an outage while running: the session ends, the attempts while the broker is down fail
        with capture_logs() as logs:
            broker.stop()
            wait_until(lambda: failed_attempts(logs) >= 3)
            broker.start()
            spb_link = tel._links[1]
            end = time.monotonic() + 15
            while not (spb_link.born and col.client.is_connected()) and time.monotonic() < end:
                time.sleep(0.05)
        seen = len(births(col))
        col.publish(NODE.format("NCMD"), rebirth_request())
        col.wait_topic(NODE.format("NBIRTH"), seen + 1)
        assert metric_map(births(col)[-1])["bdSeq"].value == 1

        deaths = len(col.on(NODE.format("NDEATH")))  # a Last Will of the outage may be there
        tel.stop()  # NDEATH with the session's bdSeq; the next process takes the next one
        death = ps.NDeath.decode(col.wait_topic(NODE.format("NDEATH"), deaths + 1)[-1].payload)
        assert death.bd_seq_metric.value == 1
        telemetry_factory(broker, sparkplug={"enabled": True})
        col.wait_topic(NODE.format("NBIRTH"), len(births(col)) + 1)
        assert metric_map(births(col)[-1])["bdSeq"].value == 2
    finally:
        broker.stop()


def test_replayed_data_carries_only_what_the_birth_declared(
    broker, telemetry_factory, collector_factory
):
    """A camera taken out of the config between runs: its state, still queued from the last
    run, is left out of the replayed NDATA (which a host would reject), and a queued NDATA with
    nothing left is not sent at all, so the seq runs on without a gap."""
    col = collector_factory(broker, ["spBv1.0/#"])
    old = telemetry_factory(
        broker, cameras=("cam-a", "cam-c"), sparkplug={"enabled": True}, start=False
    )
    old.set_status(cameras={"cam-a": ("ok", None), "cam-c": ("ok", None)})
    old.set_status(cameras={"cam-c": ("failed", "timeout")})  # only the removed camera
    old.publish_result(summary())
    old.stop()  # never connected: the three NDATA stay in the outbox
    new = telemetry_factory(broker, cameras=("cam-a", "cam-b"), sparkplug={"enabled": True})
    col.wait_topic(NODE.format("NDATA"), 2)
    new.set_status(cameras={"cam-b": ("failed", "timeout")})  # one more NDATA: a barrier
    col.wait_topic(NODE.format("NDATA"), 3)  # had cam-c's gone out, this would be the 4th
    (birth,) = births(col)
    declared = set(metric_map(birth))
    assert "Cameras/cam-c/State" not in declared
    *data, barrier = [ps.NData.decode(m.payload) for m in col.on(NODE.format("NDATA"))]
    assert [d.seq for d in data] == [1, 2]
    assert {m.name: m.value for m in barrier.metrics} == {"Cameras/cam-b/State": "failed"}
    assert all(m.name in declared and m.is_historical for d in data for m in d.metrics)
    assert {m.name: m.value for m in data[0].metrics} == {"Cameras/cam-a/State": "ok"}
    assert metric_map(data[1])["Inventory/Volume m3"].value == 12.345


def test_birth_stamps_each_metric_with_when_its_value_was_measured(
    broker, telemetry_factory, collector_factory
):
    """A historian records each value once: a rebirth gives the scan's metrics the capture
    time and an alarm or camera the time of its NDATA, as the NDATA did; the birth time only
    goes to bdSeq, the rebirth control and values never set."""
    col = collector_factory(broker, ["spBv1.0/#"])
    tel = telemetry_factory(broker, sparkplug={"enabled": True})
    col.wait_topic(NODE.format("NBIRTH"))
    tel.publish_result(summary())
    tel.publish_alarm(
        AlarmEvent.from_json(
            {"type": "level_high", "state": "raised", "severity": "warning", "scan_id": "s"}
        )
    )
    tel.set_status(cameras={"cam-a": ("ok", None)})
    col.wait_topic(NODE.format("NDATA"), 3)
    sent = {
        m.name: m.timestamp
        for raw in col.on(NODE.format("NDATA"))
        for m in ps.NData.decode(raw.payload).metrics
    }
    time.sleep(0.01)  # the rebirth's own time differs from every NDATA's
    col.publish(NODE.format("NCMD"), rebirth_request())
    col.wait_topic(NODE.format("NBIRTH"), 2)
    rebirth = births(col)[1]
    stamps = {m.name: m.timestamp for m in rebirth.metrics}
    assert {name: stamps[name] for name in sent} == sent
    assert stamps["Inventory/Volume m3"] == stamps["Scan/Time"] == 1795312800000
    never_set = {
        "bdSeq",
        "Node Control/Rebirth",
        "Node Info/Software Version",
        "Alarms/collapse",
        "Cameras/cam-b/State",
    }
    assert {stamps[name] for name in never_set} == {rebirth.timestamp}
    assert rebirth.timestamp > max(sent.values())
