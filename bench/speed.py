"""Reconstruction speed (issue 2, "Accuracy and speed").

(a) four clouds of 400k points, 1 cm grid over 6 x 6 m, timed in-process, per stage;
(b) time against points and against cells, which should grow about linearly;
(c) whole processes side by side, in one run: `silo-agent process --grid-step 0.01 --json` on
    one scan against CloudCompare's 2.5D volume on the same scan's fused, cropped cloud, and
    `silo-agent process CACHE` over 20 cached scans (one process) per scan against CloudCompare
    run once per scan; then where a single `process` spends its time, stage by stage, and the
    import times (`python -X importtime`) of `process --help` and of the process path.
`--whole` runs (c) alone (bench/results/speed-process.md).
By default the process is pinned to CPU 0 (children inherit it), so every figure is one core.
The in-process figures run with freed memory kept in the heap, as the agent runs
(silo_agent/base/heap.py); (a) also gives the time without.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from benchlib import (
    REPO,
    cloudcompare_volume,
    fmt,
    fused_cloud,
    header,
    pinned,
    resampled,
    timing_options,
)

from silo_agent.base.heap import keep_freed_memory
from silo_agent.config import ReconstructionConfig
from silo_agent.grid.grid import Grid
from silo_agent.reconstruct import Reconstruction, reconstruct
from silo_agent.scan import Scan, write_ply, write_scan
from silo_agent.sim.simulate import simulate

VIEWS = ["A1", "A3", "A5", "A7"]
POINTS = (200_000, 400_000, 800_000, 1_600_000, 3_200_000)
STEPS = (0.04, 0.02, 0.01, 0.005)


def median_time(fn: Callable[[], object], runs: int) -> tuple[float, list[float]]:
    """Median wall time of `runs` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def timed_reconstruct(scan: Scan, step: float, runs: int) -> tuple[float, Reconstruction]:
    """Median total time and the last result (its per-stage timings)."""
    settings = ReconstructionConfig(grid_step_m=step)
    results: list[Reconstruction] = []
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
        "| stage | s |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v:.4f} |" for k, v in result.timings_s.items()]
    lines.append(f"| total of stages | {sum(result.timings_s.values()):.4f} |")
    return [*lines, ""]


def section_b(base: Scan, points: Sequence[int], steps: Sequence[float], runs: int) -> list[str]:
    lines = [
        "## (b) Time against points and cells",
        "",
        f"Median of {runs} runs. Points: four cameras, 1 cm grid. Cells: 1.6M points (or the"
        " largest point count run), grid cells over the 6 x 6 m region.",
        "",
        "| points | time s | µs per point |",
        "|---|---|---|",
    ]
    for n in points:
        median, _ = timed_reconstruct(resampled(base, n), 0.01, runs)
        lines.append(f"| {n:,} | {median:.3f} | {median / n * 1e6:.3f} |")
    fixed = 1_600_000 if 1_600_000 in points else max(points)
    scan = resampled(base, fixed)
    lines += [
        "",
        f"| grid step m | cells | time s (at {fixed:,} points) | µs per cell |",
        "|---|---|---|---|",
    ]
    for step in steps:
        median, _ = timed_reconstruct(scan, step, runs)
        rows, cols = Grid.over(scan.site.region, step).shape
        cells = rows * cols
        lines.append(f"| {step:g} | {cells:,} | {median:.3f} | {median / cells * 1e6:.3f} |")
    return [*lines, ""]


CACHED_SCANS = 20
PROCESS = [sys.executable, "-m", "silo_agent", "process"]
ENV = os.environ | {"PYTHONPATH": str(REPO)}


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of every child process waited for so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _wall(command: list[str]) -> tuple[float, str, str]:
    """Wall time, stdout and stderr of a command run to completion."""
    start = time.perf_counter()
    out = subprocess.run(command, capture_output=True, text=True, check=True, cwd=REPO, env=ENV)
    return time.perf_counter() - start, out.stdout, out.stderr


@dataclasses.dataclass(frozen=True)
class Timed:
    wall_s: float
    cpu_s: float  # user + system: what the run cost, less sensitive to other load than wall
    volumes: list[float | None]
    reconstruct_s: tuple[float, ...] = ()  # per scan, the engine's own stage times summed


