"""How near CloudCompare's time the agent's method can come on a big round bin: the least a
Python process takes for the 2.5D volume alone, and the per-point work the method cannot do
without, against CloudCompare and `silo-agent process`, same scan, same run.

(a) Whole processes, alternating, median of `--runs`, pinned to one core: CloudCompare's
    `-VOLUME` on the fused, cropped points (as bench/silos.py gives it); bench/bare_volume.py
    (read the PLYs, silo frame, crop, cell means, nearest fill, sum: what CloudCompare
    computes, in numpy); `python -m silo_agent process`. And, in one process, the per-point
    stages a wall-rejecting method pays before any grid work (reconstruct/walls.py): each
    ray's wall crossing with its camera's smoothed depth (`WallCrossing.of_cloud`, every
    point), and the wall verdict with the steadying of the points it keeps (`wall_free`: that
    smoothing once more, among them), judged against the scene's true grain surface in place
    of a first pass. The floor is the bare process plus those two stages: the agent cannot
    come under it without dropping the wall test or the noise handling its accuracy is made of.
(b) The agent's own stage times (`timings_s` of its median run in (a)).
(c) The bay batch of bench/silos.py (b), 12 scans with a third of the cells unobserved: one
    `process CACHE`, one bare_volume.py over the 12 scans and CloudCompare once per scan,
    alternating; and, in one process, the membrane fill (`reconstruct.fill.membrane_fill`,
    pyamg and scipy's conjugate gradients) of the holes the bare cell means leave: the fill
    those unobserved cells need, whatever estimates the observed ones.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from bare_volume import cell_means, read_points
from benchlib import (
    BAY_SCANS,
    PROCESS,
    Measured,
    bay_cache,
    big_bin,
    big_bin_scan,
    header,
    measured,
    measured_cloudcompare,
    median_seconds,
    scan_and_cloud,
    timed_on,
    timing_options,
    write_bay_batch,
    write_report,
)

from silo_agent.grid.grid import Grid
from silo_agent.reconstruct import WALL_PASS_STEP_M
from silo_agent.reconstruct.fill import membrane_fill
from silo_agent.reconstruct.walls import WallCrossing, wall_free
from silo_agent.scan import Scan, read_scan
from silo_agent.sim.scenes import Scene

BARE = [sys.executable, str(Path(__file__).with_name("bare_volume.py"))]
NOISE_FACTOR = 1.0
BAY_STEP_M = 0.01
BATCH_TARGET = 0.8  # the batch's target, x CloudCompare once per scan
STAGES = (  # the agent's `timings_s`, in its order
    "walls",
    "fuse_crop",
    "registration_residual",
    "clustered_means",
    "fill",
    "slope_correction",
    "volume",
)


def per_point_stages(scan_dir: Path, scene: Scene, runs: int) -> tuple[float, float]:
    """(every camera's `WallCrossing.of_cloud`, `wall_free` of them all) in seconds, median of
    `runs`, on the scan as `process` reads it; the grain height at the wall is `scene`'s."""
    scan = read_scan(scan_dir)
    shape = scan.site.bin
    if shape is None:
        raise ValueError(f"{scan_dir}: no bin")
    grid = Grid.over(scan.site.region, WALL_PASS_STEP_M)
    grain = np.where(grid.inside > 0, scene.height(*grid.centres()), np.nan)
    crossing_s, verdict_s = [], []
    for _ in range(runs):
        start = time.perf_counter()
        crossings = [WallCrossing.of_cloud(c, shape, grid, NOISE_FACTOR)[0] for c in scan.cameras]
        middle = time.perf_counter()
        wall_free(scan.cameras, crossings, shape, grain, NOISE_FACTOR)
        crossing_s.append(middle - start)
        verdict_s.append(time.perf_counter() - middle)
    return statistics.median(crossing_s), statistics.median(verdict_s)


@dataclass(frozen=True)
class SideBySide:
    """One scan at one step: median wall seconds and the volumes."""

    cc_s: float
    bare_s: float
    agent_s: float
    crossing_s: float  # every camera's WallCrossing.of_cloud, in one process
    wall_free_s: float  # wall_free of every camera's crossings: verdict and steadying
    bare_volume: float
    agent_volume: float
    stages: dict[str, float]  # the agent's timings_s, its median run

    @property
    def floor_s(self) -> float:
        return self.bare_s + self.crossing_s + self.wall_free_s


def side_by_side(scan: Scan, scene: Scene, step: float, runs: int, work: Path) -> SideBySide:
    scan_dir, ply = scan_and_cloud(scan, step, work)
    cc: list[Measured] = []
    bare: list[Measured] = []
    agent: list[Measured] = []
    for _ in range(runs):
        cc.append(measured_cloudcompare(ply, step, scan.site.floor_z)[0])
        bare.append(measured([*BARE, f"{step:g}", str(scan_dir)]))
        agent.append(measured([*PROCESS, str(scan_dir), "--grid-step", f"{step:g}", "--json"]))
    middle = sorted(agent, key=lambda r: r.wall_s)[len(agent) // 2]
    crossing_s, wall_free_s = per_point_stages(scan_dir, scene, runs)
    return SideBySide(
        statistics.median(r.wall_s for r in cc),
        statistics.median(r.wall_s for r in bare),
        statistics.median(r.wall_s for r in agent),
        crossing_s,
        wall_free_s,
        json.loads(bare[-1].stdout)["volume_m3"],
        json.loads(agent[-1].stdout)["volume_m3"],
        json.loads(middle.stdout)["timings_s"],
    )


def report(runs: int, root: Path, cameras: Sequence[int], steps: Sequence[float]) -> list[str]:
    scene = big_bin(12.0)
    truth = scene.volume_m3
    most = big_bin_scan(scene, max(cameras))
    rows, stage_rows, verdicts = [], [], []
    for count in cameras:
        scan = replace(most, cameras=most.cameras[:: max(cameras) // count])
        for step in steps:
            with tempfile.TemporaryDirectory(dir=root) as tmp:
                r = side_by_side(scan, scene, step, runs, Path(tmp))
            cc, bare, agent, floor = r.cc_s, r.bare_s, r.agent_s, r.floor_s
            crossing, verdict = r.crossing_s, r.wall_free_s
            bare_error = 100 * (r.bare_volume - truth) / truth
            agent_error = 100 * (r.agent_volume - truth) / truth
            rows.append(
                f"| {count} | {step * 100:g} cm | {cc:.3f} | {bare:.3f} ({bare / cc:.2f}x) |"
                f" {crossing:.3f} | {verdict:.3f} | **{floor:.3f} ({floor / cc:.2f}x)** |"
                f" {agent:.3f} ({agent / cc:.2f}x) | {bare_error:+.2f} % | {agent_error:+.2f} % |"
            )
            stages = r.stages
            stage_rows.append(
                f"| {count} | {step * 100:g} cm | "
                + " | ".join(f"{stages.get(k, 0.0):.3f}" for k in STAGES)
                + f" | {agent - sum(stages.values()):.3f} |"
            )
            room = (
                f"leaving {cc - bare:.2f} s for the whole method"
                if bare < cc
                else "slower than CloudCompare before any of the method"
            )
            verdicts.append(
                f"- {count} cameras, {step * 100:g} cm: CloudCompare {cc:.2f} s; the bare numpy"
                f" volume alone {bare / cc:.2f}x of it, {room}; the two per-point wall stages"
                f" {crossing + verdict:.2f} s: floor {floor / cc:.2f}x, the agent"
                f" {agent / cc:.2f}x"
            )
    return [
        "## (a) Whole processes and the per-point floor",
        "",
        f"12 m round bin (benchlib.big_bin), full-resolution D455s (1280x720) evenly round the"
        f" eave, seed 0; median of {runs} alternating runs each, wall seconds on one core. The"
        " floor: the bare process plus the two per-point stages (measured in one process, on"
        " the scan as `process` reads it).",
        "",
        "| cameras | grid | CloudCompare | bare numpy volume | wall crossings + smoothed depth"
        " | wall verdict + steadying | floor | `silo-agent process` | bare volume error |"
        " agent volume error |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        *verdicts,
        f"- true volume {truth:.2f} m³",
        "",
        "## (b) The agent's stages (its `timings_s`, the median run)",
        "",
        "The rest: start, imports, reading and checking the scan, pile detection, output.",
        "",
        "| cameras | grid | " + " | ".join(STAGES) + " | the rest |",
        "|---|---|" + "---|" * (len(STAGES) + 1),
        *stage_rows,
        "",
    ]


def membrane_fill_s(directories: Sequence[Path], runs: int) -> float:
    """Median seconds of the membrane fill of every scan's holes, the bare cell means'."""
    holes = []
    for directory in directories:
        points, site = read_points(directory)
        height, inside = cell_means(points, site, BAY_STEP_M)
        holes.append((height, np.isfinite(height) & inside, inside))

    def fill_all() -> None:
        for height, known, inside in holes:
            membrane_fill(height, known, inside)

    return median_seconds(fill_all, runs)


def batch(runs: int, root: Path) -> list[str]:
    _, directories, plys = write_bay_batch(root, BAY_STEP_M)
    cache = bay_cache(root)
    agent, bare, cc = [], [], []
    for _ in range(runs):
        agent.append(measured([*PROCESS, str(cache), "--grid-step", f"{BAY_STEP_M:g}", "--json"]))
        bare.append(measured([*BARE, f"{BAY_STEP_M:g}", *map(str, directories)]).wall_s)
        cc_s = sum(measured_cloudcompare(ply, BAY_STEP_M, 0.0)[0].wall_s for ply in plys)
        cc.append(cc_s)
    n = BAY_SCANS
    agent_s = statistics.median(r.wall_s for r in agent) / n
    bare_s, cc_s = statistics.median(bare) / n, statistics.median(cc) / n
    fill_s = membrane_fill_s(directories, runs) / n
    floor = bare_s + fill_s
    target = BATCH_TARGET * cc_s
    return [
        "## (c) The bay batch: a third of the cells unobserved",
        "",
        f"{n} scans of bench/silos.py's 8 x 6 m walled bay, four wall cameras at 848x480,"
        f" {BAY_STEP_M * 100:g} cm grid; seconds a scan, median of {runs} alternating runs. The"
        " floor: the bare batch plus the membrane fill of the holes its cell means leave"
        " (measured in one process).",
        "",
        "| CloudCompare once per scan | bare numpy batch | membrane fill | floor |"
        " `process CACHE` | target (0.8x CloudCompare) |",
        "|---|---|---|---|---|---|",
        f"| {cc_s:.3f} | {bare_s:.3f} ({bare_s / cc_s:.2f}x) | {fill_s:.3f} |"
        f" **{floor:.3f} ({floor / cc_s:.2f}x)** | {agent_s:.3f} ({agent_s / cc_s:.2f}x) |"
        f" {target:.3f} |",
        "",
        f"- the target leaves {target - floor:.3f} s a scan above the floor for the rest of the"
        f" method (fusing, trust, clustering, the repose bounds, slope, levels, detection); the"
        f" agent spends {agent_s - floor:.3f} s on them",
        "",
    ]


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    timing_options(p, runs=3)
    p.add_argument("--cameras", default="8,16", help="comma list of camera counts")
    p.add_argument("--steps", default="0.01,0.02", help="comma list of grid steps (m)")
    p.add_argument("--parts", default="a,c", help="sections: a (with b), c, or a,c (default)")
    p.add_argument("--out", type=Path, default=Path("bench/results/floor.md"))
    args = p.parse_args(argv)
    timed_on(args.cpu)
    cameras = [int(c) for c in args.cameras.split(",")]
    steps = [float(s) for s in args.steps.split(",")]
    if any(max(cameras) % c for c in cameras):
        p.error(f"--cameras: each must divide the largest, not {args.cameras!r}")
    parts = set(args.parts.split(","))
    if not parts or parts - {"a", "c"}:
        p.error(f"--parts: a, c or a,c, not {args.parts!r}")
    load_before = os.getloadavg()
    head = header("The agent against the floor of its method", f"pinned to CPU {args.cpu}")
    with tempfile.TemporaryDirectory(prefix="silo-floor-") as tmp:
        lines = report(args.runs, Path(tmp), cameras, steps) if "a" in parts else []
        if "c" in parts:
            lines += batch(args.runs, Path(tmp))
    write_report(
        args.out,
        head,
        load_before,
        lines,
        "wall times are under that load; the ratios come from alternating runs in the same minutes",
    )


if __name__ == "__main__":
    main()
