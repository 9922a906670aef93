"""`calibrate --write`: the config rewrite keeps comments, backs up, validates and round-trips;
the command line names unmatched serials and bad configs."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from silo_agent.base.exits import CONFIG_ERROR as EX_CONFIG
from silo_agent.calibrate import CalibrationError, rewrite_config_text, write_calibrated_config
from silo_agent.config import load_config, parse_config
from silo_agent.grid.geometry import transform_from_euler
from silo_agent.scan import write_scan
from tests.support.calib import render
from tests.support.cli import run_cli

CONFIG = """\
# site config -- keep this comment
[silo]
id = "sim"                     # the silo
region = [[-2.2, -2.2], [2.2, -2.2], [2.2, 2.2], [-2.2, 2.2]]
floor_z = 0.0
ceiling_z = 1.5

[[cameras]]
serial = "cam-matrix"          # matrix form
extrinsic = [[1, 0, 0, 0],     # row 0
             [0, 1, 0, 0],
             [0, 0, 1, 0], [0, 0, 0, 1]]   # trailing comment
width = 848

[[cameras]]
# paper form
serial = "cam-euler"
rotate_deg = [0, 186, -5]      # Appendix A, T1
translate_m = [0.2, 0, -5.2]   # metres

[[cameras]]
serial = "cam-view"
source = "sim"
view = "A1"                    # placed by its view

