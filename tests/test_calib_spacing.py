"""Measured camera spacings (`[[calibration.spacing]]`): `calibrate` holds the rig to them,
with or without overlap between the two cameras; the config validates and keeps them."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from silo_agent.calibrate import CalibrationError, calibrate, write_calibrated_config
from silo_agent.config import (
    SPACING_SIGMA_M,
    CalibrationConfig,
    ConfigError,
    SpacingConfig,
    load_config,
    parse_config,
)
from silo_agent.scan import write_scan
from silo_agent.sim.layouts import view_pose
from tests.support.calib import render, rig
from tests.support.cli import run_cli


def _dilated(views: list[str], outward_m: float, seed: int):
    """A scan whose cameras really sit `outward_m` closer to the rig's centre (in plan) than
    their extrinsics say: the configured rig is dilated by 2 x `outward_m` across."""
    nominal = {v: view_pose(rig().scene, v) for v in views}
    middle = np.mean([p[:3, 3] for p in nominal.values()], axis=0)
    true = {}
    for view, pose in nominal.items():
        radial = pose[:3, 3] - middle
        radial[2] = 0.0
        true[view] = pose.copy()
        true[view][:3, 3] -= outward_m * radial / np.linalg.norm(radial)
    scan = render(views, seed=seed, true_poses=true)
    return scan, {f"sim-{v}": t for v, t in true.items()}


def _distance(poses, a: str, b: str) -> float:
    return float(np.linalg.norm(poses[a][:3, 3] - poses[b][:3, 3]))


@pytest.mark.parametrize("views", [["A1", "A5"], ["A1", "A3"]], ids=["opposite", "adjacent"])
def test_a_dilated_rig_is_brought_back_to_its_measured_spacing(views: list[str]) -> None:
    scan, truth = _dilated(views, 0.005, seed=3)  # configured 1 cm too far apart
    a, b = (f"sim-{v}" for v in views)
    measured = _distance(truth, a, b)
    plain = calibrate(scan, CalibrationConfig(), floor=True)
    assert abs(_distance(plain.extrinsics(), a, b) - measured) > 0.004  # the scan alone: no
    spacing = SpacingConfig(a=a, b=b, distance_m=measured, sigma_m=0.003)
    result = calibrate(scan, CalibrationConfig(spacing=[spacing]), floor=True)
    after = result.extrinsics()
    assert abs(_distance(after, a, b) - measured) < 0.001
    check = result.spacings[0]
    assert (check.a, check.b, check.measured_m) == (a, b, measured)
    assert check.before_m == pytest.approx(measured + 0.010, abs=1e-6)
    assert check.after_m == pytest.approx(_distance(after, a, b))
    for serial in (a, b):
        # the floor's height stays locked; the camera moved in plan towards the other
        assert abs(after[serial][2, 3] - plain.extrinsics()[serial][2, 3]) < 1e-5
        assert np.linalg.norm(after[serial][:2, 3] - truth[serial][:2, 3]) < 0.003
    if views == ["A1", "A5"]:  # no usable overlap: the constraint alone moved them, half each
        assert not result.pairs[0].used
        moves = [np.linalg.norm(after[s][:2, 3] - plain.extrinsics()[s][:2, 3]) for s in (a, b)]
        assert moves == pytest.approx([0.005, 0.005], abs=0.0005)
        assert any("only its measured spacing moved it" in n for n in result.notes)
    out = result.to_json()["spacing"][0]
    assert out["error_before_m"] == pytest.approx(0.010, abs=1e-6)
    assert abs(out["error_after_m"]) < 0.001
    assert f"{a}|{b}" in result.describe().split("spacing ")[1]


def test_spacing_of_a_camera_not_in_the_scan_is_refused() -> None:
    scan = render(["A1", "A3"], seed=1)
    settings = CalibrationConfig(spacing=[SpacingConfig(a="sim-A1", b="sim-A9", distance_m=2)])
    with pytest.raises(CalibrationError, match=r"calibration\.spacing .*sim-A9"):
        calibrate(scan, settings, floor=True)


CONFIG = """\
[silo]
id = "sim"
region = [[-2.2, -2.2], [2.2, -2.2], [2.2, 2.2], [-2.2, 2.2]]
floor_z = 0.0
ceiling_z = 1.5

