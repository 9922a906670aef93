"""`silo-agent devices`, `scan` and `record` through real librealsense playback (no mocks)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

# ruff: noqa: E402 (the imports below need pyrealsense2, or this module is skipped first)
# pyrealsense2 has x86-64 wheels only: elsewhere these tests are skipped, the rest runs
rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed")
pytestmark = pytest.mark.realsense

from silo_agent.cli import main
from silo_agent.scan import read_scan
from tests.support.playback import grain_layer, playback_camera, playback_config


def _connected_serials() -> set[str]:
    return {d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()}


def test_scan_end_to_end_from_playback(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    config = playback_config(
        tmp_path,
        playback_camera("CAM-A", grain_layer(tmp_path, "CAM-A"))
        + playback_camera("CAM-B", grain_layer(tmp_path, "CAM-B")),
    )

    assert main(["scan", "--config", str(config), "--out", str(tmp_path / "scans"), "--json"]) == 0

    report = json.loads(capsys.readouterr().out)
    directory = Path(report["scan_dir"])
    assert directory.parent == tmp_path / "scans"
    assert directory.name.startswith("silo-cli-") and directory.name.endswith("Z")
    assert report["degraded"] is False and report["cameras"]["failed"] == []
    scan = read_scan(directory)
    assert scan.scan_id == directory.name == report["scan_id"]
    assert [c.serial for c in scan.cameras] == ["CAM-A", "CAM-B"]
    assert scan.reconstruction["grid_step_m"] == 0.05
    assert scan.cameras[0].extra["frames_aggregated"] == 3
    assert scan.cameras[0].extra["firmware"] == "5.16.0.1"
    assert np.median(scan.cameras[0].points_in_silo()[:, 2]) == pytest.approx(0.5, abs=0.002)
    # the flat 0.5 m layer over the part of the region the cameras see
    assert report["grid_step_m"] == 0.05
    assert report["surface"]["mean_z"] == pytest.approx(0.5, abs=0.01)
    assert report["volume_m3"] > 0
    assert report["mass_t"] == pytest.approx(report["volume_m3"] * 0.77)
    assert json.loads((directory / "result.json").read_text())["scan_id"] == scan.scan_id


def test_scan_with_a_failing_camera_is_degraded(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = playback_config(
        tmp_path,
        playback_camera("GOOD", grain_layer(tmp_path, "GOOD"))
        + playback_camera("SHORT", grain_layer(tmp_path, "SHORT", frames=2)),
    )

    assert main(["scan", "--config", str(config), "--json"]) == 0  # into audit.directory

    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["degraded"] is True
    assert [f["serial"] for f in report["cameras"]["failed"]] == ["SHORT"]
    assert "camera SHORT: timed out" in captured.err
    directory = Path(report["scan_dir"])
    assert directory.parent == tmp_path / "audit"
    manifest = json.loads((directory / "scan.json").read_text())
    assert manifest["degraded"] is True
    assert [c["serial"] for c in manifest["cameras"]] == ["GOOD"]


def test_scan_with_no_camera_left_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = playback_config(tmp_path, playback_camera("GONE", tmp_path / "missing.db3"))
    assert main(["scan", "--config", str(config), "--out", str(tmp_path / "scans")]) == 1
    err = capsys.readouterr().err
    assert "camera GONE: recording" in err and "no scan written" in err
    assert not (tmp_path / "scans").exists()


def test_devices_lists_what_is_connected(capsys: pytest.CaptureFixture) -> None:
    status = main(["devices"])
    out = capsys.readouterr().out
    serials = _connected_serials()
    if serials:
        assert status == 0 and all(s in out for s in serials)
    else:
        assert status == 1 and out.strip() == "no RealSense devices found"


def test_record_refuses_a_config_without_live_cameras(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = playback_config(tmp_path, playback_camera("PB", grain_layer(tmp_path, "PB")))
    assert main(["record", "--config", str(config), "--out", str(tmp_path / "rec")]) == 1
    assert "no live cameras" in capsys.readouterr().err


def test_record_names_a_camera_that_is_not_connected(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = playback_config(
        tmp_path,
        """
[[cameras]]
serial = "999999999999"
extrinsic = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
""",
    )
    assert main(["record", "--config", str(config), "--out", str(tmp_path / "rec")]) == 1
    assert "camera 999999999999: not connected" in capsys.readouterr().err
    assert not (tmp_path / "rec" / "999999999999.db3").exists()


def test_record_wants_a_positive_duration(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as info:
        main(["record", "--config", "x.toml", "--out", str(tmp_path), "--seconds", "-3"])
    assert info.value.code == 2
    assert "want a duration in seconds > 0, got '-3'" in capsys.readouterr().err
