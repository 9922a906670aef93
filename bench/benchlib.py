"""Shared helpers for the benchmarks: provenance header, CloudCompare runner, forked timeouts."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import platform
import re
import select
import shlex
import signal
import statistics
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

from silo_agent.base.d455 import MAX_HEIGHT_PX, MAX_WIDTH_PX
from silo_agent.config import ReconstructionConfig
from silo_agent.grid.grid import Grid
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.fuse import fuse_and_crop
from silo_agent.scan import Scan, Site, write_ply, write_scan
from silo_agent.sim.grains import grain
from silo_agent.sim.layouts import EAVE_AIM, EAVE_INSET_M, look_at
from silo_agent.sim.scenes import Scene, bin_scene, cone_height, numeric_volume
from silo_agent.sim.simulate import SimRig, plan_view

REPO = Path(__file__).resolve().parent.parent
CLOUDCOMPARE = "CloudCompare"
CLOUDCOMPARE_ENV = os.environ | {"QT_QPA_PLATFORM": "offscreen"}  # headless
PROCESS = [sys.executable, "-m", "silo_agent", "process"]  # the agent's `process`, whole
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


def write_report(
    out: Path,
    head: list[str],
    load_before: tuple[float, float, float],
    lines: list[str],
    under: str,
) -> None:
    """Write and print a report: `header`'s lines, the machine's load at the start and end of
    the run with what that load affects (`under`), then the tables."""
    before, after = (f"{a:.2f} / {b:.2f} / {c:.2f}" for a, b, c in (load_before, os.getloadavg()))
    load = (
        f"- machine load (load average 1 / 5 / 15 min) at start {before}, at end {after}, on"
        f" {os.cpu_count()} cores shared with other work: {under}"
    )
    text = "\n".join([*head[:-1], load, "", *lines]) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(text)


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
    command = cloudcompare_command(ply, step, floor_z)
    for old in ply.parent.glob("VolumeCalculationReport*.txt"):
        old.unlink()
    start = time.perf_counter()
    subprocess.run(
        command, env=CLOUDCOMPARE_ENV, capture_output=True, check=True, timeout=timeout_s
    )
    wall = time.perf_counter() - start
    return CCResult(cloudcompare_report_volume(ply.parent), wall)


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


# ---------------------------------------------------------------- big silos (issue 22)

# A child process's peak memory (ru_maxrss) starts at its parent's size on Linux (the mark
# survives exec), and a bench holding scans is large: a small launcher runs the command and
# reports its child's peak, user + system time, wall time and the command's stdout.
_LAUNCHER = """
import json, os, subprocess, sys, time
start = time.perf_counter()
child = subprocess.Popen(sys.argv[2:], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                         cwd=sys.argv[1] or None)
out = child.stdout.read()
_, status, usage = os.wait4(child.pid, 0)
wall = time.perf_counter() - start
print(json.dumps({"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
                  "peak_mb": usage.ru_maxrss / 1024, "status": os.waitstatus_to_exitcode(status),
                  "stdout": out.decode(errors="replace")}))