def _agent(command: list[str]) -> Timed:
    cpu = _children_cpu_s()
    wall, out, _ = _wall(command)
    results = [json.loads(line) for line in out.splitlines()]
    return Timed(
        wall,
        _children_cpu_s() - cpu,
        [r["volume_m3"] for r in results],
        tuple(sum(r["timings_s"].values()) for r in results),
    )


def _cloudcompare(plys: list[Path], floor_z: float) -> Timed:
    """CloudCompare once per cloud, times summed."""
    cpu = _children_cpu_s()
    runs = [cloudcompare_volume(ply, 0.01, floor_z) for ply in plys]
    return Timed(sum(r.wall_s for r in runs), _children_cpu_s() - cpu, [r.volume_m3 for r in runs])


def _cached_scans(base: Scan, workdir: Path) -> tuple[Path, list[Path]]:
    """CACHED_SCANS scan directories in one cache directory, each a different draw of
    1.6 M points from the scene, and beside each its fused, cropped cloud for CloudCompare."""
    cache = workdir / "cache"
    plys = []
    for k in range(CACHED_SCANS):
        scan = dataclasses.replace(resampled(base, 4 * 400_000, seed=k), scan_id=f"scan-{k:02d}")
        write_scan(scan, cache / scan.scan_id)
        ply = workdir / "cc" / scan.scan_id / "fused.ply"
        ply.parent.mkdir(parents=True)
        write_ply(ply, fused_cloud(scan, 0.01))
        plys.append(ply)
    return cache, plys


def _ratio_line(what: str, agent_s: float, cc_s: float, target: float) -> str:
    verdict = "met" if agent_s / cc_s <= target else "NOT met"
    return (
        f"{what}: silo-agent / CloudCompare wall time **{agent_s / cc_s:.2f}**"
        f" (target <= {target:g}: {verdict})."
    )


def section_c(
    base: Scan, runs: int, workdir: Path, baseline: tuple[str, Path] | None = None
) -> list[str]:
    """Single scan and batch, silo-agent and CloudCompare interleaved so both see the same
    machine load."""
    cache, plys = _cached_scans(base, workdir)
    scan_dir, ply = cache / "scan-00", plys[0]
    floor_z = base.site.floor_z
    agent, cc = [], []
    for _ in range(runs):
        agent.append(_agent([*PROCESS, str(scan_dir), "--grid-step", "0.01", "--json"]))
        cc.append(_cloudcompare([ply], floor_z))
    batch = _agent([*PROCESS, str(cache), "--grid-step", "0.01", "--json"])
    cc_batch = _cloudcompare(plys, floor_z)
    truth = base.extra["truth"]["volume_m3"]

    def median(runs_: list[Timed], what: str) -> float:
        return statistics.median(getattr(r, what) for r in runs_)

    def err(v: float | None) -> str:
        return "—" if v is None else f"{100 * (v - truth) / truth:+.2f} %"

    def errors(timed: Timed) -> str:
        volumes = [v for v in timed.volumes if v is not None]
        if len(volumes) < len(timed.volumes):
            return "—"  # a scan without a volume: no range
        return f"{err(min(volumes))} .. {err(max(volumes))}"

    n = CACHED_SCANS
    return [
        "## (c) Whole processes side by side, 1 cm grid",
        "",
        "Everything in this section ran in one run of this script, silo-agent and CloudCompare"
        " alternating, on the same core. CloudCompare is given each scan's cloud already fused"
        " and cropped (written beforehand, not timed); `silo-agent process` reads the raw scan"
        " directory (PLYs + manifest) and does everything itself: start Python, import, read,"
        " reconstruct, detect piles, print. CPU s is user + system time of the process: it"
        " counts what the run itself costs, where wall time also counts waiting for the core"
        " while other work runs on it.",
        "",
        f"### Single scan (4 cameras, 1.6 M points), median of {runs}",
        "",
        "| tool | wall s | CPU s | volume m³ | error |",
        "|---|---|---|---|---|",
        f"| `python -m silo_agent process SCAN --grid-step 0.01 --json` |"
        f" {median(agent, 'wall_s'):.3f} | {median(agent, 'cpu_s'):.3f} |"
        f" {fmt(agent[-1].volumes[0])} | {err(agent[-1].volumes[0])} |",
        f"| `CloudCompare -SILENT -AUTO_SAVE OFF -O fused.ply -VOLUME -GRID_STEP 0.01"
        f" -CONST_HEIGHT {floor_z:g}` | {median(cc, 'wall_s'):.3f} | {median(cc, 'cpu_s'):.3f} |"
        f" {fmt(cc[-1].volumes[0])} | {err(cc[-1].volumes[0])} |",
        f"| true volume | | | {truth:.4f} | |",
        "",
        _ratio_line("Single scan", median(agent, "wall_s"), median(cc, "wall_s"), 1.5)
        + f" CPU time ratio {median(agent, 'cpu_s') / median(cc, 'cpu_s'):.2f}.",
        "",
        f"### Batch: {n} cached scans (each a different draw of 1.6 M points)",
        "",
        "| tool | wall s, all | s per scan | CPU s per scan | volume error, min .. max |",
        "|---|---|---|---|---|",
        f"| `python -m silo_agent process CACHE --grid-step 0.01 --json` (one process) |"
        f" {batch.wall_s:.3f} | {batch.wall_s / n:.3f} | {batch.cpu_s / n:.3f} |"
        f" {errors(batch)} |",
        f"| CloudCompare as above, once per scan | {cc_batch.wall_s:.3f} |"
        f" {cc_batch.wall_s / n:.3f} | {cc_batch.cpu_s / n:.3f} | {errors(cc_batch)} |",
        "",
        _ratio_line("Batch, per scan", batch.wall_s, cc_batch.wall_s, 1.0)
        + f" CPU time ratio {batch.cpu_s / cc_batch.cpu_s:.2f}.",
        "",
        f"In the batch, the reconstruction's own stages take {batch.reconstruct_s[0]:.3f} s on"
        f" the first scan and a median {statistics.median(batch.reconstruct_s[1:]):.3f} s on"
        " the others (arrays already faulted in); the rest of a scan's"
        f" {batch.wall_s / n:.3f} s is reading it, pile detection and the process's start"
        " shared out.",
        "",
        *_stages(scan_dir, runs),
        *_import_tables(scan_dir, baseline),
    ]


