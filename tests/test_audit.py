"""The audit cache on a real directory: atomic scan directories with hashes and the config
snapshot, retention by size and age that spares alarm baselines, export."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tarfile
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from silo_agent.base.atomic import write_atomic
from silo_agent.config import AuditConfig
from silo_agent.scan import CameraCloud, Scan, ScanError, Site, read_scan
from silo_agent.storage.audit import AuditCache, comparable, differences

T0 = datetime(2026, 11, 1, 6, 0, tzinfo=UTC)


def make_scan(k: int, points: int = 2000, when: datetime | None = None) -> Scan:
    rng = np.random.default_rng(k)
    when = when or T0 + timedelta(hours=k)
    clouds = [
        CameraCloud(
            serial=f"cam-{c}",
            points=(rng.normal(0, 1, (points, 3)) * [1, 1, 0.2] + [0, 0, 3]).astype(np.float32),
            extrinsic=np.eye(4),
        )
        for c in range(2)
    ]
    return Scan(
        scan_id=f"silo-t-{when:%Y%m%dT%H%M%SZ}",
        captured_at=f"{when:%Y-%m-%dT%H:%M:%SZ}",
        silo_id="silo-t",
        site=Site(np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float), 0.0),
        cameras=clouds,
        reconstruction={"grid_step_m": 0.05},
    )


def test_scan_directory_carries_hashes_config_and_version(tmp_path: Path):
    cache = AuditCache(AuditConfig(directory=tmp_path / "scans"), "silo-t")
    path = cache.write_scan(make_scan(1), {"silo": {"id": "silo-t"}, "note": "snapshot"})
    manifest = json.loads((path / "scan.json").read_text())
    assert manifest["format"] == "silo-scan/1"
    assert manifest["config"] == {"silo": {"id": "silo-t"}, "note": "snapshot"}
    assert manifest["software_version"]
    for camera in manifest["cameras"]:
        cloud = (path / camera["cloud"]).read_bytes()
        assert camera["cloud_sha256"] == hashlib.sha256(cloud).hexdigest()
    assert [c.points.shape for c in read_scan(path).cameras] == [(2000, 3), (2000, 3)]
    assert sorted(p.name for p in cache.directory.iterdir()) == [path.name]  # no staging left
    with pytest.raises(ScanError, match="never overwritten"):
        cache.write_scan(make_scan(1), {})


def test_retention_keeps_the_cache_within_max_bytes_oldest_first(tmp_path: Path):
    probe = AuditCache(AuditConfig(directory=tmp_path / "probe"), "silo-t")
    probe.write_scan(make_scan(0), {})
    one = probe.entries()[0].bytes
    max_bytes = int(4.5 * one)
    cache = AuditCache(
        AuditConfig(directory=tmp_path / "scans", max_bytes=max_bytes, max_age_days=3650), "silo-t"
    )
    ids = []
    for k in range(30):
        ids.append(cache.write_scan(make_scan(k), {}).name)
        baseline = set(ids[2:3])  # an alarm baseline, from the third scan on
        cache.enforce(protected=baseline, now=T0 + timedelta(hours=k))
        total = sum(e.bytes for e in cache.entries())
        assert total <= max_bytes
    kept = [e.scan_id for e in cache.entries()]
    assert kept == [ids[2], *ids[-3:]]  # the baseline, then the newest that fit


def test_retention_by_age(tmp_path: Path):
    cache = AuditCache(AuditConfig(directory=tmp_path / "scans", max_age_days=2), "silo-t")
    ids = [cache.write_scan(make_scan(k, when=T0 + timedelta(days=k)), {}).name for k in range(6)]
    removed = cache.enforce(protected={ids[0]}, now=T0 + timedelta(days=5, hours=1))
    assert removed == ids[1:4]  # older than 2 days, except the protected baseline
    assert [e.scan_id for e in cache.entries()] == [ids[0], *ids[4:]]


def test_disk_full_eviction_spares_protected(tmp_path: Path):
    cache = AuditCache(AuditConfig(directory=tmp_path / "scans"), "silo-t")
    ids = [cache.write_scan(make_scan(k), {}).name for k in range(21)]
    assert cache.evict_for_space(protected={ids[0]}) == ids[1:3]  # the oldest 10 %


def test_staging_left_by_a_crash_is_cleaned(tmp_path: Path):
    cache = AuditCache(AuditConfig(directory=tmp_path / "scans"), "silo-t")
    cache.write_scan(make_scan(1), {})
    stray = cache.directory / ".silo-t-20261101T070000Z.abc"
    stray.mkdir()
    (stray / "cam-0.ply").write_bytes(b"partial")
    assert [e.scan_id for e in cache.entries()] == ["silo-t-20261101T070000Z"]
    cache.enforce()
    assert not stray.exists()


def test_export_and_lookup(tmp_path: Path):
    cache = AuditCache(AuditConfig(directory=tmp_path / "scans"), "silo-t")
    scan_id = cache.write_scan(make_scan(1), {}).name
    out = cache.export(scan_id, tmp_path / "x.tar.gz")
    with tarfile.open(out) as tar:
        names = sorted(tar.getnames())
    assert names == [
        scan_id,
        f"{scan_id}/cam-0.ply",
        f"{scan_id}/cam-1.ply",
        f"{scan_id}/scan.json",
    ]
    for bad in ("nope", "../scans", f".{scan_id}"):
        with pytest.raises(ScanError):
            cache.find(bad)


def test_latest_result_is_the_newest_scan_that_has_one(tmp_path: Path):
    cache = AuditCache(AuditConfig(directory=tmp_path / "scans"), "silo-t")
    with pytest.raises(ValueError, match="no scan"):
        cache.latest_result()
    old, new = (cache.write_scan(make_scan(k, points=10), {}) for k in (1, 2))
    (old / "result.json").write_text(json.dumps({"scan_id": old.name}))
    assert cache.latest_result() == {"scan_id": old.name}  # the newest failed: no result
    (new / "result.json").write_text('{"scan_id": ')
    with pytest.raises(ValueError, match=str(new / "result.json")):
        cache.latest_result()


def test_differences_are_bit_exact_and_ignore_timings():
    a = {"volume_m3": 1.2345678901234567, "surface": {"max_z": 0.7}, "timings": {"x": 1.0}}
    b = {"volume_m3": 1.2345678901234567, "surface": {"max_z": 0.7}, "timings": {"x": 2.0}}
    assert differences(comparable(a), comparable(b)) == []
    c = dict(b, volume_m3=np.nextafter(1.2345678901234567, 2.0))
    (line,) = differences(comparable(a), comparable(c))
    assert line.startswith("volume_m3: published 1.2345678901234567 -> replayed 1.23456789012345")


def test_entries_are_read_again_only_where_a_directory_changed(tmp_path: Path):
    """A daemon lists its cache two or three times a scan (retention, pile ids, the page):
    a directory whose mtime has not moved is not read again, one that changed is (a result
    written into it counts its bytes, a removed scan goes, a new one comes)."""
    cache = AuditCache(AuditConfig(directory=tmp_path / "scans"), "silo-t")
    first, second = (cache.write_scan(make_scan(k, points=10), {}) for k in (1, 2))
    past = 1_000_000_000_000_000_000  # 2001: older than any fresh change
    for path in (first, second):
        os.utime(path, ns=(past, past))
    before = {e.scan_id: e.bytes for e in cache.entries()}
    assert set(before) == {first.name, second.name}

    # not read again while its mtime stands: another silo's manifest, put in place by hand
    # without moving the directory's mtime, is not seen
    manifest = json.loads((first / "scan.json").read_text())
    (first / "scan.json").write_text(json.dumps({**manifest, "silo_id": "silo-x"}))
    os.utime(first, ns=(past, past))
    assert [e.scan_id for e in cache.entries()] == [first.name, second.name]

    # what the agent writes moves it: read again
    write_atomic(second / "result.json", b'{"scan_id": "x"}\n')
    third = cache.write_scan(make_scan(3, points=10), {})
    shutil.rmtree(first)
    now = {e.scan_id: e.bytes for e in cache.entries()}
    assert set(now) == {second.name, third.name}
    assert now[second.name] == before[second.name] + len(b'{"scan_id": "x"}\n')
