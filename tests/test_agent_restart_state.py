"""What a restarted daemon reports before its first scan: the Prometheus last-scan gauges hold
the cached results (not 0: an empty silo), and the `outbox` alarm still raised is declared
and raised wherever alarms are (Prometheus, Sparkplug NBIRTH, Home Assistant discovery, the
retained `P/alarm/outbox`), from the one list of alarm types; and a live session is judged
at the newest cached scan's level, as before the restart."""

from __future__ import annotations

import json
import shutil
import signal
import urllib.request
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pysparkplug as ps
import pytest
from prometheus_client.parser import text_string_to_metric_families

from silo_agent.analysis.alarm_types import ALARM_TYPES
from silo_agent.scan import read_scan
from silo_agent.storage.audit import read_heightmap
from tests.support.agent import BASE, SILO, Daemon, write_config
from tests.support.mqtt import validate_json
from tests.support.mqtt_broker import free_port

NODE_BIRTH = f"spBv1.0/silos/NBIRTH/{SILO}"
DISCOVERY = f"homeassistant/device/silo_agent_{SILO}/config"


def gauges(port: int) -> dict[tuple[str, tuple], float]:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def seconds(stamp: str) -> float:
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def a_later_invalid_scan(valid_dir: Path, hours: int) -> dict:
    """A copy of the cached valid scan, `hours` later and invalid (coverage too low): the
    newest result, which must not replace the volume of the last valid one."""
    captured = datetime.fromisoformat(
        json.loads((valid_dir / "result.json").read_text())["captured_at"].replace("Z", "+00:00")
    ) + timedelta(hours=hours)
    scan_id = f"{SILO}-{captured:%Y%m%dT%H%M%SZ}"
    target = valid_dir.parent / scan_id
    shutil.copytree(valid_dir, target)
    stamp = captured.isoformat(timespec="milliseconds").replace("+00:00", "Z")
    manifest = json.loads((target / "scan.json").read_text())
    manifest.update(scan_id=scan_id, captured_at=stamp)
    (target / "scan.json").write_text(json.dumps(manifest))
    result = json.loads((target / "result.json").read_text())
    result.update(
        scan_id=scan_id,
        captured_at=stamp,
        valid=False,
        coverage=0.125,
        invalid_reason="coverage 12.5 % below silo minimum 30 %",
    )
    (target / "result.json").write_text(json.dumps(result))
    return result


@pytest.mark.slow
def test_last_scan_metrics_survive_a_restart(tmp_path: Path, broker) -> None:
    port = free_port()
    metrics = {"enabled": True, "port": port}
    config = write_config(tmp_path / "agent.toml", broker.port, tmp_path, metrics=metrics)
    assert Daemon(config, tmp_path, "--scans", "1").wait(120) == 0
    (valid_dir,) = (tmp_path / "scans").glob(f"{SILO}-*")
    valid = json.loads((valid_dir / "result.json").read_text())
    assert valid["valid"] and valid["volume_m3"] > 30
    newest = a_later_invalid_scan(valid_dir, hours=1)

    write_config(config, broker.port, tmp_path, schedule={"scan_at_start": False}, metrics=metrics)
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("agent started")
        values = gauges(port)
        assert values[("silo_agent_last_volume_cubic_meters", ())] == valid["volume_m3"]
        assert values[("silo_agent_last_mass_kilograms", ())] == pytest.approx(
            valid["mass_t"] * 1000.0, rel=1e-12
        )
        assert values[("silo_agent_last_valid_scan_timestamp_seconds", ())] == seconds(
            valid["captured_at"]
        )
        assert values[("silo_agent_last_scan_timestamp_seconds", ())] == seconds(
            newest["captured_at"]
        )
        assert values[("silo_agent_last_coverage_ratio", ())] == newest["coverage"]
        assert values[("silo_agent_scans_total", (("outcome", "ok"),))] == 0  # no scan ran
        agent.signal(signal.SIGTERM)
        assert agent.wait(20) == 0
    finally:
        agent.kill()


