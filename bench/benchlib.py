"""Shared helpers for the benchmarks: provenance header, CloudCompare runner, forked timeouts."""

from __future__ import annotations

import os
import pickle
import platform
import re
import select
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from silo_agent.config import ReconstructionConfig
from silo_agent.grid.grid import Grid
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.fuse import fuse_and_crop
from silo_agent.scan import Scan, write_ply

REPO = Path(__file__).resolve().parent.parent
CLOUDCOMPARE = "CloudCompare"
T = TypeVar("T")


def git_commit() -> str:
    """Short commit of the working tree, with `-dirty` when it has local changes."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, check=False
        ).stdout.strip()

    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    return commit + ("-dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def machine() -> str:
    """CPU model and core count (lscpu), plus Python and OS."""
    model = platform.processor() or "unknown CPU"
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        found = re.search(r"^Model name:\s*(.+)$", out, re.MULTILINE)
        model = found.group(1).strip() if found else model
    except (OSError, subprocess.CalledProcessError):
        pass
    return (
        f"{model}, {os.cpu_count()} logical cores, Python {platform.python_version()},"
        f" {platform.system()} {platform.release()}"
    )


def header(title: str, note: str = "") -> list[str]:
    """Markdown title and provenance lines: command, date, commit, machine."""
    command = "PYTHONPATH=. python " + shlex.join(
        ["bench/" + Path(sys.argv[0]).name, *sys.argv[1:]]
    )
    lines = [
        f"# {title}",
        "",
        f"- command: `{command}`",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- commit: `{git_commit()}`",
        f"- machine: {machine()}",
    ]
    if note:
        lines.append(f"- {note}")
    return [*lines, ""]


def volume_m3(scan: Scan, settings: ReconstructionConfig) -> float:
    """The reconstructed volume of a bench scan; one without a volume is a broken benchmark."""
    result = reconstruct(scan, settings)
    if result.volume_m3 is None:
        raise RuntimeError(f"{scan.scan_id}: no volume ({result.invalid_reason})")
    return result.volume_m3


def fused_cloud(scan: Scan, step: float) -> np.ndarray:
    """The scan's clouds fused in the silo frame and cropped to region and ceiling."""
    return fuse_and_crop(scan.cameras, scan.site, Grid.over(scan.site.region, step)).points


@dataclass(frozen=True)
class CCResult:
    volume_m3: float
    wall_s: float


def cloudcompare_volume(
    ply: Path, step: float, floor_z: float, timeout_s: float = 300.0
) -> CCResult:
    """CloudCompare's 2.5D volume of a PLY above a constant floor, headless.

    CloudCompare writes `VolumeCalculationReport_<date>.txt` next to the cloud, named to the
    minute, so the cloud sits alone in a fresh directory and the report is read from there.
    """
    env = os.environ | {"QT_QPA_PLATFORM": "offscreen"}
    command = [
        CLOUDCOMPARE,
        "-SILENT",
        "-AUTO_SAVE",
        "OFF",
        "-O",
        str(ply),
        "-VOLUME",
        "-GRID_STEP",
        f"{step:g}",
        "-CONST_HEIGHT",
        f"{floor_z:g}",
    ]
    for old in ply.parent.glob("VolumeCalculationReport*.txt"):
        old.unlink()
    start = time.perf_counter()
    subprocess.run(command, env=env, capture_output=True, check=True, timeout=timeout_s)
    wall = time.perf_counter() - start
    reports = list(ply.parent.glob("VolumeCalculationReport*.txt"))
    if len(reports) != 1:
        raise RuntimeError(f"CloudCompare wrote {len(reports)} volume reports for {ply}")
    found = re.search(r"^Volume:\s*([-+0-9.eE]+)", reports[0].read_text(), re.MULTILINE)
    reports[0].unlink()
    if found is None:
        raise RuntimeError(f"no 'Volume:' line in CloudCompare's report for {ply}")
    return CCResult(float(found.group(1)), wall)


def cloudcompare_on_scan(scan: Scan, step: float, workdir: Path) -> CCResult:
    """CloudCompare's 2.5D volume on the scan's fused, cropped cloud at grid `step`."""
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        ply = Path(tmp) / "fused.ply"
        write_ply(ply, fused_cloud(scan, step))
        return cloudcompare_volume(ply, step, scan.site.floor_z)


class TimedOut(Exception):
    """The call ran past its time budget and was killed."""


def call_with_timeout(fn: Callable[[], T], timeout_s: float) -> T:
    """Run `fn` in a forked child and return its result; kill it after `timeout_s`.

    A fork (not multiprocessing) so this works inside pool workers and shares the parent's
    memory (the scans) without pickling them.
    """
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        os.close(read_fd)
        try:
            payload = pickle.dumps((True, fn()))
        except BaseException as error:  # report any failure to the parent
            payload = pickle.dumps((False, repr(error)))
        with os.fdopen(write_fd, "wb") as out:
            out.write(payload)
        os._exit(0)
    os.close(write_fd)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    with os.fdopen(read_fd, "rb") as pipe:
        while True:
            left = deadline - time.monotonic()
            ready, _, _ = select.select([pipe], [], [], max(left, 0.0))
            if not ready:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                raise TimedOut(f"over {timeout_s:g} s")
            chunk = os.read(pipe.fileno(), 1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
    os.waitpid(pid, 0)
    ok, value = pickle.loads(b"".join(chunks))
    if not ok:
        raise RuntimeError(value)
    return value


def fmt(value: Any, spec: str = ".4f", missing: str = "—") -> str:
    """Format a number, or `missing` for None/NaN."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return missing
    return format(value, spec)