STAGES = r"""
import json, os, sys, time
t = [time.perf_counter()]
from silo_agent.cli import build_parser
args = build_parser().parse_args(["process", *sys.argv[1:]])
t.append(time.perf_counter())
os.environ.setdefault("PYDANTIC_DISABLE_PLUGINS", "__all__")  # as the command line does
from silo_agent.base.heap import keep_freed_memory
keep_freed_memory()
import numpy, pydantic
t.append(time.perf_counter())
import silo_agent.config, silo_agent.scan, silo_agent.service.scan_path as service
t.append(time.perf_counter())
import silo_agent.reconstruct
t.append(time.perf_counter())
import silo_agent.detect, silo_agent.service.batch
t.append(time.perf_counter())
scan = silo_agent.scan.read_scan(args.scan_dirs[0])
t.append(time.perf_counter())
analysis = service.overridden(service.settings_of(scan), None, args.grid_step, args.method)
result = service.analyse_with(scan, analysis, [])
t.append(time.perf_counter())
print(json.dumps(service.summary_of(result, scan, {}).to_json(), allow_nan=False))
t.append(time.perf_counter())
fresh = result.reconstruction.timings_s
again = time.perf_counter()
warm = service.analyse_with(scan, analysis, []).reconstruction.timings_s
again = time.perf_counter() - again
report = {"steps": [b - a for a, b in zip(t, t[1:])], "fresh": fresh, "warm": warm, "again": again}
print(json.dumps(report), file=sys.stderr)
sys.stdout.flush(); sys.stderr.flush()
os._exit(0)  # as `silo-agent process` ends
"""
IMPORT_STEPS = [
    "import silo_agent.cli, parse the arguments",
    "import numpy and pydantic",
    "import the config models, the scan reader and service (silo_agent.config, .scan, ...)",
    "import silo_agent.reconstruct (with scipy.ndimage, its filters)",
    "import silo_agent.detect",
]
READ_STEP = "read the scan (4 PLYs, 1.6 M points; manifest checked)"
PRINT_STEP = "print the JSON"


