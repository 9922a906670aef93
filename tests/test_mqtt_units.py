"""Schemas in sync, height-map format, outbox durability rules (no broker needed)."""

from __future__ import annotations

import io
import json
import sqlite3
import struct
import time
import zlib

import numpy as np
import pytest

from silo_agent.analysis.summary import ScanSummary
from silo_agent.cli import main
from silo_agent.config import ConfigError, MqttConfig
from silo_agent.grid.heightmap import HeightMap
from silo_agent.storage.audit import AuditCache
from silo_agent.telemetry.client import read_secret
from silo_agent.telemetry.heightmap_codec import (
    HEADER,
    HeightMapFormatError,
    decode_heightmap,
    encode_heightmap,
)
from silo_agent.telemetry.outbox import Outbox, OutboxLimits
from silo_agent.telemetry.payloads import check_summary, json_schemas, render_schema
from tests.support.agent import write_config
from tests.support.mqtt import SCHEMAS, realistic_heightmap, summary, summary_json


def test_committed_schemas_match_the_models():
    committed = {p.name for p in SCHEMAS.glob("*.json")}
    assert committed == set(json_schemas())
    for name, schema in json_schemas().items():
        assert (SCHEMAS / name).read_text() == render_schema(schema), name
    assert main(["schemas", "--check", str(SCHEMAS)]) == 0


def test_summary_problems_are_named():
    bad = summary_json()
    del bad["coverage"]
    with pytest.raises(ValueError, match="lacks 'coverage'"):
        ScanSummary.from_json(bad)
    with pytest.raises(ValueError, match="coverage"):
        check_summary(summary(coverage=1.5))
    with pytest.raises(ValueError, match="level"):
        ScanSummary.from_json(summary_json(level=[1, 2, 3]))


# ---------------------------------------------------------------- height map


def test_8_by_6_m_at_2_cm_is_small_and_exact_to_half_a_millimetre():
    hm = realistic_heightmap(rows=300, cols=400, step=0.02)
    blob = encode_heightmap(hm, "silo-t-1")
    assert len(blob) < 150_000
    back = decode_heightmap(blob)
    assert back.shape == (300, 400) and back.step == 0.02 and back.origin == hm.origin
    known = np.isfinite(hm.heights)
    assert np.array_equal(np.isfinite(back.heights), known)
    assert np.max(np.abs(back.heights[known] - hm.heights[known])) <= 0.0005 + 1e-9
    assert np.array_equal(back.observed, hm.observed)
    assert np.max(np.abs(back.inside - hm.inside)) <= 0.5 / 255


def test_header_says_where_cell_0_0_is_and_the_readme_decoder_works():
    heights = np.array([[1.0, 1.5, np.nan], [2.0, 2.25, 2.5]])
    hm = HeightMap(
        (10.0, 20.0),
        0.5,
        heights,
        np.array([[1, 0, 0], [1, 1, 0]], bool),
        np.array([[1, 1, 0], [1, 1, 1]], float),
    )
    blob = encode_heightmap(hm, "scan-7")
    fields = HEADER.unpack_from(blob)
    assert fields[0] == b"SLHM" and fields[5:10] == (2, 3, 0.5, 10.0, 20.0)
    assert fields[4] == 0b11  # row 0 = min y, origin = outer corner
    # the numpy decoder of docs/mqtt.md, verbatim in spirit: header, then three zlib layers
    rows, cols = struct.unpack_from("<II", blob, 8)
    z0, unknown, nf, ns, nh = struct.unpack_from("<dHHHI", blob, 40)
    pos = 66 + nf + ns
    codes = np.cumsum(
        np.frombuffer(zlib.decompress(blob[pos : pos + nh]), "<u2").reshape(rows, cols),
        axis=1,
        dtype=np.uint16,
    )
    z = np.where(codes == unknown, np.nan, z0 + codes / 1000.0)
    np.testing.assert_allclose(z, heights, atol=5e-4)
    assert blob[66 : 66 + nf] == b"silo" and blob[66 + nf : pos] == b"scan-7"


def test_corrupt_height_maps_are_refused():
    blob = encode_heightmap(realistic_heightmap(rows=20, cols=30), "x")
    with pytest.raises(HeightMapFormatError, match="magic"):
        decode_heightmap(b"JUNK" + blob[4:])
    with pytest.raises(HeightMapFormatError, match="length"):
        decode_heightmap(blob[:-3])


