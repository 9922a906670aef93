"""Several calibration scans pooled: `pool_scans` gives each camera the points of all scans,
refuses scans of other cameras or another site, and `calibrate` takes repeated `--scan` and
`--capture --captures N`."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from silo_agent.calibrate import ScanMismatch, calibrate, pool_scans
from silo_agent.config import CalibrationConfig, load_config
from silo_agent.reconstruct import site_from_config
from silo_agent.scan import read_scan, write_scan
from silo_agent.sim.layouts import perturb, view_pose
from tests.support.calib import render_repeats, rig
from tests.support.cli import run_cli

VIEWS = ["A1", "A3"]


@pytest.fixture(scope="module")
def repeats():
    """Two scans of the same rig, cameras 0.5 deg / 1 cm off, independent noise."""
    true = {
        view: perturb(view_pose(rig().scene, view), 0.5, 0.01, np.random.default_rng(200 + k))
        for k, view in enumerate(VIEWS)
    }
    return render_repeats(VIEWS, seed=7, count=2, true_poses=true)


def _rays(points: np.ndarray) -> np.ndarray:
    """Each camera-frame point's ray direction (x/z, y/z): one per pixel."""
    p = np.asarray(points, dtype=float)
    return p[:, :2] / p[:, 2:3]


@pytest.mark.slow
def test_pooled_scans_average_each_pixel(repeats) -> None:
    """A pixel seen in both scans gives the midpoint of its two points; one seen in a single
    scan (a dropout in the other) keeps its point; no pixel appears twice."""
    first, second = repeats
    assert not np.array_equal(first.cameras[0].points, second.cameras[0].points)  # new noise
    pooled = pool_scans(repeats)
    for camera, a, b in zip(pooled.cameras, first.cameras, second.cameras, strict=True):
        pa, pb, got = (np.asarray(c.points, dtype=float) for c in (a, b, camera))
        near_a, ia = cKDTree(_rays(pa)).query(_rays(got))
        near_b, ib = cKDTree(_rays(pb)).query(_rays(got))
        in_a, in_b = near_a < 1e-5, near_b < 1e-5  # one pixel is 2.3e-3 wide
        assert np.all(in_a | in_b)
        expected = np.where(
            (in_a & in_b)[:, None], (pa[ia] + pb[ib]) / 2, np.where(in_a[:, None], pa[ia], pb[ib])
        )
        np.testing.assert_allclose(got, expected, atol=2e-6)
        shared = int(np.sum(cKDTree(_rays(pb)).query(_rays(pa))[0] < 1e-5))
        assert len(got) == len(pa) + len(pb) - shared
        np.testing.assert_allclose(
            camera.extra["gravity"], np.mean([a.extra["gravity"], b.extra["gravity"]], axis=0)
        )
    together = calibrate(pooled, CalibrationConfig(), floor=True)
    alone = calibrate(first, CalibrationConfig(), floor=True)
    for c, a in zip(together.cameras, alone.cameras, strict=True):
        # the second scan's noise moves a camera by ~1e-2 (about the cone): it counted
        assert np.abs(c.after - a.after).max() > 2e-3
    assert all(abs(r.median_m) < 0.002 for r in together.residual_after.values())


def test_cameras_without_intrinsics_pool_all_points(repeats) -> None:
    bare = [replace(s, cameras=[replace(c, intrinsics=None) for c in s.cameras]) for s in repeats]
    pooled = pool_scans(bare)
    for camera, a, b in zip(pooled.cameras, *(s.cameras for s in bare), strict=True):
        np.testing.assert_array_equal(camera.points, np.concatenate([a.points, b.points]))


def test_one_scan_pools_to_itself(repeats) -> None:
    assert pool_scans(repeats[:1]) is repeats[0]


def test_scans_of_other_cameras_are_refused_naming_the_scan(repeats) -> None:
    first, second = repeats
    other = replace(
        second, cameras=[second.cameras[0], replace(second.cameras[1], serial="sim-A5")]
    )
    with pytest.raises(ScanMismatch) as caught:
        pool_scans([first, other], ["one/scan.json", "two/scan.json"])
    message = str(caught.value)
    assert message.startswith("two/scan.json: not the same cameras as one/scan.json")
    assert "sim-A5" in message and "sim-A3" in message and "\n" not in message
    fewer = replace(second, cameras=second.cameras[:1])
    with pytest.raises(ScanMismatch, match="missing: sim-A3"):
        pool_scans([first, fewer])