def alarm_view(port: int, spb, ha, births: int, configs: int) -> dict[str, dict[str, bool]]:
    """Every alarm type each consumer knows and whether it shows it raised."""
    birth = ps.NBirth.decode(spb.wait_topic(NODE_BIRTH, births)[births - 1].payload)
    discovery = json.loads(ha.wait_topic(DISCOVERY, configs)[configs - 1].payload)
    return {
        "prometheus": {
            labels[0][1]: value == 1
            for (name, labels), value in gauges(port).items()
            if name == "silo_agent_alarm_active"
        },
        "sparkplug": {
            m.name.removeprefix("Alarms/"): m.value
            for m in birth.metrics
            if m.name.startswith("Alarms/")
        },
        "homeassistant": {
            key.removeprefix("alarm_"): None
            for key in discovery["cmps"]
            if key.startswith("alarm_")
        },
    }


@pytest.mark.slow
def test_outbox_alarm_is_declared_and_raised_everywhere_across_a_restart(
    tmp_path: Path, broker, collector_factory
) -> None:
    port = free_port()
    options = dict(
        schedule={"scan_at_start": False},
        mqtt={"sparkplug.enabled": True, "homeassistant.enabled": True},
        metrics={"enabled": True, "port": port},
    )
    config = write_config(tmp_path / "agent.toml", broker.port, tmp_path, **options)
    (tmp_path / "outbox.sqlite").write_bytes(b"not a database " * 200)
    spb = collector_factory(broker, ["spBv1.0/#"], client_id="host")
    ha = collector_factory(broker, ["homeassistant/#"], client_id="ha")
    for start in (1, 2):  # 1: the corrupt outbox is moved aside; 2: the copy is still there
        agent = Daemon(config, tmp_path)
        try:
            agent.wait_log("agent started")
            view = alarm_view(port, spb, ha, births=start, configs=start)
            for consumer, alarms in view.items():
                assert sorted(alarms) == sorted(ALARM_TYPES), (start, consumer)
            assert {t for t, on in view["prometheus"].items() if on} == {"outbox"}, start
            assert {t for t, on in view["sparkplug"].items() if on} == {"outbox"}, start
            state = collector_factory(broker, [f"{BASE}/alarm/outbox"], client_id=f"ha-{start}")
            retained = validate_json(state.wait_topic(f"{BASE}/alarm/outbox")[0].payload)
            assert retained["state"] == "raised" and "corrupt" in retained["message"], start
            agent.signal(signal.SIGTERM)
            assert agent.wait(20) == 0
        finally:
            agent.kill()
    assert list(tmp_path.glob("outbox.sqlite.corrupt-*"))


@pytest.mark.slow
def test_a_live_session_is_judged_at_the_last_scans_level_across_a_restart(
    tmp_path: Path, broker, collector_factory
) -> None:
    """Before its first scan a restarted agent judges a live session's cameras at the level
    of the newest cached scan, as it did before the restart, not halfway to the cameras: the
    two 424x240 wall cameras are refused, and the reply says at which level."""
    config = write_config(tmp_path / "agent.toml", broker.port, tmp_path)
    assert Daemon(config, tmp_path, "--scans", "1").wait(120) == 0
    (scan_dir,) = (tmp_path / "scans").glob(f"{SILO}-*")
    heightmap = read_heightmap(scan_dir)
    assert heightmap is not None
    level = float(np.nanmean(heightmap.heights))
    cameras_z = [c.extrinsic[2][3] for c in read_scan(scan_dir).cameras]
    assert abs(level - min(cameras_z) / 2) > 0.05  # halfway from the floor (z = 0): not it

    write_config(config, broker.port, tmp_path, schedule={"scan_at_start": False})
    col = collector_factory(broker, [f"{BASE}/#"])
    agent = Daemon(config, tmp_path)
    try:
        col.wait_for(
            lambda ms: any(
                m.topic == f"{BASE}/status" and json.loads(m.payload)["state"] == "online"
                for m in ms
            )
        )
        col.publish(f"{BASE}/cmd/live", b'{"on": true, "request_id": "after-restart"}')
        (message,) = col.wait_topic(f"{BASE}/cmd/live/reply")
        reply = validate_json(message.payload)
        assert reply["status"] == "error" and reply["request_id"] == "after-restart"
        assert f"(at z = {level:.2f} m)" in reply["error"]
        agent.signal(signal.SIGTERM)
        assert agent.wait(20) == 0
    finally:
        agent.kill()