def test_heights_beyond_the_format_range_are_refused():
    hm = HeightMap((0, 0), 1.0, np.array([[0.0, 70.0]]), np.ones((1, 2), bool), np.ones((1, 2)))
    with pytest.raises(ValueError, match="span"):
        encode_heightmap(hm, "x")


# ---------------------------------------------------------------- outbox


def test_outbox_is_wal_full_sync_and_keeps_seq_and_bd_seq(tmp_path):
    path = tmp_path / "o.sqlite"
    box = Outbox(path)
    e1 = box.enqueue("t/a", lambda e: e.model_dump_json().encode())
    e2 = box.enqueue("t/a", lambda e: b"x")
    assert (e1.seq, e2.seq) == (1, 2)
    assert box.bd_seq() == 0
    box.advance_bd_seq()  # a session was accepted with bdSeq 0
    assert box._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert box._db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    box.close()
    again = Outbox(path)
    rows = again.pending()
    assert [(r.msg_id, r.seq) for r in rows] == [(e1.msg_id, 1), (e2.msg_id, 2)]
    assert json.loads(rows[0].payload)["msg_id"] == e1.msg_id
    assert again.enqueue("t/a", lambda e: b"y").seq == 3
    assert again.bd_seq() == again.bd_seq() == 1  # reading it does not use it up
    again.ack([rows[0].id])
    assert [r.seq for r in again.pending()] == [2, 3]


def test_retained_latest_keeps_only_the_newest_pending_value(tmp_path):
    box = Outbox(tmp_path / "o.sqlite")
    box.enqueue("p/volume", lambda e: b"v1", retain=True, latest=True)
    box.enqueue("p/scan", lambda e: b"s1")
    box.enqueue("p/volume", lambda e: b"v2", retain=True, latest=True)
    assert [(r.topic, r.payload) for r in box.pending()] == [("p/scan", b"s1"), ("p/volume", b"v2")]


def test_bounds_drop_oldest_non_retained_first_and_count(tmp_path):
    box = Outbox(tmp_path / "o.sqlite", OutboxLimits(max_messages=3))
    box.enqueue("p/volume", lambda e: b"v", retain=True, latest=True)
    for k in range(4):
        box.enqueue("p/scan", lambda e, k=k: f"s{k}".encode())
    assert [r.payload for r in box.pending()] == [b"v", b"s2", b"s3"]
    assert box.counter("dropped") == 2


def test_age_bound_drops_old_non_retained(tmp_path):
    box = Outbox(tmp_path / "o.sqlite", OutboxLimits(max_age_s=60))
    box.enqueue("p/scan", lambda e: b"old")
    box.enqueue("p/volume", lambda e: b"old-v", retain=True, latest=True)
    box._db.execute("UPDATE messages SET created = ?", (time.time() - 120,))
    box.enqueue("p/scan", lambda e: b"new")
    assert [r.payload for r in box.pending()] == [b"old-v", b"new"]
    assert box.counter("dropped") == 1


def test_a_failed_build_commits_nothing(tmp_path):
    box = Outbox(tmp_path / "o.sqlite")

    def boom(_env):
        raise RuntimeError("no")

    with pytest.raises(RuntimeError):
        box.enqueue("t", boom)
    assert box.pending() == [] and box.next_envelope().seq == 1
    # committed means on disk for another connection
    box.enqueue("t", lambda e: b"x")
    other = sqlite3.connect(tmp_path / "o.sqlite")
    assert other.execute("SELECT COUNT(*) FROM messages").fetchone()[0] == 1


# ---------------------------------------------------------------- config & secrets


def test_secrets_come_from_file_or_environment(tmp_path, monkeypatch):
    (tmp_path / "pw").write_text("s3cret\nignored\n")
    assert read_secret(tmp_path / "pw", None, "mqtt.password") == "s3cret"
    monkeypatch.setenv("PW_VAR", "from-env")
    assert read_secret(None, "PW_VAR", "mqtt.password") == "from-env"
    with pytest.raises(ConfigError, match=r"mqtt\.password_env: environment variable NOPE"):
        read_secret(None, "NOPE", "mqtt.password")
    with pytest.raises(ConfigError, match=r"mqtt\.password_file"):
        read_secret(tmp_path / "missing", None, "mqtt.password")


def test_mqtt_config_rejects_contradictions():
    with pytest.raises(ValueError, match="not both"):
        MqttConfig(username="u", password_file="/x", password_env="Y")
    with pytest.raises(ValueError, match="needs a username"):
        MqttConfig(password_env="Y")
    with pytest.raises(ValueError, match="cert_file and key_file"):
        MqttConfig(tls={"cert_file": "/c.pem"})
    with pytest.raises(ValueError):
        MqttConfig(protocol="4")


