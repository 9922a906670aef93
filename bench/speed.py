"""Reconstruction speed (issue 2, "Accuracy and speed").

(a) four clouds of 400k points, 1 cm grid over 6 x 6 m, timed in-process, per stage;
(b) time against points and against cells, which should grow about linearly;
(c) whole processes: `silo-agent process --grid-step 0.01 --json` against CloudCompare's 2.5D
    volume on the same scan's fused, cropped cloud.
By default the process is pinned to CPU 0 (children inherit it), so every figure is one core.
The in-process figures run with freed memory kept in the heap, as the agent runs
(silo_agent/heap.py); (a) also gives the time without.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from benchlib import REPO, cloudcompare_volume, fmt, fused_cloud, header

from silo_agent.config import ReconstructionConfig
from silo_agent.heap import keep_freed_memory
from silo_agent.reconstruct import Result, reconstruct
from silo_agent.reconstruct.grid import Grid
from silo_agent.scan import Scan, write_ply, write_scan
from silo_agent.sim.simulate import simulate

VIEWS = ["A1", "A3", "A5", "A7"]
POINTS = (200_000, 400_000, 800_000, 1_600_000, 3_200_000)
STEPS = (0.04, 0.02, 0.01, 0.005)


def resampled(scan: Scan, total: int, seed: int = 0) -> Scan:
    """The scan with each camera's cloud drawn (with replacement if short) to total/len points."""
    rng = np.random.default_rng(seed)
    per = total // len(scan.cameras)
    cameras = []
    for cam in scan.cameras:
        pick = rng.choice(len(cam.points), per, replace=len(cam.points) < per)
        cameras.append(dataclasses.replace(cam, points=cam.points[pick], colors=None))
    return dataclasses.replace(scan, cameras=cameras)