"""


@dataclass(frozen=True)
class Measured:
    wall_s: float
    cpu_s: float  # user + system
    peak_mb: float  # the process's peak resident memory
    stdout: str


def pinned(cpu: int) -> None:
    """Pin this process to `cpu`, its BLAS libraries too; children inherit the CPU.

    Pinning binds the calling thread only: numpy's and scipy's OpenBLAS, loaded before it with
    a worker thread a core, kept theirs on the other core, so a call timed in this process
    (scaling.py's fills) ran on two cores and counted both threads' CPU time, 1.9-3.3x the
    one-core figure for scipy's conjugate gradients and pyamg. Their pools are held to one
    thread; a child started after the pinning sizes its own to the one CPU it inherits."""
    import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS, so its pool is held too)
    from threadpoolctl import threadpool_limits

    os.sched_setaffinity(0, {cpu})
    threadpool_limits(limits=1)


def timing_options(parser: argparse.ArgumentParser, runs: int) -> None:
    """The timing benches' --runs (default `runs`) and --cpu options."""
    parser.add_argument("--runs", type=int, default=runs, help="timed runs per figure (median)")
    parser.add_argument("--cpu", type=int, default=0, help="the one CPU to pin to (default 0)")


def median_seconds(
    work: Callable[[], object],
    runs: int,
    clock: Callable[[], float] = time.perf_counter,
    warm_up: bool = False,
) -> float:
    """Median seconds of `runs` calls of `work` on `clock` (`time.perf_counter`: wall time;
    `time.process_time`: this process's CPU time), after one untimed call if `warm_up`."""
    if warm_up:
        work()
    times = []
    for _ in range(runs):
        start = clock()
        work()
        times.append(clock() - start)
    return statistics.median(times)


def timed_on(cpu: int) -> None:
    """Set this process up for timing whole processes: `pinned` to `cpu`, and silo_agent's
    modules compiled to bytecode, as `pip install` does, so that a timed `process` reads them
    compiled: this checkout is an editable install, and a shell with PYTHONDONTWRITEBYTECODE
    set (this machine's) would have every run compile all of them again (about 0.1 s a
    process), which no installed gateway pays."""
    import compileall

    import silo_agent

    pinned(cpu)
    compileall.compile_dir(Path(silo_agent.__file__).parent, quiet=1)


def measured(
    command: list[str], cwd: Path | None = None, env: dict[str, str] | None = None
) -> Measured:
    """Run `command` to completion as a grandchild of a small launcher (see _LAUNCHER)."""
    done = subprocess.run(
        [sys.executable, "-c", _LAUNCHER, str(cwd or ""), *command],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    report = json.loads(done.stdout)
    if report["status"] != 0:
        raise RuntimeError(f"{shlex.join(command)} exited {report['status']}")
    return Measured(report["wall_s"], report["cpu_s"], report["peak_mb"], report["stdout"])


def cloudcompare_command(ply: Path, step: float, floor_z: float) -> list[str]:
    """CloudCompare's headless 2.5D volume of `ply` above a constant floor (run it in the
    PLY's directory: it writes its report there)."""
    return [
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


def cloudcompare_report_volume(directory: Path) -> float:
    """The volume in the one CloudCompare report in `directory` (the report is removed)."""
    reports = list(directory.glob("VolumeCalculationReport*.txt"))
    if len(reports) != 1:
        raise RuntimeError(f"CloudCompare wrote {len(reports)} volume reports in {directory}")
    found = re.search(r"^Volume:\s*([-+0-9.eE]+)", reports[0].read_text(), re.MULTILINE)
    reports[0].unlink()
    if found is None:
        raise RuntimeError(f"no 'Volume:' line in CloudCompare's report in {directory}")
    return float(found.group(1))


def scan_and_cloud(scan: Scan, step: float, work: Path) -> tuple[Path, Path]:
    """`scan` written to `work / "scan"` for a grid of `step`, and its fused, cropped cloud
    alone in `work / "cc"` for CloudCompare: (the scan directory, the PLY)."""
    scan_dir = write_scan(
        dataclasses.replace(scan, reconstruction={"grid_step_m": step}), work / "scan"
    )
    ply = work / "cc" / "fused.ply"
    ply.parent.mkdir(parents=True)
    write_ply(ply, fused_cloud(scan, step))
    return scan_dir, ply


def measured_cloudcompare(ply: Path, step: float, floor_z: float) -> tuple[Measured, float]:
    """CloudCompare's volume of `ply` (alone in its directory) as a measured whole process,
    and the volume it reports."""
    run = measured(cloudcompare_command(ply, step, floor_z), ply.parent, CLOUDCOMPARE_ENV)
    return run, cloudcompare_report_volume(ply.parent)


# the round bins of the big-silo benches: diameter -> (eave, grain at the wall, heap radius),
# in the proportions of the simulator's bin-18. "20 m" is 19.99 m: the region of an exact
# 20 m bin (a 720-gon of the circle's area) is 20.0001 m across, 2001 x 2001 cells at 1 cm,
# just past the 4 M-cell limit (base/limits.py)
BIG_BINS = {12.0: (12.0, 8.0, 2.0, 4.0), 20.0: (19.99, 12.0, 3.5, 6.5)}
FULL_RESOLUTION = (MAX_WIDTH_PX, MAX_HEIGHT_PX)  # the D455's largest depth stream


def big_bin(diameter_m: float) -> Scene:
    actual, eave, level, heap = BIG_BINS[diameter_m]
    return bin_scene(
        grain("wheat"),
        name=f"bin-{actual:g}m",
        diameter_m=actual,
        eave_m=eave,
        level_m=level,
        feature_radius_m=heap,
    )


def eave_pose(scene: Scene, bearing_rad: float) -> np.ndarray:
    """An eave camera at `bearing_rad`, placed and aimed as the simulator's eave layout places
    A1-A8 (EAVE_INSET_M inside the wall, aimed EAVE_AIM of the radius past the centre), so
    16 cameras are the eight views and the eight between them."""
    assert scene.bin is not None
    centre, radius = np.asarray(scene.bin.centre), scene.bin.radius_m
    direction = np.array([np.cos(bearing_rad), np.sin(bearing_rad)])
    xy = centre + direction * (radius - EAVE_INSET_M)
    target = np.append(centre - direction * EAVE_AIM * radius, scene.target[2])
    return look_at(np.array([xy[0], xy[1], scene.wall_camera_z]), target)


def big_bin_scan(scene: Scene, cameras: int, seed: int = 0, rig: SimRig | None = None) -> Scan:
    """`cameras` full-resolution D455s evenly round the eave of a big bin."""
    rig = rig or SimRig(scene)
    clouds = []
    for k in range(cameras):
        bearing = 2 * np.pi * k / cameras - np.pi / 2  # the first at -y, as A1
        view = plan_view(
            f"E{k + 1:02d}",
            f"sim-E{k + 1:02d}",
            eave_pose(scene, bearing),
            seed,
            (0.0, 0.0),
            *FULL_RESOLUTION,
        )
        clouds.append(dataclasses.replace(rig.cloud(view, seed), colors=None))
    return Scan(
        scan_id=f"{scene.name}-{cameras}cams-s{seed}",
        captured_at="2026-12-02T00:00:00Z",
        silo_id="bench",
        site=scene.site,
        cameras=clouds,
        reconstruction={"grid_step_m": 0.01},
        extra={"truth": scene.truth()},
    )


# An 8 x 6 m walled bay with two piles, seen by four wall cameras that leave about a third of
# it unobserved: the case where the fill dominates (issue 22)
BAY_HALF = (4.0, 3.0)
BAY_WALL_M, BAY_CEILING_M, BAY_CAMERA_Z = 3.5, 3.0, 3.2
BAY_CAMERAS = (
    ((-3.95, -2.95), (-0.5, 0.3)),
    ((3.95, -2.95), (1.0, 0.3)),
    ((0.0, -2.95), (0.0, 0.8)),
    ((-3.95, 0.0), (-0.5, 0.0)),
)  # (position, aim)


def bay_scene() -> Scene:
    wheat = grain("wheat")
    hx, hy = BAY_HALF

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        inside = (np.abs(x) <= hx) & (np.abs(y) <= hy)
        piles = np.maximum(
            cone_height(x, y, (-1.5, 0.5), 2.0, wheat.slope),
            cone_height(x, y, (1.8, -0.8), 1.6, wheat.slope),
        )
        return np.where(inside, 0.4 + piles, BAY_WALL_M)

    margin = 0.3
    region = np.array(
        [
            [-hx + margin, -hy + margin],
            [hx - margin, -hy + margin],
            [hx - margin, hy - margin],
            [-hx + margin, hy - margin],
        ]
    )
    site = Site(region, floor_z=0.0, ceiling_z=BAY_CEILING_M, bulk_density_t_m3=wheat.density_t_m3)
    return Scene(
        name="bay-8x6",
        grain=wheat,
        site=site,
        height=height,
        extent=(-hx - 0.1, hx + 0.1, -hy - 0.1, hy + 0.1),
        outer_z=None,
        volume_m3=numeric_volume(height, region, 0.0, 0.005),
        target=(0.0, 0.0, 0.4),
        layout="wall",
        wall_half_m=hx,
        wall_camera_z=BAY_CAMERA_Z,
    )


def bay_scan(scene: Scene, seed: int, rig: SimRig) -> Scan:
    clouds = []
    for k, ((x, y), (ax, ay)) in enumerate(BAY_CAMERAS):
        pose = look_at(np.array([x, y, BAY_CAMERA_Z]), np.array([ax, ay, 0.4]))
        view = plan_view(f"B{k + 1}", f"sim-B{k + 1}", pose, seed, (0.0, 0.0))
        clouds.append(dataclasses.replace(rig.cloud(view, seed), colors=None))
    return Scan(
        scan_id=f"bay-{seed:02d}",
        captured_at="2026-12-02T00:00:00Z",
        silo_id="bench",
        site=scene.site,
        cameras=clouds,
        reconstruction={"grid_step_m": 0.01},
        extra={"truth": scene.truth()},
    )


BAY_SCANS = 12  # the batch of bay scans, a third of each unobserved


def bay_cache(root: Path) -> Path:
    """Where `write_bay_batch` writes its scans under `root`: a cache `process` reads whole."""
    return root / "bay-cache"


def write_bay_batch(root: Path, step: float) -> tuple[Scene, list[Path], list[Path]]:
    """BAY_SCANS scans of `bay_scene` (seeds 0..) written to `bay_cache(root)`, and each
    one's fused, cropped cloud for CloudCompare alone in a directory under `root / "bay-cc"`:
    (the scene, the scan directories, the PLYs)."""
    scene = bay_scene()
    rig = SimRig(scene)
    directories, plys = [], []
    for seed in range(BAY_SCANS):
        scan = bay_scan(scene, seed, rig)
        directories.append(write_scan(scan, bay_cache(root) / scan.scan_id))
        ply = root / "bay-cc" / scan.scan_id / "fused.ply"
        ply.parent.mkdir(parents=True)
        write_ply(ply, fused_cloud(scan, step))
        plys.append(ply)
    return scene, directories, plys


def resampled(scan: Scan, total: int, seed: int = 0) -> Scan:
    """The scan with each camera's cloud drawn (with replacement if short) to total/len points."""
    rng = np.random.default_rng(seed)
    per = total // len(scan.cameras)
    cameras = []
    for cam in scan.cameras:
        pick = rng.choice(len(cam.points), per, replace=len(cam.points) < per)
        cameras.append(dataclasses.replace(cam, points=cam.points[pick], colors=None))
    return dataclasses.replace(scan, cameras=cameras)
