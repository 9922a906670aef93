"""Shared fixtures: synthetic scans with analytic truth, written as silo-scan/1 directories;
a private mosquitto per test (never 1883) with Telemetry instances and subscribers on it.

Markers (pyproject.toml): `broker` on every test that uses the `broker` fixture (added here) or
starts its own mosquitto, `realsense` on the modules that need pyrealsense2 (skipped where it
is not installed), `slow` on the tests that take tens of seconds; `-m "not slow"` leaves them
out."""

from __future__ import annotations

import os

# as every command runs (silo_agent/cli `_dispatch`), before numpy is imported: a scan replayed
# in this process must compute what the daemon this suite starts computed, to the bit (BLAS on
# two threads rounds a refine's least squares differently)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path

import numpy as np
import pytest

from silo_agent.scan import Scan, write_scan
from tests.support.browser import browser  # noqa: F401
from tests.support.mqtt import broker, collector_factory, telemetry_factory  # noqa: F401
from tests.support.synthetic import cone, observe, ring_views


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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if "broker" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.broker)
    # modules with slow tests first, so `make test`'s workers (one module each at a time) do not
    # end on a long one while the other idles; the same order on every worker, as xdist needs
    slow_modules = {item.module for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.module not in slow_modules)
