"""Hostile and unlucky input, against the real CLI, the real daemon and real filesystems:
every bad config, scan file or full disk ends in exit 0, 65 or 78 with one line naming the
file and key, never a traceback, a hang, unbounded memory or a deletion of what the agent
did not write (docs/limits.md lists each case)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
from structlog.testing import capture_logs

from silo_agent.config import AuditConfig
from silo_agent.storage.audit import AuditCache
from tests.support.agent import BASE, Daemon, write_config
from tests.support.cli import run_cli
from tests.support.mqtt import validate_json

EX_DATAERR, EX_CONFIG = 65, 78  # sysexits.h, written out: not read from the code under test
CLOUD_POINT_LIMIT = 10_000_000  # documented in docs/limits.md


def _one_line_failure(done: subprocess.CompletedProcess, status: int, *fragments: str) -> str:
    assert done.returncode == status, done.stderr
    assert "Traceback" not in done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, done.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


# ---------------------------------------------------------------- configuration


def _config(tmp_path: Path, **sections) -> Path:
    return write_config(tmp_path / "agent.toml", 1, tmp_path, **sections)


def _replace(path: Path, old: str, new: str) -> Path:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    return path


def _append(path: Path, text: str) -> Path:
    path.write_text(path.read_text() + "\n" + text + "\n")
    return path


def _latin1(path: Path) -> Path:
    """The silo id with an é as Latin-1 writes it: one byte 0xe9 (offset 18, after
    `[silo]\\nid = "silo-`), no UTF-8 sequence."""
    path.write_bytes(path.read_bytes().replace(b'id = "silo-d"', b'id = "silo-\xe9"'))
    return path


def _under_a_file(tmp_path: Path) -> Path:
    regular = tmp_path / "a-file"
    regular.write_text("not a directory\n")
    return regular


BAD_CONFIGS = {
    "audit directory under a regular file": (
        lambda t: _config(t, audit={"directory": str(_under_a_file(t) / "scans")}),
        ["audit.directory", "a-file is not a directory"],
    ),
    "audit directory in /proc": (
        lambda t: _config(t, audit={"directory": "/proc/silo-agent-test/scans"}),
        ["audit.directory", "cannot create files in /proc"],
    ),
    "outbox under a regular file": (
        lambda t: _replace(
            _config(t), str(t / "outbox.sqlite"), str(_under_a_file(t) / "outbox.sqlite")
        ),
        ["mqtt.outbox_path", "a-file is not a directory"],
    ),
    "outbox is a directory": (
        lambda t: _replace(_config(t), str(t / "outbox.sqlite"), str(t)),
        ["mqtt.outbox_path", "is not a regular file"],
    ),
    "interval overflowing a timedelta": (
        lambda t: _config(t, schedule={"interval_s": 1e300}),
        ["schedule.interval_s", "less than or equal"],
    ),
    "boolean as a number": (
        lambda t: _config(t, schedule={"interval_s": True}),
        ["schedule.interval_s", "valid number"],
    ),
    "string as a port": (
        lambda t: _replace(_config(t), "port = 1\n", 'port = "18951"\n'),
        ["mqtt.port", "valid integer"],
    ),
    "missing TLS CA file": (
        lambda t: _append(_config(t), f'[mqtt.tls]\nca_file = "{t / "ca.pem"}"'),
        ["mqtt.tls.ca_file", "ca.pem does not exist"],
    ),
    "missing TLS client certificate": (
        lambda t: _append(
            _config(t), f'[mqtt.tls]\ncert_file = "{t / "c.pem"}"\nkey_file = "{_under_a_file(t)}"'
        ),
        ["mqtt.tls.cert_file", "c.pem does not exist"],
    ),
    "TLS key that is a directory": (
        lambda t: _append(
            _config(t), f'[mqtt.tls]\ncert_file = "{_under_a_file(t)}"\nkey_file = "{t}"'
        ),
        ["mqtt.tls.key_file", "is not a regular file"],
    ),
    "empty broker host": (
        lambda t: _replace(_config(t), 'host = "127.0.0.1"', 'host = ""'),
        ["mqtt.host", "want a host name or IP address, got ''"],
    ),
    "sim view that does not exist": (
        lambda t: _replace(_config(t), 'view = "A2"', 'view = "A9"'),
        ["cameras.0.view", "unknown view 'A9'"],
    ),
    "grid too fine for the region": (
        lambda t: _replace(_config(t), "grid_step_m = 0.05", "grid_step_m = 0.002"),
        ["reconstruction.grid_step_m", "9,000,000 cells", "limit of 4,000,000"],
    ),
    "live map grid too fine for the region": (  # check-config passed it; a session's start
        # then stopped the agent (the live map past the cell limit, raised in its main loop)
        lambda t: _append(
            _replace(
                _config(t),
                "region = [[-3.0, -3.0], [3.0, -3.0], [3.0, 3.0], [-3.0, 3.0]]",
                "region = [[-8.0, -8.0], [8.0, -8.0], [8.0, 8.0], [-8.0, 8.0]]",
            ),
            "[live]\ngrid_step_m = 0.006",
        ),
        ["live.grid_step_m", "7,112,889 cells", "limit of 4,000,000"],
    ),
    "camera translation beyond float32": (
        lambda t: _replace(
            _config(t),
            'view = "A2"',
            'view = "A2"\nrotate_deg = [0, 0, 0]\ntranslate_m = [1e39, 0, 0]',
        ),
        ["cameras.0", "translation beyond"],
    ),
    "not UTF-8": (
        lambda t: _latin1(_config(t)),
        ["agent.toml: not UTF-8", "byte 0xe9 at offset 18"],
    ),
}


@pytest.mark.parametrize("case", BAD_CONFIGS)
def test_bad_config_fails_check_config_with_78_naming_the_key(tmp_path: Path, case: str):
    make, fragments = BAD_CONFIGS[case]
    config = make(tmp_path)
    _one_line_failure(run_cli("check-config", str(config)), EX_CONFIG, str(config), *fragments)
    assert not (tmp_path / "scans").exists()  # checking wrote nothing


@pytest.mark.parametrize(
    "case",
    [
        "audit directory under a regular file",
        "boolean as a number",
        "missing TLS CA file",
        "not UTF-8",
    ],
)
def test_bad_config_stops_run_with_78_before_anything_starts(tmp_path: Path, case: str):
    make, fragments = BAD_CONFIGS[case]
    config = make(tmp_path)
    _one_line_failure(run_cli("run", "--config", str(config)), EX_CONFIG, *fragments)
    assert not (tmp_path / "outbox.sqlite").exists()


def test_offline_process_does_not_need_the_services_directories(tmp_path: Path, scan_dir: Path):
    config = BAD_CONFIGS["audit directory under a regular file"][0](tmp_path)
    done = run_cli("process", str(scan_dir), "--config", str(config), "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["volume_m3"] > 0


def test_integers_still_count_where_a_float_belongs(tmp_path: Path):
    config = _config(tmp_path, schedule={"interval_s": 60, "misfire_grace_s": 30})
    done = run_cli("check-config", str(config))
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""


def test_a_cron_that_never_fires_is_a_warning(tmp_path: Path):
    config = _config(tmp_path, schedule={"cron": "0 6 30 2 *"})  # 30 February
    done = run_cli("check-config", str(config))
    assert done.returncode == 0, done.stderr
    assert "schedule.cron: '0 6 30 2 *' never fires" in done.stderr


def test_non_utf8_config_on_sighup_is_rejected_and_the_daemon_goes_on(
    tmp_path: Path, broker, collector_factory
):
    config = write_config(
        tmp_path / "agent.toml", broker.port, tmp_path, schedule={"scan_at_start": False}
    )
    col = collector_factory(broker, [f"{BASE}/#"])
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("agent started")
        col.wait_for(  # `online` comes after the agent subscribed: the request below is not lost
            lambda ms: any(
                m.topic == f"{BASE}/status" and json.loads(m.payload)["state"] == "online"
                for m in ms
            )
        )
        config.write_bytes(config.read_bytes() + b"\n# caf\xe9 latin-1\n")
        agent.signal(signal.SIGHUP)
        (rejected,) = agent.wait_log("config reload rejected, keeping the running config")
        assert "not UTF-8" in rejected["error"] and "offset" in rejected["error"]
        col.publish(f"{BASE}/cmd/scan", b'{"request_id": "r-1"}')  # the old config scans
        agent.wait_log("scan finished")
        agent.signal(signal.SIGTERM)
        assert agent.wait(20) == 0
    finally:
        agent.kill()


# ---------------------------------------------------------------- scan directories and files


def _manifest(scan_dir: Path) -> dict:
    return json.loads((scan_dir / "scan.json").read_text())


def _first_cloud(scan_dir: Path) -> Path:
    return scan_dir / _manifest(scan_dir)["cameras"][0]["cloud"]


def _ply_header(*lines: str) -> bytes:
    return (
        "\n".join(["ply", "format binary_little_endian 1.0", *lines, "end_header"]) + "\n"
    ).encode()


def _process(scan_dir: Path, *args: str) -> subprocess.CompletedProcess:
    return run_cli("process", str(scan_dir), "--json", *args)


def test_fifo_cloud_is_refused_not_waited_on(scan_dir: Path):
    cloud = _first_cloud(scan_dir)
    cloud.unlink()
    os.mkfifo(cloud)
    _one_line_failure(_process(scan_dir), EX_DATAERR, str(cloud), "not a regular file")


def test_device_symlink_cloud_is_refused_not_read_for_ever(scan_dir: Path):
    cloud = _first_cloud(scan_dir)
    cloud.unlink()
    cloud.symlink_to("/dev/zero")
    _one_line_failure(_process(scan_dir), EX_DATAERR, str(cloud), "not a regular file")


@pytest.mark.parametrize(
    ("header", "fragment"),
    [
        (
            [
                "element vertex 1",
                "property float x",
                "property float y",
                "property float z",
                "property float x",
            ],
            "property 'x' is repeated",
        ),
        (["element"], "bad element line 'element'"),
    ],
)
def test_malformed_ply_header_is_one_line(scan_dir: Path, header, fragment):
    cloud = _first_cloud(scan_dir)
    cloud.write_bytes(_ply_header(*header) + bytes(16))
    _one_line_failure(_process(scan_dir), EX_DATAERR, str(cloud), fragment)


def test_cloud_past_the_point_limit_is_refused_before_reading(scan_dir: Path):
    cloud = _first_cloud(scan_dir)
    count = CLOUD_POINT_LIMIT + 1
    header = _ply_header(
        f"element vertex {count}", "property float x", "property float y", "property float z"
    )
    with open(cloud, "wb") as out:  # sparse: the header announces 120 MB it would be read for
        out.write(header)
        out.truncate(len(header) + 12 * count)
    _one_line_failure(_process(scan_dir), EX_DATAERR, str(cloud), f"{count:,} points", "limit")


def test_oversized_manifest_is_refused(scan_dir: Path):
    data = _manifest(scan_dir)
    data["padding"] = " " * (17 * 2**20)
    (scan_dir / "scan.json").write_text(json.dumps(data))
    _one_line_failure(_process(scan_dir), EX_DATAERR, "scan.json", "larger than the limit")


def test_deeply_nested_manifest_is_one_line(scan_dir: Path):
    text = (scan_dir / "scan.json").read_text().rstrip().removesuffix("}")
    (scan_dir / "scan.json").write_text(text + ', "deep": ' + "[" * 100_000 + "]" * 100_000 + "}")
    _one_line_failure(_process(scan_dir), EX_DATAERR, "scan.json", "nested too deeply")


def test_extrinsic_overflowing_float32_is_rejected_not_dropped(scan_dir: Path):
    data = _manifest(scan_dir)
    data["cameras"][1]["extrinsic"][0][3] = 1e39  # finite as float64, inf as float32
    (scan_dir / "scan.json").write_text(json.dumps(data))
    _one_line_failure(_process(scan_dir), EX_DATAERR, "cameras.1.extrinsic", "translation beyond")


def test_duplicate_serials_in_the_manifest_are_refused(scan_dir: Path):
    data = _manifest(scan_dir)
    data["cameras"][2]["serial"] = data["cameras"][0]["serial"]
    (scan_dir / "scan.json").write_text(json.dumps(data))
    _one_line_failure(
        _process(scan_dir), EX_DATAERR, "cameras", "repeated", data["cameras"][0]["serial"]
    )


def test_grid_past_the_cell_limit_is_refused_before_allocating(scan_dir: Path):
    # the smallest step allowed over the 5 m region: 20.7 million cells, several GB if tried
    _one_line_failure(
        _process(scan_dir, "--grid-step", "0.0011"), EX_DATAERR, "cells", "limit of 4,000,000"
    )


# ---------------------------------------------------------------- audit cache


def _cloud(k: int):
    from silo_agent.scan import CameraCloud, Scan, Site

    def scan(silo: str, when: str) -> Scan:
        points = np.random.default_rng(k).normal(0, 1, (500, 3)).astype(np.float32)
        return Scan(
            scan_id=f"{silo}-{when}",
            captured_at="2026-11-01T06:00:00Z",
            silo_id=silo,
            site=Site(np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float), 0.0),
            cameras=[CameraCloud("cam-0", points, np.eye(4))],
        )

    return scan


def test_retention_removes_only_this_silos_scans_and_logs_each(tmp_path: Path):
    root = tmp_path / "scans"
    ours = AuditCache(AuditConfig(directory=root, max_bytes=1), "silo-a")
    mine = [
        ours.write_scan(_cloud(k)("silo-a", f"2026110{k}T060000Z"), {}).name for k in range(1, 4)
    ]
    neighbour = AuditCache(AuditConfig(directory=root), "silo-b")
    theirs = neighbour.write_scan(_cloud(9)("silo-b", "20261101T060000Z"), {})
    impostor = root / "silo-a-20261101T070000Z"  # our name, another silo's manifest
    impostor.mkdir()
    (impostor / "scan.json").write_text(
        json.dumps({"silo_id": "silo-b", "captured_at": "2026-11-01T07:00:00Z"})
    )
    keep = [
        root / ".git" / "HEAD",
        root / ".keepme" / "x",
        root / ".silo-b-20261101T080000Z.ab" / "c.ply",
        root / "notes.txt",
    ]
    for path in keep:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("not the agent's\n")
    staging = root / ".silo-a-20261101T090000Z.k3j_x"  # ours, left by a crash mid-write
    staging.mkdir()
    with capture_logs() as logs:
        removed = ours.enforce()
    assert removed == mine
    assert not any((root / m).exists() for m in mine) and not staging.exists()
    assert all(p.exists() for p in keep) and theirs.exists() and impostor.exists()
    logged = [e.get("scan_id") or e.get("path") for e in logs if "removed" in e["event"]]
    assert sorted(logged) == sorted([*mine, str(staging)])


def test_a_result_lost_to_a_full_disk_raises_the_cache_alarm(
    tmp_path: Path, broker, collector_factory
):
    """Real tmpfs out of inodes: the raw scan fits, its result.json / height map do not."""
    from tests.support.faults import leave_inodes, tmpfs

    with tmpfs(tmp_path / "disk", "20m,nr_inodes=64") as disk:
        scans = disk / "scans"
        scans.mkdir()
        leave_inodes(disk, 4)  # room for the raw scan: staging dir, 2 clouds, scan.json
        config = write_config(
            tmp_path / "agent.toml", broker.port, tmp_path, audit={"directory": str(scans)}
        )
        col = collector_factory(broker, [f"{BASE}/#"])
        agent = Daemon(config, tmp_path, "--scans", "1")
        try:
            assert agent.wait(90) == 0
        finally:
            agent.kill()
        log = agent.log()
        (finished,) = [e for e in log if e.get("event") == "scan finished"]
        (kept,) = [p for p in scans.iterdir() if not p.name.startswith(".")]
        assert kept.name == finished["scan_id"] and not (kept / "result.json").exists()
        assert any(e.get("event") == "cannot keep the result with the scan" for e in log)
        col.wait_for(lambda ms: any(m.topic == f"{BASE}/alarm" for m in ms))
        (alarm,) = [validate_json(m.payload) for m in col.on(f"{BASE}/alarm")]
        assert (alarm["type"], alarm["state"]) == ("cache", "raised")
        assert alarm["scan_id"] == finished["scan_id"]


# ---------------------------------------------------------------- service


def test_systemd_unit_stops_restarting_on_bad_files_and_bounds_memory():
    unit = (Path(__file__).parent.parent / "systemd" / "silo-agent.service").read_text()
    settings = dict(
        line.split("=", 1) for line in unit.splitlines() if "=" in line and not line.startswith("#")
    )
    assert set(settings["RestartPreventExitStatus"].split()) == {"65", "78"}
    assert settings["MemoryMax"].rstrip("G").isdigit()