@pytest.mark.broker  # starts its own mosquitto
def test_drops_are_reported_on_status(tmp_path):
    from silo_agent.telemetry.client import Telemetry
    from tests.support.mqtt import mqtt_config
    from tests.support.mqtt_broker import Broker

    cfg = mqtt_config(Broker(tmp_path / "b"), tmp_path, outbox_max_messages=10)
    tel = Telemetry(cfg, "silo-t", ["cam-a"])  # never started: everything stays pending
    for k in range(12):
        tel.publish_result(summary(f"silo-t-{k}"))
    # 12 scans + the newest volume (retained "latest") = 13 rows, bound 10: 3 oldest scans go
    status = tel.status().outbox
    assert (status.pending, status.dropped) == (10, 3)
    scans = [
        json.loads(r.payload)["scan_id"]
        for r in tel.outbox.pending(limit=20)
        if r.topic.endswith("/scan")
    ]
    assert scans == [f"silo-t-{k}" for k in range(3, 12)]
    tel.outbox.close()


def test_the_documented_numpy_decoder_decodes_a_published_map():
    doc = (SCHEMAS.parents[1] / "docs" / "mqtt.md").read_text()
    section = doc[doc.index("## Height map") :]
    code = section[section.index("```python") + len("```python") :]
    code = code[: code.index("```")]
    namespace: dict = {}
    exec(code, namespace)
    hm = realistic_heightmap(rows=40, cols=50)
    m = namespace["decode"](encode_heightmap(hm, "silo-t-9"))
    z, observed = m["z"], m["observed"]
    assert m["origin"] == hm.origin and m["step"] == hm.step and m["scan_id"] == "silo-t-9"
    assert np.array_equal(np.isnan(z), np.isnan(hm.heights))
    assert np.nanmax(np.abs(z - hm.heights)) <= 0.0005 + 1e-9
    assert np.array_equal(observed, hm.observed)


@pytest.mark.broker  # starts its own mosquitto
def test_a_bad_result_queues_nothing_and_stale_sparkplug_rows_are_dropped(tmp_path):
    from silo_agent.telemetry.client import Telemetry
    from tests.support.mqtt import mqtt_config
    from tests.support.mqtt_broker import Broker

    cfg = mqtt_config(Broker(tmp_path / "b"), tmp_path, sparkplug={"enabled": True})
    tel = Telemetry(cfg, "silo-t", ["cam-a"])
    too_tall = HeightMap(
        (0, 0), 1.0, np.array([[0.0, 70.0]]), np.ones((1, 2), bool), np.ones((1, 2))
    )
    with pytest.raises(ValueError, match="span"):
        tel.publish_result(summary(), too_tall)
    assert tel.outbox.size() == (0, 0)
    tel.publish_result(summary())
    kinds = sorted(r.kind for r in tel.outbox.pending())
    assert kinds == ["json", "json", "sparkplug"]
    tel.outbox.close()
    plain = Telemetry(mqtt_config(Broker(tmp_path / "b"), tmp_path), "silo-t", ["cam-a"])
    assert sorted(r.kind for r in plain.outbox.pending()) == ["json", "json"]
    plain.outbox.close()


def test_publish_by_hand_refuses_a_bad_file_in_one_line(tmp_path, capsys):
    """`silo-agent publish`: a result or event file that is no summary or event is exit 65
    with one line naming the file and the problem, before anything is queued."""
    config = write_config(tmp_path / "agent.toml", 9, tmp_path)
    result = tmp_path / "result.json"
    result.write_text(json.dumps({**summary_json(), "level": [1, 2]}))
    assert main(["publish", "--config", str(config), "--result", str(result)]) == 65
    assert (
        capsys.readouterr().err.strip().startswith(f"silo-agent: {result}: result summary: level")
    )
    result.write_text(json.dumps(summary_json()))
    event = tmp_path / "event.json"
    event.write_text(json.dumps({"type": "x", "state": "raised", "colour": "red"}))
    argv = ["publish", "--config", str(config), "--result", str(result), "--alarm", str(event)]
    assert main(argv) == 65
    assert "unknown key(s) colour" in capsys.readouterr().err
    assert not (tmp_path / "outbox.sqlite").exists()


