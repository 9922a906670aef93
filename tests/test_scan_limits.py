"""A scan past the cell or point limits is refused with exit 65 and one line before anything
of its size is allocated: the refusing process stays at the size of its imports (issue 22)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

EX_DATAERR = 65  # sysexits.h, written out: not read from the code under test
SCAN_POINT_LIMIT = 16_000_000  # docs/limits.md
# `process` with its imports is about 60 MB; one float64 grid of the refused step below
# would be 165 MB, one refused cloud 108 MB of body and as much again of points
SMALL_PROCESS_MB = 140


# A fork of the test process would start its peak at pytest's own size (Linux keeps the
# high-water mark across exec), so a small launcher runs `process` and reports its peak.
LAUNCHER = """
import os, subprocess, sys
child = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)
_, status, usage = os.wait4(child.pid, 0)
print(usage.ru_maxrss)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def _process(*args: str) -> tuple[int, str, float]:
    """Exit status, stderr and peak resident memory (MB) of `silo-agent process ARGS`."""
    done = subprocess.run(
        [sys.executable, "-c", LAUNCHER, sys.executable, "-m", "silo_agent", "process", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    return done.returncode, done.stderr, int(done.stdout) / 1024


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def test_a_grid_past_the_cell_limit_is_refused_before_it_is_allocated(scan_dir: Path) -> None:
    # 0.0011 m over the 5 m region: 20.7 million cells
    status, stderr, peak_mb = _process(str(scan_dir), "--json", "--grid-step", "0.0011")
    assert status == EX_DATAERR
    line = _one_line(stderr)
    assert "cells" in line and "limit of 4,000,000" in line
    assert peak_mb < SMALL_PROCESS_MB


def test_clouds_past_the_scan_point_limit_are_refused_from_their_headers(scan_dir: Path) -> None:
    # two clouds of 9 million points each (sparse files: their bodies are never written)
    # take the scan past the limit of 16 million; neither body may be read
    count = 9_000_000
    clouds = sorted(scan_dir.glob("*.ply"))[:2]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {count}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    ).encode("ascii")
    for cloud in clouds:
        with open(cloud, "wb") as out:
            out.write(header)
            out.truncate(len(header) + count * 12)
    status, stderr, peak_mb = _process(str(scan_dir), "--json")
    assert status == EX_DATAERR
    line = _one_line(stderr)
    assert f"limit of {SCAN_POINT_LIMIT:,} points" in line and clouds[1].name in line
    assert peak_mb < SMALL_PROCESS_MB