def median_time(fn: Callable[[], object], runs: int) -> tuple[float, list[float]]:
    """Median wall time of `runs` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def timed_reconstruct(scan: Scan, step: float, runs: int) -> tuple[float, Result]:
    """Median total time and the last result (its per-stage timings)."""
    settings = ReconstructionConfig(grid_step_m=step)
    results: list[Result] = []
    median, _ = median_time(lambda: results.append(reconstruct(scan, settings)), runs)
    return median, results[-1]


def section_a(scan: Scan, runs: int, cold_heap_s: float) -> list[str]:
    n = sum(len(c.points) for c in scan.cameras)
    median, result = timed_reconstruct(scan, 0.01, runs)
    lines = [
        f"## (a) Four clouds of {n // 4:,} points, 1 cm grid over 6 x 6 m",
        "",
        f"Whole `reconstruct` (BICM), median of {runs} runs after a warm-up: **{median:.3f} s**"
        f" (target <= 0.3 s on one core). Volume {fmt(result.volume_m3)} m³, true"
        f" {scan.extra['truth']['volume_m3']:.4f} m³. Without keeping freed memory (a process"
        f" that has not called `keep_freed_memory`, glibc's default): {cold_heap_s:.3f} s."
        " Stages of the last run:",
        "",
        "| stage | s |", "|---|---|",
    ]
    lines += [f"| {k} | {v:.4f} |" for k, v in result.timings_s.items()]
    lines.append(f"| total of stages | {sum(result.timings_s.values()):.4f} |")
    return [*lines, ""]


def section_b(base: Scan, points: Sequence[int], steps: Sequence[float], runs: int) -> list[str]:
    lines = [
        "## (b) Time against points and cells", "",
        f"Median of {runs} runs. Points: four cameras, 1 cm grid. Cells: 1.6M points (or the"
        " largest point count run), grid cells over the 6 x 6 m region.", "",
        "| points | time s | µs per point |", "|---|---|---|",
    ]
    for n in points:
        median, _ = timed_reconstruct(resampled(base, n), 0.01, runs)
        lines.append(f"| {n:,} | {median:.3f} | {median / n * 1e6:.3f} |")
    fixed = 1_600_000 if 1_600_000 in points else max(points)
    scan = resampled(base, fixed)
    lines += ["", f"| grid step m | cells | time s (at {fixed:,} points) | µs per cell |",
              "|---|---|---|---|"]
    for step in steps:
        median, _ = timed_reconstruct(scan, step, runs)
        rows, cols = Grid.over(scan.site.region, step).shape
        cells = rows * cols
        lines.append(f"| {step:g} | {cells:,} | {median:.3f} | {median / cells * 1e6:.3f} |")
    return [*lines, ""]


def _process(scan_dir: Path) -> tuple[float, float | None]:
    start = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-m", "silo_agent", "process", str(scan_dir), "--grid-step", "0.01",
         "--json"],
        capture_output=True, text=True, check=True, cwd=REPO,
        env=os.environ | {"PYTHONPATH": str(REPO)},
    )
    wall = time.perf_counter() - start
    return wall, json.loads(out.stdout)["volume_m3"]


def section_c(scan: Scan, runs: int, workdir: Path) -> list[str]:
    scan_dir = write_scan(scan, workdir / "scan")
    ply = workdir / "cc" / "fused.ply"
    ply.parent.mkdir()
    write_ply(ply, fused_cloud(scan, 0.01))
    agent = [_process(scan_dir) for _ in range(runs)]
    cc = [cloudcompare_volume(ply, 0.01, scan.site.floor_z) for _ in range(runs)]
    agent_s = statistics.median(w for w, _ in agent)
    cc_s = statistics.median(r.wall_s for r in cc)
    truth = scan.extra["truth"]["volume_m3"]

    def err(v: float | None) -> str:
        return "—" if v is None else f"{100 * (v - truth) / truth:+.2f} %"

    return [
        "## (c) Whole processes, same 4-camera scan, 1 cm grid", "",
        f"Wall time of the whole process, median of {runs}. CloudCompare is given the cloud"
        " already fused and cropped (written beforehand, not timed); `silo-agent process` reads"
        " the raw scan directory (PLYs + manifest) and does everything itself.", "",
        "| tool | wall s | volume m³ | error |", "|---|---|---|---|",
        f"| `python -m silo_agent process SCAN --grid-step 0.01 --json` | {agent_s:.3f} |"
        f" {fmt(agent[-1][1])} | {err(agent[-1][1])} |",
        f"| `CloudCompare -SILENT -AUTO_SAVE OFF -O fused.ply -VOLUME -GRID_STEP 0.01"
        f" -CONST_HEIGHT {scan.site.floor_z:g}` | {cc_s:.3f} | {fmt(cc[-1].volume_m3)} |"
        f" {err(cc[-1].volume_m3)} |",
        f"| true volume | | {truth:.4f} | |",
        "",
        f"silo-agent / CloudCompare wall time: {agent_s / cc_s:.2f}"
        " (target: silo-agent no slower, <= 1).", "",
    ]


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="full", choices=["full", "crater"])
    p.add_argument("--runs", type=int, default=5, help="timed runs per figure (median)")
    p.add_argument("--cpu", type=int, default=0, help="the one CPU to pin to (default 0)")
    p.add_argument("--all-cores", action="store_true", help="do not pin to one CPU")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: 2 runs, two point counts, two grid steps")
    p.add_argument("--out", type=Path, default=Path("bench/results/speed.md"))
    args = p.parse_args(argv)
    points, steps = (POINTS[:2], STEPS[:2]) if args.quick else (POINTS, STEPS)
    runs = 2 if args.quick else args.runs
    if not args.all_cores:
        os.sched_setaffinity(0, {args.cpu})
    cores = sorted(os.sched_getaffinity(0))
    base = simulate(args.scene, VIEWS, seed=0)
    scan = resampled(base, 4 * 400_000)
    note = "QUICK RUN (smoke test, fewer runs and sizes); " if args.quick else ""
    lines = header("Speed benchmark", note + f"scene {args.scene}, views {', '.join(VIEWS)};"
                   f" pinned to CPU(s) {cores} (subprocesses inherit it)")
    cold_heap_s, _ = timed_reconstruct(scan, 0.01, runs)  # before keep_freed_memory
    keep_freed_memory()
    lines += section_a(scan, runs, cold_heap_s)
    lines += section_b(base, points, steps, runs)
    with tempfile.TemporaryDirectory(prefix="silo-speed-") as tmp:
        lines += section_c(scan, 2 if args.quick else 5, Path(tmp))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