def _stages(scan_dir: Path, runs: int) -> list[str]:
    """Where one `process` run spends its time: the same steps as `process` runs, timed inside
    a fresh interpreter, plus the interpreter's own start (`python -c pass`) and its end (the
    script's wall time less its steps). The analysis is then run again in the same process:
    the warm column is what the same stage costs once its memory has been touched."""
    start = statistics.median(_wall([sys.executable, "-c", "pass"])[0] for _ in range(runs))
    walls, reports = [], []
    for _ in range(runs):
        wall, _, err = _wall(
            [sys.executable, "-c", STAGES, str(scan_dir), "--grid-step", "0.01", "--json"]
        )
        report = json.loads(err.splitlines()[-1])
        walls.append(wall - report["again"])
        reports.append(report)

    def med(values: Sequence[float]) -> float:
        return statistics.median(values)

    steps = [med(column) for column in zip(*(r["steps"] for r in reports), strict=True)]
    *imports, read, analyse, printed = steps
    stages = list(reports[0]["fresh"])
    fresh = {k: med([r["fresh"][k] for r in reports]) for k in stages}
    warm = {k: med([r["warm"][k] for r in reports]) for k in stages}
    detect = med([r["steps"][-2] - sum(r["fresh"].values()) for r in reports])
    ended = med([w - start - sum(r["steps"]) for w, r in zip(walls, reports, strict=True)])
    total = med(walls)
    lines = [
        f"### Where a single `process` spends its time (median of {runs} fresh processes)",
        "",
        "The steps `process` takes, in its order, each timed inside one fresh interpreter; the"
        " reconstruction's stages as it times them. The last column runs the same analysis"
        " again in that process: the difference is the first touch of the stage's memory"
        " (page faults), which a batch pays once.",
        "",
        "| step | fresh process s | again, same process s |",
        "|---|---|---|",
        f"| start the interpreter (`python -c pass`, separate runs) | {start:.3f} | |",
    ]
    lines += [f"| {name} | {s:.3f} | |" for name, s in zip(IMPORT_STEPS, imports, strict=True)]
    lines.append(f"| {READ_STEP} | {read:.3f} | |")
    lines += [f"| reconstruct: {k} | {fresh[k]:.3f} | {warm[k]:.3f} |" for k in stages]
    lines += [
        f"| detect piles (the rest of `analyse`) | {detect:.3f} | |",
        f"| {PRINT_STEP} | {printed:.3f} | |",
        f"| end the process (flush, `os._exit`) | {ended:.3f} | |",
        f"| **total** (the script's wall time, median) | **{total:.3f}** | |",
        "",
        f"Reconstruction {sum(fresh.values()):.3f} s in the fresh process, {sum(warm.values()):.3f}"
        f" s again in the same process; `analyse` took {analyse:.3f} s in all.",
        "",
    ]
    return lines


F2PY_ALL = "numpy.f2py with what it imports (cumulative, also counted in its packages)"


def _importtime(command: list[str], tree: Path = REPO) -> dict[str, float]:
    """Seconds of import per top-level package (self times summed), from `-X importtime`, of
    silo_agent from source `tree` (run from there: `-m` looks in the working directory first)."""
    done = subprocess.run(
        [sys.executable, "-X", "importtime", *command],
        capture_output=True,
        text=True,
        cwd=tree,
        env=ENV | {"PYTHONPATH": str(tree)},
        check=False,
    )
    per: dict[str, float] = {}
    for line in done.stderr.splitlines():
        found = re.match(r"import time:\s+(\d+) \|\s+(\d+) \|\s+(\S+)$", line)
        if found:
            name = found.group(3)
            root = "numpy.f2py" if name.startswith("numpy.f2py") else name.split(".")[0]
            per[root] = per.get(root, 0.0) + int(found.group(1)) / 1e6
            if name == "numpy.f2py":
                per[F2PY_ALL] = int(found.group(2)) / 1e6
    return per


