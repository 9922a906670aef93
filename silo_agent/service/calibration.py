"""`silo-agent calibrate`'s scans: read from disk, or captured with every camera and kept in
the audit directory like any scan; then pooled and handed to the calibration
(silo_agent.calibrate), which the daemon never imports."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

from silo_agent.calibrate import Calibration, calibrate, pool_scans, start_poses
from silo_agent.capture import capture_all
from silo_agent.config import Config
from silo_agent.reconstruct import site_from_config
from silo_agent.scan import MANIFEST, Scan, ScanError, read_scan, write_scan
from silo_agent.service.scan_path import new_scan, new_scan_id


class CaptureFailed(Exception):
    """A calibration capture without every camera: no calibration is done."""


def read_scans(directories: Sequence[Path]) -> tuple[list[Scan], list[str]]:
    """Calibration scans from disk, each named by its manifest; ScanError for a bad one."""
    scans = [read_scan(d) for d in directories]
    return scans, [str(Path(d) / MANIFEST) for d in directories]


def capture_scans(config: Config, captures: int) -> tuple[list[Scan], list[str]]:
    """`captures` captures in a row (the rig does not move), each kept for audit under
    audit.directory as `<scan id>-calibration[-<k>of<n>]`. CaptureFailed when a camera fails."""
    scans, names = [], []
    for number in range(captures):
        started = datetime.now(UTC)
        capture = capture_all(config, number)
        for failure in capture.failures:
            print(f"silo-agent: warning: {failure.error}", file=sys.stderr)
        if capture.failures or not capture.clouds:
            raise CaptureFailed(
                f"calibration needs every camera; {len(capture.failures)} failed,"
                " no calibration done"
            )
        scan_id = new_scan_id(config, started, set())
        scan = new_scan(config, scan_id, started, capture.clouds, capture.failures)
        suffix = "" if captures == 1 else f"-{number + 1}of{captures}"
        try:  # keep the calibration scan for audit, like any scan
            directory = write_scan(
                scan, config.audit.directory / f"{scan.scan_id}-calibration{suffix}"
            )
            print(f"calibration scan written to {directory}", file=sys.stderr)
        except (ScanError, OSError) as exc:
            print(f"silo-agent: warning: calibration scan not kept: {exc}", file=sys.stderr)
        scans.append(scan)
        names.append(f"capture {number + 1} of {captures}")
    return scans, names


def calibrate_scans(
    config: Config, scans: list[Scan], names: list[str], floor: bool
) -> Calibration:
    """Pool the scans (ScanMismatch) and calibrate them (CalibrationError)."""
    scan = pool_scans(scans, names)
    return calibrate(
        scan,
        config.calibration,
        floor=floor,
        site=site_from_config(config),
        start=start_poses(config, scan),
        grid_step=config.reconstruction.grid_step_m,
    )
