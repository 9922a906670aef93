"""Shared fixtures: synthetic scans with analytic truth, written as silo-scan/1 directories;
a private mosquitto per test (never 1883) with Telemetry instances and subscribers on it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from mqtt_support import broker, collector_factory, telemetry_factory  # noqa: F401
from synthetic import cone, observe, ring_views

from silo_agent.scan import Scan, write_scan


@pytest.fixture(scope="session")
def cone_scene():
    return cone()


@pytest.fixture(scope="session")
def cone_scan_4(cone_scene) -> Scan:
    return observe(cone_scene, ring_views(4), np.random.default_rng(7), spacing=0.01)


@pytest.fixture(scope="session")
def cone_scan_2(cone_scene) -> Scan:
    return observe(cone_scene, ring_views(2), np.random.default_rng(8), spacing=0.01)


@pytest.fixture
def scan_dir(tmp_path: Path, cone_scan_4: Scan) -> Path:
    return write_scan(cone_scan_4, tmp_path / "scan")


def run_cli(*args: str, check: bool = False) -> subprocess.CompletedProcess:
    """The real `silo-agent` entry point in a subprocess."""
    return subprocess.run(
        [sys.executable, "-m", "silo_agent", *args],
        capture_output=True, text=True, check=check, timeout=120,
    )  # fmt: skip
