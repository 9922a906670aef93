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

from silo_agent.capture.recording import write_recording
from silo_agent.cli import main
from silo_agent.scan import read_scan

INTRINSICS = {"width": 160, "height": 96, "fx": 80.0, "fy": 80.0, "ppx": 79.5, "ppy": 47.5}


def _connected_serials() -> set[str]:
    return {d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()}


def _write_config(tmp_path: Path, cameras: str) -> Path:
    path = tmp_path / "silo.toml"
    path.write_text(
        f"""
[silo]
id = "silo-cli"
region = [[-1.5, -1.5], [1.5, -1.5], [1.5, 1.5], [-1.5, 1.5]]
floor_z = 0.0
bulk_density_t_m3 = 0.77

[reconstruction]
grid_step_m = 0.05

[audit]
directory = "{tmp_path / "audit"}"
{cameras}
"""
    )
    return path


def _camera(serial: str, playback: Path, **keys: object) -> str:
    extra = "".join(f"{k} = {json.dumps(v)}\n" for k, v in keys.items())
    return f"""
[[cameras]]
serial = "{serial}"
source = "playback"
playback = "{playback}"
# looking straight down from 2 m
extrinsic = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 2.0], [0, 0, 0, 1]]
warmup_frames = 2
frames = 3
timeout_s = 1.0
{extra}"""


def _grain_layer(tmp_path: Path, serial: str, frames: int = 5) -> Path:
    """A flat grain surface 0.5 m above the floor, seen from 2 m: 1.5 m away, with D455-like
    depth noise (a few mm at 1.5 m)."""
    path = tmp_path / f"{serial}.db3"
    rng = np.random.default_rng(len(serial))
    depth = [
        np.round(1500 + rng.normal(0, 4.0, (96, 160))).astype(np.uint16) for _ in range(frames)
    ]
    write_recording(path, serial, INTRINSICS, depth, 0.001, 30)
    return path


def test_scan_end_to_end_from_playback(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    config = _write_config(
        tmp_path,
        _camera("CAM-A", _grain_layer(tmp_path, "CAM-A"))
        + _camera("CAM-B", _grain_layer(tmp_path, "CAM-B")),
    )

    assert main(["scan", "--config", str(config), "--out", str(tmp_path / "scans"), "--json"]) == 0

    report = json.loads(capsys.readouterr().out)
    directory = Path(report["scan_dir"])
    assert directory.parent == tmp_path / "scans"
    assert directory.name.startswith("silo-cli-") and directory.name.endswith("Z")
    assert report["degraded"] is False and report["failures"] == []
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
    config = _write_config(
        tmp_path,
        _camera("GOOD", _grain_layer(tmp_path, "GOOD"))
        + _camera("SHORT", _grain_layer(tmp_path, "SHORT", frames=2)),
    )

    assert main(["scan", "--config", str(config), "--json"]) == 0  # into audit.directory

    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["degraded"] is True
    assert [f["serial"] for f in report["failures"]] == ["SHORT"]
    assert "camera SHORT: timed out" in captured.err
    directory = Path(report["scan_dir"])
    assert directory.parent == tmp_path / "audit"
    manifest = json.loads((directory / "scan.json").read_text())
    assert manifest["degraded"] is True
    assert [c["serial"] for c in manifest["cameras"]] == ["GOOD"]


def test_scan_with_no_camera_left_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = _write_config(tmp_path, _camera("GONE", tmp_path / "missing.db3"))
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
    config = _write_config(tmp_path, _camera("PB", _grain_layer(tmp_path, "PB")))
    assert main(["record", "--config", str(config), "--out", str(tmp_path / "rec")]) == 1
    assert "no live cameras" in capsys.readouterr().err


def test_record_names_a_camera_that_is_not_connected(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    config = _write_config(
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
