"""A camera that measures nothing (its cloud has no point left) is a failed camera: the scan
goes on with the others, marked degraded, and stays readable. Simulated cameras, a real audit
cache and the real CLI; the camera that sees nothing looks straight up at an open sky."""

from __future__ import annotations

import json
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import pytest

from silo_agent.cli import main
from silo_agent.config import load_config
from silo_agent.scan import read_scan
from silo_agent.service.pipeline import Pipeline
from silo_agent.storage.audit import AuditCache
from silo_agent.telemetry.prometheus import Metrics
from silo_agent.telemetry.publisher import MemoryPublisher
from tests.support.agent import SILO, write_config

UNUSED_PORT = 9  # nothing here connects to a broker
SKY = "sim-SKY"
# the camera's optical axis (+z) along the silo's +z, 4 m up over the open bay: nothing in view
SKY_CAMERA = f"""
[[cameras]]
serial = "{SKY}"
source = "sim"
extrinsic = [[1, 0, 0, 0], [0, 1, 0, -2.5], [0, 0, 1, 4.0], [0, 0, 0, 1]]
width = 424
height = 240
"""


def _config(tmp_path: Path, cameras: tuple[tuple[str, str | None], ...]) -> Path:
    """The test daemon's config on the simulator with `cameras` and the sky camera last."""
    path = write_config(tmp_path / "agent.toml", UNUSED_PORT, tmp_path, cameras=cameras)
    path.write_text(path.read_text() + SKY_CAMERA)
    return path


def test_a_camera_without_points_fails_and_the_scan_stays_readable(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = _config(tmp_path, cameras=(("sim-A2", "A2"), ("sim-A6", "A6")))
    out = tmp_path / "out"

    assert main(["scan", "--config", str(config), "--out", str(out), "--json"]) == 0

    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert f"warning: camera {SKY}: no valid depth pixels" in captured.err
    assert report["degraded"] is True
    assert report["cameras"]["used"] == ["sim-A2", "sim-A6"]
    (failed,) = report["cameras"]["failed"]
    assert failed["serial"] == SKY and "no valid depth pixels" in failed["error"]
    directory = Path(report["scan_dir"])
    manifest = json.loads((directory / "scan.json").read_text())
    assert manifest["degraded"] is True
    assert manifest["failures"] == [failed]
    assert not (directory / f"{SKY}.ply").exists()
    assert [c.serial for c in read_scan(directory).cameras] == ["sim-A2", "sim-A6"]

    assert main(["process", str(directory), "--json"]) == 0
    processed = json.loads(capsys.readouterr().out)
    assert processed["valid"] is True and processed["cameras"]["failed"] == [failed]
    assert main(["replay", str(directory)]) == 0
    assert "identical" in capsys.readouterr().out


def test_no_camera_with_points_writes_no_scan(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = _config(tmp_path, cameras=())
    out = tmp_path / "out"

    assert main(["scan", "--config", str(config), "--out", str(out)]) == 1

    err = capsys.readouterr().err
    assert f"camera {SKY}: no valid depth pixels" in err
    assert "no camera delivered a cloud; no scan written" in err
    assert list(out.iterdir() if out.exists() else []) == []


def test_the_daemon_reports_the_camera_failed_and_raises_the_camera_alarm(
    tmp_path: Path,
) -> None:
    config = load_config(_config(tmp_path, cameras=(("sim-A2", "A2"),)), service=True)
    publisher = MemoryPublisher()
    cache = AuditCache(config.audit, config.silo.id)
    pipeline = Pipeline(config, publisher, cache, Metrics())
    started = datetime(2026, 11, 22, 2, 0, 0, tzinfo=UTC)

    outcome = pipeline.run(
        f"{SILO}-{started:%Y%m%dT%H%M%SZ}", started, time.monotonic() + 60, threading.Event()
    )

    assert outcome.outcome == "ok" and outcome.directory is not None
    assert outcome.summary is not None and outcome.summary.degraded
    assert [c.serial for c in outcome.summary.cameras.failed] == [SKY]
    state, error = publisher.cameras[SKY]
    assert state == "failed" and error is not None and "no valid depth pixels" in error
    assert publisher.cameras["sim-A2"] == ("ok", None)
    assert ("camera", "raised") in [(e.type, e.state) for e in publisher.alarms()]
    assert [c.serial for c in read_scan(outcome.directory).cameras] == ["sim-A2"]
