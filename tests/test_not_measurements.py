"""Points that are not measurements ("no return" at the origin, NaN, behind the camera, outside
the sensor's depth range) are dropped when a scan is read, and counted in the result."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from silo_agent.config import ReconstructionConfig
from silo_agent.reconstruct import reconstruct
from silo_agent.scan import Scan, read_ply, read_scan, write_ply, write_scan
from tests.support.cli import run_cli

NO_RETURNS = 243_517  # the raw export of issue 24: +6 % at 5 mm before they were dropped


def _first_cloud(scan_dir: Path) -> Path:
    manifest = json.loads((scan_dir / "scan.json").read_text())
    return scan_dir / manifest["cameras"][0]["cloud"]


def _add_points(cloud: Path, extra: np.ndarray) -> None:
    points, _ = read_ply(cloud)
    write_ply(cloud, np.concatenate([points, extra.astype(np.float32)]))


def test_origin_points_change_nothing_and_are_counted(tmp_path: Path, cone_scan_4: Scan) -> None:
    clean = reconstruct(cone_scan_4, ReconstructionConfig(grid_step_m=0.005))
    scan_dir = write_scan(cone_scan_4, tmp_path / "scan")
    _add_points(_first_cloud(scan_dir), np.zeros((NO_RETURNS, 3)))

    scan = read_scan(scan_dir)
    result = reconstruct(scan, ReconstructionConfig(grid_step_m=0.005))

    assert result.volume_m3 == clean.volume_m3
    assert result.points["not_measurements"] == NO_RETURNS


def test_each_kind_is_dropped_with_its_colour(tmp_path: Path, cone_scan_4: Scan) -> None:
    scan_dir = write_scan(cone_scan_4, tmp_path / "scan")
    manifest = json.loads((scan_dir / "scan.json").read_text())
    manifest["cameras"][0]["depth_range_m"] = [0.5, 4.0]
    (scan_dir / "scan.json").write_text(json.dumps(manifest))
    cloud = _first_cloud(scan_dir)
    points, _ = read_ply(cloud)
    bad = np.array(
        [
            [np.nan, 0.0, 1.0],  # not finite
            [0.0, np.inf, 1.0],
            [0.1, 0.1, -1.0],  # behind the camera
            [0.0, 0.0, 0.0],  # "no return"
            [0.0, 0.0, 0.45],  # nearer than the range
            [0.0, 0.0, 4.5],  # farther
        ]
    )
    kept = points[points[:, 2] >= 0.5]
    kept = kept[kept[:, 2] <= 4.0]
    everything = np.concatenate([points, bad]).astype(np.float32)
    colours = np.zeros((len(everything), 3), np.uint8)
    colours[: len(points)] = 7
    colours[len(points) :] = 200  # the bad points' colour must go with them
    write_ply(cloud, everything, colours)

    camera = read_scan(scan_dir).cameras[0]

    assert camera.not_measurements == len(everything) - len(kept)
    assert len(camera.points) == len(kept)
    assert np.isfinite(camera.points).all()
    assert camera.colors is not None and np.all(camera.colors == 7)


def test_process_prints_the_count(tmp_path: Path, cone_scan_4: Scan) -> None:
    scan_dir = write_scan(cone_scan_4, tmp_path / "scan")
    _add_points(_first_cloud(scan_dir), np.array([[np.nan, 0, 1], [0, 0, 0], [0, 0, 0]]))

    result = run_cli("process", str(scan_dir), "--json")

    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["points"]["not_measurements"] == 3


def test_a_bad_depth_range_is_a_clear_error(tmp_path: Path, cone_scan_4: Scan) -> None:
    scan_dir = write_scan(cone_scan_4, tmp_path / "scan")
    manifest = json.loads((scan_dir / "scan.json").read_text())
    manifest["cameras"][1]["depth_range_m"] = [3.0, 1.0]
    (scan_dir / "scan.json").write_text(json.dumps(manifest))

    result = run_cli("process", str(scan_dir))

    assert result.returncode == 65
    assert "depth_range_m" in result.stderr and "near < far" in result.stderr