def test_publish_by_hand_sends_a_kept_height_map_and_refuses_a_bad_one(tmp_path, capsys):
    """`silo-agent publish --heightmap`: the map a scan directory keeps (`add_result`) is
    queued as it was kept; a file that is no such map is exit 65 with one line naming it and
    the problem, before anything is queued."""
    config = write_config(tmp_path / "agent.toml", 9, tmp_path)
    result = tmp_path / "result.json"
    result.write_text(json.dumps(summary_json()))
    kept = tmp_path / "scan"
    kept.mkdir()
    heightmap = realistic_heightmap(60, 80)
    AuditCache.add_result(kept, summary_json(), heightmap, {})
    argv = ["publish", "--config", str(config), "--result", str(result), "--timeout", "0"]
    bad = {
        "junk.npz": lambda path: path.write_text("not a map"),
        "missing.npz": lambda path: None,
        "array.npz": lambda path: path.write_bytes(_npy_bytes(np.zeros(3))),
        "no-step.npz": lambda path: np.savez(
            path, origin=[0, 0], heights=np.zeros((2, 2)), observed=np.ones((2, 2)), inside=1
        ),
        "shapes.npz": lambda path: np.savez(
            path,
            origin=[0.0, 0.0],
            step=0.1,
            heights=np.zeros((2, 2)),
            observed=np.ones((2, 3), bool),
            inside=np.ones((2, 2)),
        ),
    }
    problems = {
        "junk.npz": "not an .npz of origin, step, heights, observed, inside",
        "missing.npz": "cannot read it",
        "array.npz": "a single array",
        "no-step.npz": "no step in it",
        "shapes.npz": "observed and inside of its shape",
    }
    for name, write in bad.items():
        path = tmp_path / name
        write(path)
        assert main([*argv, "--heightmap", str(path)]) == 65, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"silo-agent: {path}: height map: "), err
        assert problems[name] in err[0]
        assert not (tmp_path / "outbox.sqlite").exists()
    assert main([*argv, "--heightmap", str(kept / "heightmap.npz")]) == 1  # no broker: pending
    queued = Outbox(tmp_path / "outbox.sqlite")
    maps = [row for row in queued.pending() if row.topic.endswith("/heightmap")]
    queued.close()
    assert len(maps) == 1
    sent = decode_heightmap(maps[0].payload)
    assert sent.shape == heightmap.shape and sent.origin == heightmap.origin
    np.testing.assert_array_equal(sent.observed, heightmap.observed)
    np.testing.assert_allclose(sent.heights, heightmap.heights, atol=0.002, equal_nan=True)


def test_publish_by_hand_checks_every_file_before_anything_is_queued(tmp_path, capsys):
    """`silo-agent publish`: a value its payloads refuse, in the result, the alarm event or
    the height map, is exit 65 with one line naming the file and the key; nothing is queued,
    not even the result's messages ahead of a bad event."""
    config = write_config(tmp_path / "agent.toml", 9, tmp_path)
    good = tmp_path / "result.json"
    good.write_text(json.dumps(summary_json()))
    argv = ["publish", "--config", str(config), "--timeout", "0"]

    def refused(args: list[str], starts: str) -> None:
        assert main([*argv, *args]) == 65, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"silo-agent: {starts}"), err
        assert not (tmp_path / "outbox.sqlite").exists()

    for key, value in {"coverage": -1, "timings": "x"}.items():
        path = tmp_path / f"result-{key}.json"
        path.write_text(json.dumps(summary_json(**{key: value})))
        refused(["--result", str(path)], f"{path}: result summary: {key}: ")
    event = {"type": "collapse", "state": "raised", "severity": "critical", "scan_id": "x"}
    events = {
        "state": {**event, "state": "bogus"},
        "severity": {**event, "severity": "dire"},
        "value": {**event, "value": "big"},
        "position": {**event, "position": "ab"},
        "must be a JSON object": [event],
    }
    for says, bad in events.items():
        path = tmp_path / "event.json"
        path.write_text(json.dumps(bad))
        refused(["--result", str(good), "--alarm", str(path)], f"{path}: alarm event: {says}")
    tall = tmp_path / "tall.npz"  # heights spanning 100 m: more than P/heightmap can carry
    np.savez(
        tall,
        origin=[0.0, 0.0],
        step=0.1,
        heights=np.array([[0.0, 100.0]]),
        observed=np.ones((1, 2), bool),
        inside=np.ones((1, 2)),
    )
    refused(["--result", str(good), "--heightmap", str(tall)], f"{tall}: height map: ")


def _npy_bytes(values: np.ndarray) -> bytes:
    """`values` as a .npy file's bytes: one array, not an archive of them."""
    buffer = io.BytesIO()
    np.save(buffer, values)
    return buffer.getvalue()