def test_scans_of_another_site_are_refused(repeats) -> None:
    first, second = repeats
    lifted = replace(second, site=replace(second.site, floor_z=0.1))
    with pytest.raises(ScanMismatch, match=r"^b: site differs from a's \(floor_z 0.1 instead"):
        pool_scans([first, lifted], ["a", "b"])
    moved = replace(second, site=replace(second.site, region=second.site.region + 0.5))
    with pytest.raises(ScanMismatch, match="a different region"):
        pool_scans([first, moved], ["a", "b"])


CONFIG = """\
[silo]
id = "sim"
region = [[-2.2, -2.2], [2.2, -2.2], [2.2, 2.2], [-2.2, 2.2]]
floor_z = 0.0
ceiling_z = 1.5
{cameras}
[audit]
directory = "{audit}"

[simulation]
scene = "cone"
vary_noise = true
calib_error_deg = 0.5
calib_error_m = 0.01
"""


def _config(tmp_path: Path) -> Path:
    cameras = "".join(
        f'\n[[cameras]]\nserial = "sim-{v}"   # {v}\nsource = "sim"\nview = "{v}"\n' for v in VIEWS
    )
    path = tmp_path / "silo.toml"
    path.write_text(CONFIG.format(cameras=cameras, audit=tmp_path / "scans"))
    return path


@pytest.mark.slow
def test_cli_pools_repeated_scans_and_refuses_a_mismatch(tmp_path: Path, repeats) -> None:
    dirs = [write_scan(s, tmp_path / f"scan{k}") for k, s in enumerate(repeats)]
    config = _config(tmp_path)
    done = run_cli(
        "calibrate",
        "--config",
        str(config),
        "--scan",
        str(dirs[0]),
        "--scan",
        str(dirs[1]),
        "--floor",
        "--write",
        "--json",
    )
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["config_written"] and Path(out["backup"]).exists()
    assert abs(out["registration_residual_m"]["sim-A1|sim-A3"]["after"]) < 0.002
    expected = calibrate(
        pool_scans(repeats),
        CalibrationConfig(),
        floor=True,
        site=site_from_config(load_config(config)),
    )
    for camera, want in zip(out["cameras"], expected.cameras, strict=True):
        np.testing.assert_allclose(camera["extrinsic"], want.after, atol=2e-4)

    other = write_scan(replace(repeats[1], cameras=repeats[1].cameras[:1]), tmp_path / "one")
    done = run_cli(
        "calibrate",
        "--config",
        str(config),
        "--scan",
        str(dirs[0]),
        "--scan",
        str(other),
        "--floor",
    )
    assert done.returncode == 65 and done.stdout == ""
    assert done.stderr.count("\n") == 1
    assert (
        f"{other / 'scan.json'}: not the same cameras as {dirs[0] / 'scan.json'}" in done.stderr
        and "sim-A3" in done.stderr
    )

    done = run_cli("calibrate", "--config", str(config), "--scan", str(dirs[0]), "--captures", "2")
    assert done.returncode == 2 and "--captures goes with --capture" in done.stderr


@pytest.mark.slow
def test_cli_takes_several_captures_in_a_row(tmp_path: Path) -> None:
    config = _config(tmp_path)
    done = run_cli(
        "calibrate", "--config", str(config), "--capture", "--captures", "2", "--floor", "--json"
    )
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    residual = out["registration_residual_m"]["sim-A1|sim-A3"]
    assert abs(residual["before"]) > 0.003 and abs(residual["after"]) < 0.002
    kept = sorted((tmp_path / "scans").glob("*-calibration-*of2/scan.json"))
    assert [p.parent.name[-4:] for p in kept] == ["1of2", "2of2"]
    one, two = (read_scan(p.parent) for p in kept)
    assert not np.array_equal(one.cameras[0].points, two.cameras[0].points)  # new noise each
    assert all(c["floor_points"] > 0 for c in out["cameras"])