[[cameras]]
serial = "sim-A1"
source = "sim"
view = "A1"

[[cameras]]
serial = "sim-A3"
source = "sim"
view = "A3"

[[calibration.spacing]]        # laser meter, 2026-11-30
a = "sim-A1"
b = "sim-A3"
distance_m = 3.536
sigma_m = 0.002

[[calibration.spacing]]
a = "sim-A3"
b = "sim-A1"
distance_m = 3.537              # measured twice: both count
"""


def test_spacing_entries_validate_with_a_default_sigma() -> None:
    config = parse_config(tomllib.loads(CONFIG), "c.toml")
    first, second = config.calibration.spacing
    assert (first.a, first.b, first.distance_m, first.sigma_m) == ("sim-A1", "sim-A3", 3.536, 0.002)
    assert second.sigma_m == SPACING_SIGMA_M == 0.003


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (
            ('b = "sim-A3"\ndistance_m = 3.536', 'b = "sim-A7"\ndistance_m = 3.536'),
            r"c\.toml: calibration\.spacing\.0\.b: unknown camera serial 'sim-A7', expected the "
            r"serial of one of the \[\[cameras\]\] \(sim-A1, sim-A3\)",
        ),
        (
            ('b = "sim-A3"\ndistance_m = 3.536', 'b = "sim-A1"\ndistance_m = 3.536'),
            r"c\.toml: calibration\.spacing\.0: .*same camera",
        ),
        (
            ("distance_m = 3.536", "distance_m = -1"),
            r"c\.toml: calibration\.spacing\.0\.distance_m: .*greater than 0",
        ),
        (
            ("sigma_m = 0.002", "sigma_mm = 2"),
            r"c\.toml: calibration\.spacing\.0\.sigma_mm: unknown key",
        ),
    ],
)
def test_bad_spacing_entries_are_clear_config_errors(
    change: tuple[str, str], expected: str
) -> None:
    text = CONFIG.replace(*change)
    assert text != CONFIG
    with pytest.raises(ConfigError, match=expected):
        parse_config(tomllib.loads(text), "c.toml")


def test_calibrate_write_keeps_the_spacing_entries(tmp_path: Path) -> None:
    path = tmp_path / "silo.toml"
    path.write_text(CONFIG)
    poses = {"sim-A1": view_pose(rig().scene, "A1"), "sim-A3": view_pose(rig().scene, "A3")}
    write_calibrated_config(path, poses)
    new = path.read_text()
    assert new.count("[[calibration.spacing]]") == 2 and "# laser meter, 2026-11-30" in new
    assert (
        load_config(path).calibration.spacing
        == parse_config(tomllib.loads(CONFIG), "c").calibration.spacing
    )


@pytest.mark.slow
def test_cli_reports_each_spacing_before_and_after(tmp_path: Path) -> None:
    scan, truth = _dilated(["A1", "A5"], 0.005, seed=4)
    directory = write_scan(scan, tmp_path / "scan")
    measured = _distance(truth, "sim-A1", "sim-A5")
    path = tmp_path / "c.toml"
    path.write_text(
        CONFIG.split("[[cameras]]")[0]
        + f"""
[[cameras]]
serial = "sim-A1"
source = "sim"
view = "A1"

[[cameras]]
serial = "sim-A5"
source = "sim"
view = "A5"

[[calibration.spacing]]
a = "sim-A1"
b = "sim-A5"
distance_m = {measured:.4f}
"""
    )
    done = run_cli(
        "calibrate", "--config", str(path), "--scan", str(directory), "--floor", "--json"
    )
    assert done.returncode == 0, done.stderr
    (out,) = json.loads(done.stdout)["spacing"]
    assert (out["a"], out["b"], out["sigma_m"]) == ("sim-A1", "sim-A5", 0.003)
    assert out["before_m"] - out["measured_m"] == pytest.approx(0.010, abs=1e-4)
    assert abs(out["after_m"] - out["measured_m"]) < 0.001
    done = run_cli("calibrate", "--config", str(path), "--scan", str(directory), "--floor")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    header = next(k for k, x in enumerate(lines) if x.startswith("spacing "))
    line = lines[header + 1]
    assert line.startswith("sim-A1|sim-A5 ") and f"{measured * 1000:.1f} (±3.0)" in line
    assert "(+10.0) ->" in line
