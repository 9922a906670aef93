"""One scan path: a scan made by `silo-agent scan` or by the daemon replays identical, with and
without `[calibration] refine` or `level`, and every path keeps the summary the daemon
publishes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from silo_agent.analysis.summary import ScanSummary
from silo_agent.cli import main
from silo_agent.storage.audit import comparable
from silo_agent.telemetry.payloads import check_summary
from tests.support.agent import Daemon, write_config

REFINE = "\n[calibration]\nrefine = true\nlevel = false\n"
PLAIN = "\n[calibration]\nlevel = false\n"
PER_SCAN = {"plain": PLAIN, "refine": REFINE, "level": "\n[calibration]\nlevel = true\n"}


def _replay(directory: Path, capsys: pytest.CaptureFixture) -> str:
    status = main(["replay", str(directory)])
    out = capsys.readouterr().out
    assert status == 0, out
    return out


@pytest.mark.realsense
@pytest.mark.parametrize("per_scan", list(PER_SCAN))
def test_cli_scan_replays_identical_and_keeps_the_published_shape(
    tmp_path: Path, capsys: pytest.CaptureFixture, per_scan: str
) -> None:
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed")
    from tests.support.playback import grain_layer, playback_camera, playback_config

    cameras = [playback_camera(s, grain_layer(tmp_path, s)) for s in ("CAM-A", "CAM-B")]
    config = playback_config(tmp_path, "".join(cameras))
    config.write_text(config.read_text() + PER_SCAN[per_scan])
    assert main(["scan", "--config", str(config), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    directory = Path(report["scan_dir"])
    kept = json.loads((directory / "result.json").read_text())

    check_summary(ScanSummary.from_json(kept))  # what the daemon would publish
    assert kept["cameras"] == {"used": ["CAM-A", "CAM-B"], "failed": []}
    assert kept["degraded"] is False and kept["captured_at"].endswith("Z")
    # the snapshot's calibration was used
    assert ("refined" in kept["parameters"]) is (per_scan == "refine")
    assert ("leveled" in kept["parameters"]) is (per_scan == "level")
    manifest = json.loads((directory / "scan.json").read_text())
    assert manifest["config"]["calibration"]["refine"] is (per_scan == "refine")
    assert manifest["config"]["calibration"]["level"] is (per_scan == "level")
    assert "replay identical" in _replay(directory, capsys)

    # `process` of the same directory goes the same way: the same summary, nothing written
    assert main(["process", str(directory), "--json"]) == 0
    processed = json.loads(capsys.readouterr().out)
    assert processed.pop("scan_dir") == str(directory)  # which scan, in a batch's JSON Lines
    assert comparable(processed) == comparable(kept)


@pytest.mark.slow
def test_daemon_scan_with_refine_replays_identical(
    tmp_path: Path, broker, capsys: pytest.CaptureFixture
) -> None:
    config = write_config(tmp_path / "agent.toml", broker.port, tmp_path)
    config.write_text(config.read_text() + REFINE)
    agent = Daemon(config, tmp_path, "--scans", "1")
    try:
        assert agent.wait(120) == 0, agent.log_path.read_text()[-2000:]
    finally:
        agent.kill()
    (scan_id,) = [e["scan_id"] for e in agent.log() if e.get("event") == "scan finished"]
    directory = tmp_path / "scans" / scan_id
    assert "refined" in json.loads((directory / "result.json").read_text())["parameters"]
    assert "replay identical" in _replay(directory, capsys)


def test_a_bad_config_snapshot_in_a_scan_is_one_line_naming_the_key(
    scan_dir: Path, capsys: pytest.CaptureFixture
) -> None:
    manifest = json.loads((scan_dir / "scan.json").read_text())
    manifest["config"] = {"calibration": {"refine": "sometimes"}}
    (scan_dir / "scan.json").write_text(json.dumps(manifest))
    assert main(["process", str(scan_dir)]) == 65
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "scan.json: config.calibration: refine" in err
