"""The per-scan registration residual (reconstruct/residual.py) against known height offsets."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.grid.grid import Grid
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.fuse import fuse_and_crop
from silo_agent.reconstruct.residual import registration_residuals
from tests.support.calib import render


@pytest.fixture(scope="module")
def scan():
    return render(["A1", "A3", "A5"], seed=11)


def _lifted(scan, serial: str, dz: float):
    """The scan with one camera's extrinsic lifted by dz: its whole surface reads dz higher."""
    cameras = []
    for camera in scan.cameras:
        if camera.serial == serial:
            extrinsic = camera.extrinsic.copy()
            extrinsic[2, 3] += dz
            camera = replace(camera, extrinsic=extrinsic)
        cameras.append(camera)
    return replace(scan, cameras=cameras)


def test_a_calibrated_rig_has_no_residual(scan) -> None:
    result = reconstruct(scan, ReconstructionConfig())
    residual = {k: r.median_m for k, r in result.registration.items()}
    assert set(residual) == {"sim-A1|sim-A3", "sim-A1|sim-A5", "sim-A3|sim-A5"}
    for value in residual.values():
        assert abs(value) < 0.002
    assert "registration_residual" in result.timings_s


@pytest.mark.parametrize("dz", [0.004, -0.012, 0.03])
def test_residual_measures_an_injected_height_offset(scan, dz: float) -> None:
    result = reconstruct(_lifted(scan, "sim-A3", dz), ReconstructionConfig())
    residual = result.registration
    # A1 minus A3: A3 now reads dz higher everywhere
    assert residual["sim-A1|sim-A3"].median_m == pytest.approx(-dz, abs=0.0015)
    assert residual["sim-A3|sim-A5"].median_m == pytest.approx(dz, abs=0.0015)
    assert abs(residual["sim-A1|sim-A5"].median_m) < 0.002
    assert residual["sim-A1|sim-A3"].cells >= 1000


def test_pairs_without_enough_shared_cells_are_not_reported(scan) -> None:
    grid = Grid.over(scan.site.region, 0.02)
    fused = fuse_and_crop(scan.cameras, scan.site, grid)
    serials = [c.serial for c in scan.cameras]
    everything = registration_residuals(fused, grid, serials, min_points=5, min_cells=1)
    few = min(r.cells for r in everything.values())
    strict = registration_residuals(fused, grid, serials, min_points=5, min_cells=few + 1)
    assert len(strict) == len(everything) - 1
    settings = CalibrationConfig(residual_min_cells=10**7)
    assert reconstruct(scan, ReconstructionConfig(), calibration=settings).registration == {}
    assert np.isfinite(everything["sim-A1|sim-A3"].mad_m)