[calibration]
drift_consecutive = 3          # scans in a row
"""


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return transform_from_euler(rng.uniform(-180, 180, 3) * [0.4, 0.4, 1], rng.normal(0, 2, 3))


def test_rewrite_keeps_comments_and_reproduces_the_extrinsics(tmp_path: Path) -> None:
    poses = {"cam-matrix": _pose(1), "cam-euler": _pose(2), "cam-view": _pose(3)}
    path = tmp_path / "silo.toml"
    path.write_text(CONFIG)
    backup = write_calibrated_config(path, poses)
    assert backup.read_text() == CONFIG
    assert backup.name.startswith("silo.toml.") and backup.suffix == ".bak"
    new = path.read_text()
    for line in CONFIG.splitlines():
        if "#" in line and "row 0" not in line:
            assert line[line.index("#") :] in new  # every comment kept
    assert "rotate_deg = [" in new and "translate_m = [" in new
    assert "0, 186, -5" not in new
    config = load_config(path)
    for camera in config.cameras:
        np.testing.assert_allclose(camera.extrinsic_matrix(), poses[camera.serial], atol=1e-7)
    by_serial = {c.serial: c for c in config.cameras}
    assert by_serial["cam-euler"].extrinsic is None  # kept in the paper's form
    assert by_serial["cam-matrix"].width == 848
    assert config.calibration.drift_consecutive == 3
    # everything outside the camera poses is byte-identical
    untouched = [
        line
        for line in CONFIG.splitlines()
        if not line.lstrip().startswith(("extrinsic", "[0,", "rotate", "translate"))
    ]
    assert all(line in new.splitlines() for line in untouched)


def test_rewrite_of_an_unknown_serial_is_refused() -> None:
    with pytest.raises(CalibrationError, match="no \\[\\[cameras\\]\\] table with serial nope"):
        rewrite_config_text(CONFIG, {"nope": np.eye(4)})


def test_rewritten_text_validates() -> None:
    text = rewrite_config_text(CONFIG, {"cam-matrix": _pose(4)})
    parse_config(tomllib.loads(text), "rewritten")
    assert text.count("[[cameras]]") == 3


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory) -> Path:
    return write_scan(render(["A1", "A3"], seed=2), tmp_path_factory.mktemp("calib") / "scan")


def _config_for(tmp_path: Path, serials: list[str]) -> Path:
    cameras = "".join(
        f'\n[[cameras]]\nserial = "{s}"   # {s}\nsource = "sim"\nview = "{s[4:]}"\n'
        for s in serials
    )
    path = tmp_path / "c.toml"
    path.write_text(CONFIG.split("[[cameras]]")[0] + cameras)
    return path


def test_cli_calibrate_write_round_trip(tmp_path: Path, scan_dir: Path) -> None:
    """The rewritten config keeps the installed file's mode, owner and group (here the
    service's, as docs/operations.md installs it root:silo-agent 0640): written by root it
    had come back root:root and the service could no longer read its own config."""
    import os

    config = _config_for(tmp_path, ["sim-A1", "sim-A3"])
    service = 65534  # nobody / nogroup: any owner and group but the writer's (root)
    os.chown(config, service, service)
    config.chmod(0o640)
    done = run_cli(
        "calibrate",
        "--config",
        str(config),
        "--scan",
        str(scan_dir),
        "--floor",
        "--write",
        "--json",
    )
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["config_written"] and Path(out["backup"]).exists()
    assert set(out["registration_residual_m"]) == {"sim-A1|sim-A3"}
    written = {c.serial: c.extrinsic_matrix() for c in load_config(config).cameras}
    for camera in out["cameras"]:
        np.testing.assert_allclose(written[camera["serial"]], camera["extrinsic"], atol=1e-7)
        assert camera["leveled_by"] == "floor"
    assert "# sim-A1" in config.read_text()
    kept = config.stat()
    assert (kept.st_uid, kept.st_gid, kept.st_mode & 0o777) == (service, service, 0o640)


def test_cli_names_unmatched_serials_and_bad_configs(tmp_path: Path, scan_dir: Path) -> None:
    config = _config_for(tmp_path, ["sim-A1", "sim-A9"])
    config.write_text(config.read_text().replace('view = "A9"', 'view = "A5"'))  # A9 is no view
    done = run_cli("calibrate", "--config", str(config), "--scan", str(scan_dir))
    assert done.returncode == 65
    assert "sim-A3" in done.stderr and "sim-A9" in done.stderr
    done = run_cli("calibrate", "--config", str(config), "--scan", str(tmp_path / "none"))
    assert done.returncode == 65 and str(tmp_path / "none") in done.stderr
    config.write_text(config.read_text() + "\n[calibration]\ndrift_consecutive = 0\n")
    done = run_cli("calibrate", "--config", str(config), "--scan", str(scan_dir))
    assert done.returncode == EX_CONFIG
    assert "calibration.drift_consecutive" in done.stderr


def test_cli_refuses_a_scan_of_another_silo(tmp_path: Path, scan_dir: Path) -> None:
    """A scan whose manifest names another silo (same serials, same scene): refused with exit 65
    and one line naming the manifest and both silo ids, before anything is calibrated or
    written (it had proposed, and with --write written, poses from the other silo's scan)."""
    import shutil

    other = tmp_path / "other"
    shutil.copytree(scan_dir, other)
    manifest = json.loads((other / "scan.json").read_text())
    (other / "scan.json").write_text(json.dumps({**manifest, "silo_id": "silo-b"}))
    config = _config_for(tmp_path, ["sim-A1", "sim-A3"])
    text = config.read_text()
    for scans in ([other], [scan_dir, other]):
        args = [a for d in scans for a in ("--scan", str(d))]
        done = run_cli("calibrate", "--config", str(config), *args, "--floor", "--write", "--json")
        assert done.returncode == 65 and done.stdout == ""
        (line,) = done.stderr.splitlines()
        assert line.startswith(f"silo-agent: {other / 'scan.json'}: silo_id 'silo-b' ")
        assert "silo.id 'sim'" in line
        assert config.read_text() == text and sorted(p.name for p in tmp_path.iterdir()) == [
            "c.toml",
            "other",
        ]


@pytest.mark.slow
def test_cli_calibrate_capture_with_sim_cameras(tmp_path: Path) -> None:
    config = _config_for(tmp_path, ["sim-A1", "sim-A3"])
    config.write_text(
        config.read_text()
        + f"""
[simulation]
scene = "cone"
calib_error_deg = 0.5
calib_error_m = 0.01

[audit]
directory = "{tmp_path / "scans"}"
"""
    )
    done = run_cli("calibrate", "--config", str(config), "--capture", "--floor", "--json")
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert not out["config_written"] and out["backup"] is None
    residual = out["registration_residual_m"]["sim-A1|sim-A3"]
    assert abs(residual["before"]) > 0.003 and abs(residual["after"]) < 0.002
    kept = list((tmp_path / "scans").glob("*-calibration/scan.json"))
    assert len(kept) == 1  # the calibration scan is kept for audit

    # written back, the next calibration scan finds the cameras where the config says
    done = run_cli(
        "calibrate",
        "--config",
        str(config),
        "--scan",
        str(kept[0].parent),
        "--floor",
        "--write",
        "--json",
    )
    assert done.returncode == 0, done.stderr
    again = run_cli("calibrate", "--config", str(config), "--capture", "--floor", "--json")
    assert again.returncode == 0, again.stderr
    second = json.loads(again.stdout)
    assert abs(second["registration_residual_m"]["sim-A1|sim-A3"]["before"]) < 0.002
    for camera in second["cameras"]:
        # height and tilt stay; rotation about the cone's axis is unobservable on a cone, so
        # the prior alone holds it and a second calibration may turn a camera along it
        old, new = np.asarray(camera["previous_extrinsic"]), np.asarray(camera["extrinsic"])
        assert abs(new[2, 3] - old[2, 3]) < 0.002
        tilt = np.degrees(np.arccos(np.clip(old[2, :3] @ new[2, :3], -1, 1)))
        assert tilt < 0.05


def test_cli_calibrate_write_to_a_read_only_config_prints_the_result_and_changes_nothing(
    tmp_path: Path, scan_dir: Path
) -> None:
    """A config on a read-only file system: the calibration (seconds of work) is printed all
    the same, with one line naming the file and exit 1; the file, and its directory, as they
    were (it had been a traceback with the result lost)."""
    import subprocess

    from tests.support.faults import tmpfs

    with tmpfs(tmp_path / "ro", "1m") as ro:
        config = _config_for(ro, ["sim-A1", "sim-A3"])
        text = config.read_text()
        subprocess.run(["mount", "-o", "remount,ro", str(ro)], check=True)
        done = run_cli(
            *("calibrate", "--config", str(config), "--scan", str(scan_dir), "--write", "--json")
        )
        assert done.returncode == 1
        out = json.loads(done.stdout)
        assert out["config_written"] is False and out["backup"] is None
        assert set(out["registration_residual_m"]) == {"sim-A1|sim-A3"}
        (line,) = done.stderr.strip().splitlines()
        assert line.startswith(f"silo-agent: {config}: cannot write it") and "not changed" in line
        assert config.read_text() == text and sorted(p.name for p in ro.iterdir()) == ["c.toml"]


def test_cli_calibrate_bounds_the_captures_it_keeps(tmp_path: Path) -> None:
    """Each capture is a scan kept in the audit cache: a billion of them filled the disk."""
    config = _config_for(tmp_path, ["sim-A1", "sim-A3"])
    done = run_cli("calibrate", "--config", str(config), "--capture", "--captures", "1000000000")
    assert done.returncode == 2 and "must be 1 to" in done.stderr
    assert not (tmp_path / "scans").exists()
