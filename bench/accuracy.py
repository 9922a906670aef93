"""The paper's Table 1 experiment, reproduced in simulation (issue 3, "Accuracy benchmark").

Methods (alpha, poisson, hull, rectangle, bicm, and CloudCompare's 2.5D volume) x grid steps x
view combinations x scenes x seeds x calibration errors; every volume is compared with the
scene's exact volume. Writes a Markdown report and a plot of error against grid step.

`--bins`: round bins instead (bench/results/accuracy-round-bins.md): each bin scene seen by 2, 4
and 8 eave cameras, the region the wall circle; bicm with the bin's geometry, bicm without
it (the engine before it knew walls) and CloudCompare, against the scene's truth: volume,
highest and lowest grain, fill ratio and headspace.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from benchlib import TimedOut, call_with_timeout, cloudcompare_on_scan, fmt, header

from silo_agent.base.choices import SCENE_NAMES
from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.level import level_scan
from silo_agent.scan import Scan
from silo_agent.sim.scenes import make_scene
from silo_agent.sim.simulate import SimRig, simulate

METHODS = ("alpha", "poisson", "hull", "rectangle", "bicm")
SLOW = ("alpha", "poisson")  # run in a killable child under the time budget
CC = "cloudcompare"
STEPS = (0.1, 0.075, 0.05, 0.025, 0.01)
VIEWS = ("A1A5", "A1A4A6", "A1A3A5A7")
# the simulator's scenes with grain to measure (a volume error of "flat" and "empty" means nothing)
SCENES = tuple(name for name in SCENE_NAMES if name not in ("flat", "empty"))
DEFAULT_SCENES = SCENES[:5]  # the paper's open floor and the bay; the others on request
BAY_SCENES = ("crater", "full", "bay-cone", *SCENES[6:])  # the slowest groups, started first
FILLS = ("membrane", "bspline", "repose")
CALIBS: dict[str, tuple[float, float]] = {
    "none": (0.0, 0.0),
    "0.1°/3mm": (0.1, 0.003),
    "0.5°/1cm": (0.5, 0.01),
}
PAPER = {"alpha": 39.21, "poisson": 27.89, "hull": 16.29, "bicm": 3.52}  # Table 1 mean error


@dataclass(frozen=True)
class Row:
    """One volume: a method at a grid step on one simulated scan."""

    scene: str
    views: str
    seed: int
    calib: str
    method: str
    step: float
    truth: float
    volume: float | None
    seconds: float | None
    status: str  # ok | timeout | skipped | failed

    @property
    def error_pct(self) -> float | None:
        return None if self.volume is None else 100.0 * (self.volume - self.truth) / self.truth

    @property
    def n_views(self) -> int:
        return len(split_views(self.views))


def split_views(combo: str) -> list[str]:
    """'A1A3A5A7' -> ['A1', 'A3', 'A5', 'A7']."""
    return ["A" + part for part in combo.split("A") if part]


def _volume(scan: Scan, method: str, step: float, noise_factor: float) -> float | None:
    """`method` is a method's name, or bicm/FILL for bicm with that fill; METHOD+level: the
    scan leveled first as `calibration.level` levels it (each camera on the floor it sees).
    `noise_factor` is the scene's depth noise over the D455's ideal figure, set as an installer
    sets `depth_noise_factor` for their cameras (the volume's clip correction reads it)."""
    method, plus, _ = method.partition("+")
    if plus:
        scan, _, _ = level_scan(scan, CalibrationConfig(level=True))
    base, _, fill = method.partition("/")
    chosen = {"grid_step_m": step, "method": base, "depth_noise_factor": noise_factor}
    chosen |= {"fill": fill} if fill else {}
    return reconstruct(scan, ReconstructionConfig.model_validate(chosen)).volume_m3


def run_group(
    scene_name: str,
    views: str,
    seeds: Sequence[int],
    calibs: Sequence[str],
    steps: Sequence[float],
    methods: Sequence[str],
    budget_s: float,
    slow_seeds: int,
    workdir: str,
    noise_scale: float = 1.0,
) -> list[Row]:
    """Every scan of one (scene, views): simulate once per (seed, calib), run every method.
    The engine is told the scene's depth noise factor times `noise_scale` (1: the truth).

    alpha and poisson run only on seeds below `slow_seeds`. A slow method that overruns the
    budget at a step is not tried again at that step or any finer one for this (scene, views):
    its later cells are reported as skipped.
    """
    scene = make_scene(scene_name)
    rig = SimRig(scene)
    too_slow: dict[str, float] = {}  # method -> coarsest step that overran
    rows: list[Row] = []
    for seed in seeds:
        for calib in calibs:
            scan = simulate(
                scene, split_views(views), seed=seed, calib_error=CALIBS[calib], rig=rig
            )
            truth = float(scan.extra["truth"]["volume_m3"])
            for method in methods:
                if method in SLOW and seed >= slow_seeds:
                    continue
                for step in sorted(steps, reverse=True):
                    rows.append(
                        _one(
                            scan,
                            truth,
                            (scene_name, views, seed, calib),
                            method,
                            step,
                            too_slow,
                            budget_s,
                            Path(workdir),
                            noise_scale * scene.surface_factor,
                        )
                    )
            print(f"  {scene_name} {views} seed {seed} calib {calib}: done", file=sys.stderr)
    return rows


def _one(
    scan: Scan,
    truth: float,
    key: tuple[str, str, int, str],
    method: str,
    step: float,
    too_slow: dict[str, float],
    budget_s: float,
    workdir: Path,
    noise_factor: float,
) -> Row:
    if method in too_slow and step <= too_slow[method] + 1e-12:
        return Row(*key, method, step, truth, None, None, "skipped")
    start = time.perf_counter()
    try:
        if method == CC:
            volume: float | None = cloudcompare_on_scan(scan, step, workdir).volume_m3
        elif method in SLOW:
            volume = call_with_timeout(lambda: _volume(scan, method, step, noise_factor), budget_s)
        else:
            volume = _volume(scan, method, step, noise_factor)
    except TimedOut:
        too_slow[method] = max(too_slow.get(method, 0.0), step)
        return Row(*key, method, step, truth, None, budget_s, "timeout")
    except Exception as error:  # a failing baseline is a result, not a crash
        print(f"  {key} {method} {step}: {error!r}", file=sys.stderr)
        return Row(*key, method, step, truth, None, None, "failed")
    return Row(
        *key,
        method,
        step,
        truth,
        volume,
        time.perf_counter() - start,
        "ok" if volume is not None else "failed",
    )


# ---------------------------------------------------------------- report


def _abs_errors(rows: Iterable[Row]) -> list[float]:
    return [abs(e) for r in rows if (e := r.error_pct) is not None]


def _spreads(rows: Iterable[Row]) -> list[float]:
    """Per scan and method: max - min signed error across grid steps (percentage points)."""
    by_scan: dict[tuple, list[float]] = defaultdict(list)
    for r in rows:
        if r.error_pct is not None:
            by_scan[(r.scene, r.views, r.seed, r.calib, r.method)].append(r.error_pct)
    return [max(e) - min(e) for e in by_scan.values() if len(e) > 1]


def _missing(rows: Iterable[Row]) -> int:
    return sum(r.status != "ok" for r in rows)


def _stats_cells(rows: list[Row]) -> list[str]:
    errors, spreads = _abs_errors(rows), _spreads(rows)
    missing = _missing(rows)
    mean = fmt(float(np.mean(errors)), ".2f") if errors else "—"
    return [
        mean + ("¹" if missing and errors else ""),
        fmt(max(errors), ".2f") if errors else "—",
        fmt(float(np.mean(spreads)), ".2f") if spreads else "—",
        fmt(max(spreads), ".2f") if spreads else "—",
    ]


def paper_table(
    rows: list[Row], methods: Sequence[str], steps: Sequence[float], scene: str, views: str
) -> list[str]:
    """Table 1's shape: volume per method and step (mean over seeds), truth, error rows."""
    sel = [r for r in rows if r.scene == scene and r.views == views and r.calib == "none"]
    seeds = sorted({r.seed for r in sel})
    lines = [
        f"## (a) Table 1 shape: {scene}, {views}, no calibration error",
        "",
        f"Volume in m³, mean over seeds {', '.join(map(str, seeds))}; errors are |volume - true|"
        " / true over every step and seed. Paper's mean error: "
        + ", ".join(f"{m} {v} %" for m, v in PAPER.items())
        + ".",
        "",
        "| grid step (m) | " + " | ".join(methods) + " |",
        "|---" * (len(methods) + 1) + "|",
    ]
    for step in steps:
        cells = []
        for m in methods:
            vols = [
                r.volume for r in sel if r.method == m and r.step == step and r.volume is not None
            ]
            missing = any(r.status != "ok" for r in sel if r.method == m and r.step == step)
            cell = fmt(float(np.mean(vols))) if vols else "—"
            cells.append(cell + ("¹" if missing else ""))
        lines.append(f"| grid_{step:g} | " + " | ".join(cells) + " |")
    truth = sel[0].truth if sel else float("nan")
    lines.append("| true volume | " + " | ".join(fmt(truth, ".3f") for _ in methods) + " |")
    for name, fn in (
        ("maximum error", max),
        ("minimum error", min),
        ("average error", lambda e: float(np.mean(e))),
    ):
        cells = []
        for m in methods:
            errors = _abs_errors(r for r in sel if r.method == m)
            cells.append(f"{fn(errors):.2f} %" if errors else "—")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def summary_table(rows: list[Row], methods: Sequence[str], title: str) -> list[str]:
    """Per calibration level, per view count and method: error and spread statistics."""
    lines = [title, ""]
    for calib in CALIBS:
        at = [r for r in rows if r.calib == calib]
        if not at:
            continue
        lines += [
            f"Calibration error: **{calib}**",
            "",
            "| views | method | mean abs err % | max abs err % | mean spread pp | max spread pp |",
            "|---|---|---|---|---|---|",
        ]
        for n in sorted({r.n_views for r in at}):
            group = [r for r in at if r.n_views == n]
            means = {
                m: np.mean(e)
                for m in methods
                if (e := _abs_errors(r for r in group if r.method == m))
            }
            best = min(means, key=lambda m: means[m]) if means else None
            for m in methods:
                cells = _stats_cells([r for r in group if r.method == m])
                if m == best:
                    cells[0] = f"**{cells[0]}**"
                lines.append(f"| {n} | {m} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def per_scan_table(rows: list[Row], methods: Sequence[str], steps: Sequence[float]) -> list[str]:
    """Every scan's signed error at each step and its spread, for the bicm methods."""
    shown = [m for m in methods if m.startswith("bicm")]
    lines = [
        "## (e) Every scan across grid steps",
        "",
        "Signed error (%) at each step; spread = largest minus smallest (pp).",
        "",
        "| scene | views | seed | calibration | method | "
        + " | ".join(f"{s:g} m" for s in steps)
        + " | spread pp |",
        "|---" * (len(steps) + 6) + "|",
    ]
    scans = sorted({(r.scene, r.views, r.seed, r.calib) for r in rows})
    for scene, views, seed, calib in scans:
        for m in shown:
            at = {
                r.step: r.error_pct
                for r in rows
                if (r.scene, r.views, r.seed, r.calib, r.method) == (scene, views, seed, calib, m)
            }
            errors = [e for e in at.values() if e is not None]
            if not errors:
                continue
            cells = [fmt(e, "+.2f") if (e := at.get(s)) is not None else "—" for s in steps]
            spread = fmt(max(errors) - min(errors), ".2f")
            lines.append(
                f"| {scene} | {views} | {seed} | {calib} | {m} | {' | '.join(cells)} | {spread} |"
            )
    return [*lines, ""]


def skipped_note(rows: list[Row], budget_s: float) -> list[str]:
    """Footnote: every cell that has no volume and why."""
    counts: dict[tuple[str, float, str], int] = defaultdict(int)
    for r in rows:
        if r.status != "ok":
            counts[(r.method, r.step, r.status)] += 1
    if not counts:
        return ["All runs produced a volume; nothing was skipped.", ""]
    lines = [
        f'¹ Some runs have no volume and are left out of that cell\'s statistics ("—" where'
        f" none is left). Slow methods get {budget_s:g} s per run; one that overruns at a step"
        " is killed and not tried again at that step or finer ones for the same scene and"
        ' views ("skipped"). Missing runs:',
        "",
    ]
    lines += [f"- {m} at {s:g} m: {n} {status}" for (m, s, status), n in sorted(counts.items())]
    return [*lines, ""]


def timing_table(rows: list[Row], methods: Sequence[str], steps: Sequence[float]) -> list[str]:
    """Mean seconds per run (including the fuse and crop; CloudCompare: PLY write + process)."""
    lines = [
        "## (d) Run time per method and step",
        "",
        "Mean seconds per run that produced a volume, all scans; timings are noisy when the"
        " machine is shared.",
        "",
        "| method | " + " | ".join(f"{s:g} m" for s in steps) + " |",
        "|---" * (len(steps) + 1) + "|",
    ]
    for m in methods:
        cells = []
        for step in steps:
            secs = [
                r.seconds
                for r in rows
                if r.method == m and r.step == step and r.status == "ok" and r.seconds is not None
            ]
            cells.append(fmt(float(np.mean(secs)), ".2f") if secs else "—")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def plot(rows: list[Row], methods: Sequence[str], steps: Sequence[float], path: Path) -> None:
    """Mean |error| against grid step per method, one panel per view count (paper fig. 27)."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = [r for r in rows if r.calib == "none"] or rows
    counts = sorted({r.n_views for r in base})
    fig, axes = plt.subplots(
        1, len(counts), figsize=(5 * len(counts), 4), squeeze=False, sharey=True
    )
    for ax, n in zip(axes[0], counts, strict=True):
        for m in methods:
            xs, ys = [], []
            for step in steps:
                runs = [r for r in base if r.n_views == n and r.method == m and r.step == step]
                if runs and _missing(runs) == 0:  # a partial mean would mix other scenes
                    xs.append(step)
                    ys.append(float(np.mean(_abs_errors(runs))))
            ax.plot(
                xs,
                ys,
                marker="D" if m.startswith("bicm") else "o",
                label=m,
                linewidth=2.5 if m.startswith("bicm") else 1.2,
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(list(steps), [f"{s:g}" for s in steps])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("grid step (m)")
        ax.set_title(f"{n} views, no calibration error")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("mean |volume error| (%)")
    axes[0][-1].legend(fontsize=8)
    fig.suptitle(
        "Volume error against grid step, all scenes and seeds (a method is drawn"
        " only at steps where every run finished)",
        fontsize=9,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def report(
    rows: list[Row], args: argparse.Namespace, methods: Sequence[str], elapsed_s: float
) -> str:
    scenes, views = args.scenes, args.views
    paper_scene = "cone" if "cone" in scenes else scenes[0]
    paper_views = "A1A5" if "A1A5" in views else views[0]
    note = "QUICK RUN (smoke test subset, not the benchmark result); " if args.quick else ""
    if args.noise_scale != 1.0:
        note += f"the engine told {args.noise_scale:g} x each scene's depth noise factor; "
    lines = header(
        "Accuracy benchmark (paper Table 1 in simulation)",
        note + f"scenes {', '.join(scenes)}; views {', '.join(views)}; seeds"
        f" {', '.join(map(str, range(args.seeds)))}; steps {', '.join(map(str, args.steps))};"
        f" calibration errors {', '.join(args.calibs)}; {len(rows)} volumes in"
        f" {elapsed_s / 60:.1f} min",
    )
    lines += [
        'Errors are signed (volume - true) / true in %; "abs err" is its absolute value.'
        ' "spread" is, per scan and method, the largest minus the smallest signed error across'
        " the grid steps (percentage points). `cloudcompare` is CloudCompare's 2.5D volume"
        " (`-VOLUME -GRID_STEP s -CONST_HEIGHT floor_z`, empty cells left empty) on the fused,"
        " cropped cloud. Best mean per group in bold.",
        "",
    ]
    lines += paper_table(rows, methods, args.steps, paper_scene, paper_views)
    lines += summary_table(rows, methods, "## (b) Summary per view count, all scenes and seeds")
    lines.append("## (c) Per scene")
    lines.append("")
    for scene in scenes:
        lines += summary_table([r for r in rows if r.scene == scene], methods, f"### {scene}")
    lines += timing_table(rows, methods, args.steps)
    if args.per_scan:
        lines += per_scan_table(rows, methods, args.steps)
    lines += skipped_note(rows, args.budget)
    slow = [m for m in methods if m in SLOW]
    if slow and args.slow_seeds < args.seeds:
        seeds = ", ".join(map(str, range(args.slow_seeds)))
        lines += [
            f"{' and '.join(slow)} ran on seed(s) {seeds}"
            f" only (`--slow-seeds {args.slow_seeds}`), to keep the run short; their"
            " statistics cover those scans.",
            "",
        ]
    return "\n".join(lines)


# ---------------------------------------------------------------- round bins

BIN_SCENES = ("bin-heap", "bin-crater", "bin-side", "hopper-heap", "hopper-low", "bin-18")
BIN_CAMERAS = {2: "A1A5", 4: "A1A3A5A7", 8: "A1A2A3A4A5A6A7A8"}
BIN_STEP_M = 0.05
BIN_METHODS = ("bicm", "bicm, no bin geometry", CC)


@dataclass(frozen=True)
class BinRow:
    """One bin scan read one way, against the scene's truth."""

    scene: str
    cameras: int
    seed: int
    resolution: str
    method: str
    volume_pct: float | None
    level_max_m: float | None  # signed errors
    level_min_m: float | None
    fill_pp: float | None
    headspace_m: float | None
    seconds: float


def _bin_reading(
    scan: Scan, method: str, workdir: Path, noise_factor: float
) -> tuple[dict | None, float]:
    """(summary, seconds) of one method on a bin scan; CloudCompare gives a volume only.
    `noise_factor`: the scene's depth noise factor, as `_volume`."""
    start = time.perf_counter()
    if method == CC:
        volume = cloudcompare_on_scan(scan, BIN_STEP_M, Path(workdir)).volume_m3
        return {"volume_m3": volume}, time.perf_counter() - start
    settings = ReconstructionConfig.model_validate(
        {"grid_step_m": BIN_STEP_M, "depth_noise_factor": noise_factor}
    )
    site = replace(scan.site, bin=None) if method != "bicm" else None
    result = reconstruct(scan, settings, site=site)
    seconds = time.perf_counter() - start
    level = None
    if result.surface is not None:
        s, floor = result.surface, result.floor_z
        level = {"min": s.min - floor, "mean": s.mean - floor, "max": s.max - floor}
    return {"volume_m3": result.volume_m3, "level": level, **result.bin_figures()}, seconds


def _error(value: float | None, truth: float, scale: float = 1.0) -> float | None:
    return None if value is None else (value - truth) * scale


def run_bin_group(
    scene_name: str, cameras: int, seeds: Sequence[int], resolution: tuple[int, int], workdir: str
) -> list[BinRow]:
    """Every method on every seed of one (bin scene, camera count)."""
    scene = make_scene(scene_name)
    rig = SimRig(scene)
    rows = []
    size = f"{resolution[0]}x{resolution[1]}"
    for seed in seeds:
        views = split_views(BIN_CAMERAS[cameras])
        scan = simulate(scene, views, seed=seed, rig=rig, resolution=resolution)
        truth = scan.extra["truth"]
        for method in BIN_METHODS:
            summary, seconds = _bin_reading(scan, method, Path(workdir), scene.surface_factor)
            assert summary is not None
            level = summary.get("level") or {}
            volume = summary.get("volume_m3")
            fill = volume / truth["capacity_m3"] if volume is not None else None
            rows.append(
                BinRow(
                    scene_name,
                    cameras,
                    seed,
                    size,
                    method,
                    _error(volume, truth["volume_m3"], 100.0 / truth["volume_m3"]),
                    _error(level.get("max"), truth["level_max_m"]),
                    _error(level.get("min"), truth["level_min_m"]),
                    _error(fill, truth["fill_ratio"], 100.0),
                    _error(summary.get("headspace_m"), truth["headspace_m"]),
                    seconds,
                )
            )
        print(f"  {scene_name} {cameras} cameras seed {seed} {size}: done", file=sys.stderr)
    return rows


def _mean_abs(values: Iterable[float | None], spec: str) -> str:
    got = [abs(v) for v in values if v is not None]
    return fmt(float(np.mean(got)), spec) if got else "—"


def _worst(values: Iterable[float | None], spec: str) -> str:
    got = [v for v in values if v is not None]
    return fmt(max(got, key=abs), spec) if got else "—"


def bin_report(rows: list[BinRow], args: argparse.Namespace, elapsed_s: float) -> str:
    lines = header(
        "Accuracy benchmark: round bins, eave cameras, region = the wall circle",
        f"scenes {', '.join(args.bin_scenes)}; cameras {', '.join(map(str, args.bin_cameras))};"
        f" seeds {', '.join(map(str, range(args.seeds)))}; depth images"
        f" {args.resolution[0]}x{args.resolution[1]}; grid {BIN_STEP_M:g} m;"
        f" {len(rows)} readings in {elapsed_s / 60:.1f} min",
    )
    lines += [
        "Errors against the simulator's exact truth: volume in % (signed, and |mean| over"
        " seeds), levels and headspace in metres (signed; the worst seed), fill ratio in"
        " percentage points. `bicm` is the engine with the bin's geometry (`[silo.bin]`, the"
        " scan's `site.bin`): wall points dropped, the hopper counted, grain levels;"
        " `bicm, no bin geometry` the same engine told only the region (what it did before);"
        " `cloudcompare` its 2.5D volume above the floor plane on the fused, cropped cloud"
        " (it cannot count a hopper: its hopper rows measure above the floor plane only).",
        "",
        "## Summary per camera count (all scenes and seeds)",
        "",
        "| cameras | method | mean abs volume err % | worst volume err % | mean abs level.max err m"
        " | mean abs level.min err m | mean abs headspace err m |",
        "|---|---|---|---|---|---|---|",
    ]
    for cameras in args.bin_cameras:
        for method in BIN_METHODS:
            sel = [r for r in rows if r.cameras == cameras and r.method == method]
            if not sel:
                continue
            lines.append(
                f"| {cameras} | {method} | {_mean_abs((r.volume_pct for r in sel), '.2f')} |"
                f" {_worst((r.volume_pct for r in sel), '+.2f')} |"
                f" {_mean_abs((r.level_max_m for r in sel), '.3f')} |"
                f" {_mean_abs((r.level_min_m for r in sel), '.3f')} |"
                f" {_mean_abs((r.headspace_m for r in sel), '.3f')} |"
            )
    lines += [
        "",
        "## Per scene",
        "",
        "| scene | cameras | method | mean abs volume err % | worst volume err % | level.max err m"
        " | level.min err m | fill err pp | headspace err m | s per reading |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for scene in args.bin_scenes:
        for cameras in args.bin_cameras:
            for method in BIN_METHODS:
                sel = [
                    r
                    for r in rows
                    if r.scene == scene and r.cameras == cameras and r.method == method
                ]
                if not sel:
                    continue
                lines.append(
                    f"| {scene} | {cameras} | {method} |"
                    f" {_mean_abs((r.volume_pct for r in sel), '.2f')} |"
                    f" {_worst((r.volume_pct for r in sel), '+.2f')} |"
                    f" {_worst((r.level_max_m for r in sel), '+.3f')} |"
                    f" {_worst((r.level_min_m for r in sel), '+.3f')} |"
                    f" {_worst((r.fill_pp for r in sel), '+.2f')} |"
                    f" {_worst((r.headspace_m for r in sel), '+.3f')} |"
                    f" {fmt(float(np.mean([r.seconds for r in sel])), '.2f')} |"
                )
    return "\n".join([*lines, ""])


def bins_main(args: argparse.Namespace) -> None:
    start = time.perf_counter()
    rows: list[BinRow] = []
    with (
        tempfile.TemporaryDirectory(prefix="silo-bench-") as workdir,
        ProcessPoolExecutor(max_workers=args.jobs) as pool,
    ):
        futures = [
            pool.submit(run_bin_group, scene, cameras, range(args.seeds), args.resolution, workdir)
            for scene in args.bin_scenes
            for cameras in sorted(args.bin_cameras, reverse=True)
        ]
        for future in futures:
            rows += future.result()
    elapsed = time.perf_counter() - start
    out = args.out if args.out != Path("bench/results/accuracy.md") else BIN_OUT
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(bin_report(rows, args, elapsed))
    print(f"wrote {out} ({len(rows)} readings, {elapsed / 60:.1f} min)")


BIN_OUT = Path("bench/results/accuracy-round-bins.md")


def _resolution(text: str) -> tuple[int, int]:
    width, height = (int(v) for v in text.lower().split("x"))
    return width, height


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--scenes",
        type=lambda s: s.split(","),
        default=list(DEFAULT_SCENES),
        help=f"comma list of {', '.join(SCENES)} (default the first five)",
    )
    p.add_argument("--seeds", type=int, default=2, help="seeds 0..N-1 (default 2)")
    p.add_argument("--steps", type=lambda s: [float(x) for x in s.split(",")], default=list(STEPS))
    p.add_argument(
        "--methods",
        type=lambda s: s.split(","),
        default=[*METHODS, CC],
        help=f"comma list of {', '.join([*METHODS, CC])}",
    )
    p.add_argument(
        "--fills",
        type=lambda s: s.split(","),
        default=[],
        help=f"bicm once per fill, as bicm/FILL (comma list of {', '.join(FILLS)}); default"
        " bicm with the configured fill",
    )
    p.add_argument(
        "--level",
        action="store_true",
        help="also every bicm method on the scan leveled first (`calibration.level`), as"
        " METHOD+level",
    )
    p.add_argument(
        "--per-scan",
        action="store_true",
        help="also list every scan's error at each step and its spread (bicm methods)",
    )
    p.add_argument("--views", type=lambda s: s.split(","), default=list(VIEWS))
    p.add_argument(
        "--calibs",
        type=lambda s: s.split(","),
        default=list(CALIBS),
        help=f"comma list of {', '.join(CALIBS)}",
    )
    p.add_argument(
        "--budget",
        type=float,
        default=10.0,
        help="seconds per alpha/poisson run before it is killed (default 10)",
    )
    p.add_argument(
        "--slow-seeds",
        type=int,
        default=1,
        help="run alpha and poisson on seeds 0..K-1 only (default 1: they take most of the time)",
    )
    p.add_argument(
        "--noise-scale",
        type=float,
        default=1.0,
        help="tell the engine each scene's depth noise factor times this (default 1: the"
        " simulator's own; 2.5 on the open scenes: the config's default, as on a site where"
        " it was never measured)",
    )
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: cone and crater, seed 0, A1A5 and A1A3A5A7, three steps,"
        " no error and 0.5°/1cm",
    )
    p.add_argument(
        "--bins",
        action="store_true",
        help="round bins instead (writes bench/results/accuracy-round-bins.md)",
    )
    p.add_argument(
        "--bin-scenes", type=lambda s: s.split(","), default=list(BIN_SCENES), metavar="A,B"
    )
    p.add_argument(
        "--bin-cameras",
        type=lambda s: [int(x) for x in s.split(",")],
        default=sorted(BIN_CAMERAS),
        metavar="2,4,8",
    )
    p.add_argument(
        "--resolution", type=_resolution, default=(848, 480), help="bins: depth image WxH"
    )
    p.add_argument("--out", type=Path, default=Path("bench/results/accuracy.md"))
    p.add_argument("--plot", type=Path, default=Path("bench/results/accuracy.png"))
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.seeds, args.views = ["cone", "crater"], 1, ["A1A5", "A1A3A5A7"]
        args.steps, args.calibs = [0.1, 0.05, 0.025], ["none", "0.5°/1cm"]
    unknown = (
        ({*args.methods} - {*METHODS, CC})
        | ({*args.calibs} - {*CALIBS})
        | ({*args.scenes} - {*SCENES})
        | ({*args.fills} - {*FILLS})
    )
    if unknown:
        p.error(f"unknown method, calibration, scene or fill: {', '.join(sorted(unknown))}")
    args.steps = sorted(args.steps, reverse=True)
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    if args.bins:
        bins_main(args)
        return
    methods = [m for m in [*METHODS, CC] if m in args.methods]
    if args.fills and "bicm" in methods:
        at = methods.index("bicm")
        methods[at : at + 1] = [f"bicm/{fill}" for fill in args.fills]
    if args.level:
        methods += [f"{m}+level" for m in methods if m.startswith("bicm")]
    start = time.perf_counter()
    rows: list[Row] = []
    with (
        tempfile.TemporaryDirectory(prefix="silo-bench-") as workdir,
        ProcessPoolExecutor(max_workers=args.jobs) as pool,
    ):
        groups = sorted(
            ((scene, views) for scene in args.scenes for views in args.views),
            key=lambda g: (g[0] not in BAY_SCENES, -len(g[1])),
        )  # longest first
        futures = [
            pool.submit(
                run_group,
                scene,
                views,
                range(args.seeds),
                args.calibs,
                args.steps,
                methods,
                args.budget,
                args.slow_seeds,
                workdir,
                args.noise_scale,
            )
            for scene, views in groups
        ]
        for future in futures:
            rows += future.result()
    elapsed = time.perf_counter() - start
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(report(rows, args, methods, elapsed) + "\n")
    plot(rows, methods, args.steps, args.plot)
    print(f"wrote {args.out} and {args.plot} ({len(rows)} volumes, {elapsed / 60:.1f} min)")


if __name__ == "__main__":
    main()