def _import_tables(scan_dir: Path, baseline: tuple[str, Path] | None, runs: int = 3) -> list[str]:
    """Import time by package for `process --help` and the process path, median of runs, and
    the same for the `baseline` commit's source tree if given (runs alternate between them)."""
    commands = {
        "`process --help`": ["-m", "silo_agent", "process", "--help"],
        "`process SCAN`": [
            "-m",
            "silo_agent",
            "process",
            str(scan_dir),
            "--grid-step",
            "0.01",
            "--json",
        ],
    }
    trees = {"": REPO} if baseline is None else {f" at {baseline[0]}": baseline[1], "": REPO}
    columns = {
        f"{name}{label}": (command, tree)
        for name, command in commands.items()
        for label, tree in trees.items()
    }
    tables: dict[str, list[dict[str, float]]] = {k: [] for k in columns}
    for _ in range(runs):
        for key, (command, tree) in columns.items():
            tables[key].append(_importtime(command, tree))
    names = sorted({n for runs_ in tables.values() for r in runs_ for n in r})

    def median_of(key: str, name: str) -> float:
        return statistics.median(r.get(name, 0.0) for r in tables[key])

    total = {
        k: statistics.median(sum(t for n, t in r.items() if n != F2PY_ALL) for r in v)
        for k, v in tables.items()
    }
    shown = sorted(
        (n for n in names if max(median_of(k, n) for k in tables) >= 0.01),
        key=lambda n: -median_of("`process SCAN`", n),
    )
    lines = [
        f"### Import time by package (`python -X importtime`, median of {runs})",
        "",
        "Self time of every module imported, summed per top-level package (`numpy.f2py` apart:"
        " numpy loads it lazily, and scipy 1.17's array-API layer, which every scipy submodule"
        " imports, touches it; the scan path imports scipy.ndimage for its filters). Packages"
        " under 10 ms in"
        " every column are in the total only."
        + (
            ""
            if baseline is None
            else f" Columns `at {baseline[0]}` are the source tree of"
            f" that commit (`git archive {baseline[0]}`), run alternately with this one."
        ),
        "",
        "| package | " + " | ".join(f"{k} s" for k in tables) + " |",
        "|---|" + "---|" * len(tables),
    ]
    lines += [
        f"| {n} | " + " | ".join(f"{median_of(k, n):.3f}" for k in tables) + " |" for n in shown
    ]
    lines.append("| **all imports** | " + " | ".join(f"**{total[k]:.3f}**" for k in tables) + " |")
    return [*lines, ""]


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="full", choices=["full", "crater"])
    timing_options(p, runs=5)
    p.add_argument("--all-cores", action="store_true", help="do not pin to one CPU")
    p.add_argument(
        "--quick", action="store_true", help="smoke run: 2 runs, two point counts, two grid steps"
    )
    p.add_argument(
        "--whole",
        action="store_true",
        help="only (c), the whole processes (default out: speed-process.md)",
    )
    p.add_argument(
        "--baseline",
        metavar="COMMIT",
        help="also time the imports of this commit's source tree, for comparison",
    )
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    args.out = args.out or Path(
        "bench/results/speed-process.md" if args.whole else "bench/results/speed.md"
    )
    points, steps = (POINTS[:2], STEPS[:2]) if args.quick else (POINTS, STEPS)
    runs = 2 if args.quick else args.runs
    if not args.all_cores:
        pinned(args.cpu)
    cores = sorted(os.sched_getaffinity(0))
    base = simulate(args.scene, VIEWS, seed=0)
    scan = resampled(base, 4 * 400_000)
    note = "QUICK RUN (smoke test, fewer runs and sizes); " if args.quick else ""
    load_before = os.getloadavg()
    head = header(
        "Speed benchmark",
        note + f"scene {args.scene}, views {', '.join(VIEWS)};"
        f" pinned to CPU(s) {cores} (subprocesses inherit it)",
    )
    lines: list[str] = []
    if not args.whole:
        cold_heap_s, _ = timed_reconstruct(scan, 0.01, runs)  # before keep_freed_memory
        keep_freed_memory()
        lines += section_a(scan, runs, cold_heap_s)
        lines += section_b(base, points, steps, runs)
    with tempfile.TemporaryDirectory(prefix="silo-speed-") as tmp:
        baseline = None
        if args.baseline:
            tree = Path(tmp) / "baseline"
            tree.mkdir()
            archive = subprocess.run(
                ["git", "archive", args.baseline], cwd=REPO, capture_output=True, check=True
            ).stdout
            subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
            baseline = (args.baseline, tree)
        lines += section_c(base, 2 if args.quick else 5, Path(tmp), baseline)
    before, after = (f"{a:.2f} / {b:.2f} / {c:.2f}" for a, b, c in (load_before, os.getloadavg()))
    load = (
        f"- machine load (`uptime` load average, 1 / 5 / 15 min) at start {before}, at end"
        f" {after}: other work shares the {os.cpu_count()} cores, figures are under that load"
    )
    lines = [*head[:-1], load, "", *lines]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
