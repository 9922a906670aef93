"""TLS with client certificates, password authentication (right and wrong), broker ACLs."""

from __future__ import annotations

import dataclasses
import json
import time

import pytest
from structlog.testing import capture_logs

from tests.support.mqtt import BASE, SILO, summary, validate_json
from tests.support.mqtt_broker import Broker, make_tls


@pytest.mark.broker  # starts its own mosquitto
def test_tls_with_ca_and_encrypted_client_key(tmp_path, telemetry_factory, collector_factory):
    tls = make_tls(tmp_path / "pki", key_password="k3y-pass")
    broker = Broker(tmp_path / "broker", tls=tls).start()
    try:
        (tmp_path / "keypass").write_text("k3y-pass\n")
        tel = telemetry_factory(
            broker,
            tls={
                "ca_file": tls.ca,
                "cert_file": tls.client_cert,
                "key_file": tls.client_key,
                "key_password_file": tmp_path / "keypass",
            },
        )
        plain_key = dataclasses.replace(tls, client_key=tls.client_key.with_name("client.key"))
        col = collector_factory(broker, [f"{BASE}/#"], tls=plain_key)
        assert validate_json(col.wait_topic(f"{BASE}/status")[-1].payload)["state"] == "online"
        tel.publish_result(summary())
        assert validate_json(col.wait_topic(f"{BASE}/volume")[0].payload)["volume_m3"] == 12.345
    finally:
        broker.stop()


@pytest.mark.broker  # starts its own mosquitto
def test_wrong_password_is_reported_and_retried_with_back_off(
    tmp_path, monkeypatch, telemetry_factory, collector_factory
):
    broker = Broker(tmp_path / "broker", passwords={"agent": "right", "test": "t"}).start()
    try:
        monkeypatch.setenv("SILO_TEST_PW", "wrong")
        with capture_logs() as logs:
            tel = telemetry_factory(
                broker,
                username="agent",
                password_env="SILO_TEST_PW",
                reconnect_min_s=0.1,
                reconnect_max_s=0.8,
            )
            end = time.monotonic() + 15
            while sum(e["event"] == "MQTT connection failed, retrying" for e in logs) < 3:
                assert time.monotonic() < end, "fewer than 3 attempts in 15 s"
                time.sleep(0.02)
            tel.stop()
        failures = [e for e in logs if e["event"] == "MQTT connection failed, retrying"]
        assert len(failures) >= 3
        # mosquitto 2.0 answers a wrong password with "Not authorized" (0x87)
        assert all("authentication failed" in e["reason"] for e in failures)
        assert "Not authorized" in failures[0]["reason"]
        assert "mqtt.username ('agent')" in failures[0]["reason"]
        waits = [e["retry_in_s"] for e in failures]
        assert waits[-1] > 2 * waits[0]  # back-off grows (0.1 s doubling, +-20 % jitter)
        assert tel.outbox.path.exists()

        (tmp_path / "pw").write_text("right\n")
        telemetry_factory(
            broker,
            username="agent",
            password_file=tmp_path / "pw",
            outbox_path=tmp_path / "outbox2.sqlite",
        )
        col = collector_factory(broker, [f"{BASE}/status"], username="test", password="t")
        assert validate_json(col.wait_topic(f"{BASE}/status")[-1].payload)["state"] == "online"
    finally:
        broker.stop()


@pytest.mark.broker  # starts its own mosquitto
def test_acl_denial_is_logged_not_fatal(tmp_path, telemetry_factory, collector_factory):
    acl = f"""
topic read {BASE}/#
topic write {BASE}/status
topic write {BASE}/volume
topic write {BASE}/heightmap
"""
    broker = Broker(tmp_path / "broker", acl=acl).start()
    try:
        col = collector_factory(broker, [f"{BASE}/#"])
        with capture_logs() as logs:
            tel = telemetry_factory(broker)
            tel.publish_result(summary(f"{SILO}-1"))
            col.wait_topic(f"{BASE}/volume")
            deadline = time.monotonic() + 5
            while tel.outbox.size()[0] and time.monotonic() < deadline:
                time.sleep(0.05)
        refused = [e for e in logs if e["event"] == "broker refused a message, dropped"]
        assert [e["topic"] for e in refused] == [f"{BASE}/scan"]
        assert "Not authorized" in refused[0]["reason"]
        assert tel.outbox.size()[0] == 0
        assert tel.outbox.counter("rejected") == 1
        # still connected and publishing; the refusal shows on P/status
        tel.publish_result(summary(f"{SILO}-2"))
        col.wait_for(
            lambda ms: any(
                m.topic == f"{BASE}/volume" and json.loads(m.payload)["scan_id"] == f"{SILO}-2"
                for m in ms
            )
        )
        col.wait_for(
            lambda ms: any(
                m.topic == f"{BASE}/status" and json.loads(m.payload)["outbox"]["rejected"] >= 1
                for m in ms
            )
        )
        assert not col.on(f"{BASE}/scan")
        assert tel._thread.is_alive()
    finally:
        broker.stop()
