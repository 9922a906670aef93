"""Calibration on a walled bay (issue 7): does an empty bay, walls in view, calibrate better?

For every view set x seed, one rig of wall cameras (layout "wall", A1..A8 high on the walls)
whose true poses are 0.5 deg / 1 cm (random axis and direction, per camera; as
bench/calibration.py) off the extrinsics written in the scans. The rig renders two scenes with
the same true and nominal poses (the scenes share target and layout):

- `empty`: the bay before it is filled (floor and walls in every view), the calibration scan
  of the *empty-bay* workflow;
- `bay-cone`: the paper's 1.68 m³ pile in the bay, floor around it; the scan measured, and the
  calibration scan of the *pile* workflow (calibrating on the measurement scan itself), and
  with `--pool N` of the *pile, N scans pooled* workflow (it and N - 1 further frames).

Reported per workflow, after `calibrate(..., floor=True)`: the volume of the bay-cone scan
reconstructed with the calibrated extrinsics against the same scan with the true extrinsics
('perfect'), in percentage points of the exact volume; before calibration; the registration
residual (largest |median| over camera pairs) of the calibration scan before and after and of
the bay-cone scan with the calibrated extrinsics; the ICP pairs used; and the split of the
error left into its vertical and horizontal parts (bench/calibration.py's `split_errors`).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from benchlib import header, volume_m3
from calibration import (
    ERROR,
    TARGET_PP,
    VIEWS,
    floor_fit_height,
    max_residual,
    repeated_scans,
    split_errors,
)

from silo_agent.calibrate import (
    Calibration,
    calibrate,
    pool_scans,
    scan_residuals,
    with_extrinsics,
)
from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.sim.scenes import make_scene
from silo_agent.sim.simulate import SimRig, simulate

# workflow: (calibration scan, the calibration's settings); "floor only": the same leveling
# with no camera pair registered (min_overlap = 1), to show what the registration adds;
# with --pool N also "pile, N scans pooled": the bay-cone scan and N - 1 more frames of it
WORKFLOWS = {
    "empty-bay": ("empty", CalibrationConfig()),
    "empty-bay, floor only": ("empty", CalibrationConfig(min_overlap=1.0)),
    "pile": ("bay-cone", CalibrationConfig()),
}


def pooled_workflow(n: int) -> str:
    return f"pile, {n} scans pooled"


@dataclass(frozen=True)
class Outcome:
    """One workflow's calibration of one rig, judged on the bay-cone scan."""

    after_pp: float  # bay-cone volume with the calibrated extrinsics, minus perfect
    vertical_pp: float  # ... with only the vertical part of the pose errors left
    horizontal_pp: float  # ... only the horizontal part
    dilation_mm: float
    height_mm: float
    floor_fit_mm: float  # mean height at the pile centre of the floors fitted on true poses
    residual_before_m: float  # on the calibration scan
    residual_after_m: float  # on the calibration scan
    residual_cone_m: float  # on the bay-cone scan, with the calibrated extrinsics
    pairs: str  # ICP pairs: fitness, used or not
    seconds: float


@dataclass(frozen=True)
class Run:
    views: str
    seed: int
    perfect_pct: float
    before_pp: float
    residual_cone_before_m: float
    outcomes: dict[str, Outcome]


def _pairs(calibration: Calibration) -> str:
    return ", ".join(
        f"{p.a[4:]}-{p.b[4:]} {p.fitness:.2f}{'' if p.used else ' (unused)'}"
        for p in calibration.pairs
    )


def one(
    empty: SimRig,
    cone: SimRig,
    views: str,
    seed: int,
    settings: ReconstructionConfig,
    pool: int = 1,
) -> Run:
    empty_scan = simulate(empty.scene, VIEWS[views], seed, ERROR, rig=empty)
    cone_scans = repeated_scans(cone, views, seed, pool)  # the first is simulate(...)'s scan
    cone_scan = cone_scans[0]
    truth = {c.serial: np.asarray(c.extra["sim_true_extrinsic"]) for c in cone_scan.cameras}
    for a, b in zip(empty_scan.cameras, cone_scan.cameras, strict=True):  # one rig, two scenes
        assert a.serial == b.serial and np.array_equal(a.extrinsic, b.extrinsic)
        assert np.array_equal(np.asarray(a.extra["sim_true_extrinsic"]), truth[b.serial])

    def volume(poses: dict | None) -> float:
        cams = cone_scan.cameras if poses is None else with_extrinsics(cone_scan.cameras, poses)
        return volume_m3(replace(cone_scan, cameras=cams), settings)

    perfect = volume(truth)
    exact = cone.scene.volume_m3

    def pp(v: float) -> float:
        return 100.0 * (v - perfect) / exact

    pivot = np.array([cone.scene.target[0], cone.scene.target[1], cone.scene.site.floor_z])
    calibration_scans = {"empty": empty_scan, "bay-cone": cone_scan}
    workflows = dict(WORKFLOWS)
    if pool > 1:
        calibration_scans["pooled"] = pool_scans(cone_scans)
        workflows[pooled_workflow(pool)] = ("pooled", CalibrationConfig())
    outcomes = {}
    for workflow, (name, config) in workflows.items():
        scan = calibration_scans[name]
        started = time.perf_counter()
        result = calibrate(scan, config, floor=True)
        seconds = time.perf_counter() - started
        poses = result.extrinsics()
        vertical, horizontal, dilation, height = split_errors(poses, truth, pivot)
        on_cone = scan_residuals(
            with_extrinsics(cone_scan.cameras, poses), cone_scan.site, 0.02, config
        )
        outcomes[workflow] = Outcome(
            pp(volume(poses)),
            pp(volume(vertical)),
            pp(volume(horizontal)),
            dilation,
            height,
            floor_fit_height(scan, truth, pivot),
            max_residual(result.residual_before),
            max_residual(result.residual_after),
            max_residual(on_cone),
            _pairs(result),
            seconds,
        )
    before = scan_residuals(cone_scan.cameras, cone_scan.site, 0.02, CalibrationConfig())
    return Run(
        views, seed, 100.0 * (perfect / exact - 1), pp(volume(None)), max_residual(before), outcomes
    )


def rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def report(runs: list[Run]) -> list[str]:
    lines = [
        "## Volume after calibration, by workflow",
        "",
        "Volume of the bay-cone scan in percentage points of its exact volume, against the "
        "same scan reconstructed with the true extrinsics ('perfect'). *empty-bay*: "
        "`calibrate --floor` on a scan of the empty bay by the same rig; *empty-bay, floor "
        "only*: the same with no camera pair registered (`min_overlap = 1`: leveling on the "
        "floor, the rig's yaw and plan position kept as configured); *pile*: on the bay-cone "
        "scan itself; *pile, N scans pooled* (`--pool N`): on the bay-cone scan and N - 1 "
        "further frames of it pooled (`pool_scans`). Horizontal / vertical part: the scan "
        "reconstructed with only that part of each camera's remaining pose error kept (as in "
        "calibration.md). Dilation: mean radial error of the cameras' plan positions (+: too "
        "far out). Height: mean height error of the cameras' views at the pile's centre; "
        "floor fit on true poses: the same for the floor planes `calibrate` fits to each "
        "camera's points of the calibration scan placed with its true extrinsic (the "
        "leveling's own error).",
        "",
        f"| views | workflow | within {TARGET_PP} pp of perfect | mean abs (pp) "
        "| worst (pp) | mean abs vertical part (pp) | mean abs horizontal part (pp) "
        "| rms dilation (mm) | mean / rms height (mm) | mean / rms floor fit on true poses "
        "(mm) | worst residual, calibration scan after (mm) "
        "| worst residual, bay-cone scan after (mm) | calibrate time (s) |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
        "| ---: |",
    ]
    for views in VIEWS:
        rows = [r for r in runs if r.views == views]
        if not rows:
            continue
        before = np.abs([r.before_pp for r in rows])
        lines.append(
            f"| {views} | before calibration | {int((before <= TARGET_PP).sum())} of "
            f"{len(rows)} | {before.mean():.2f} | {before.max():.2f} | | | | | | | "
            f"{max(r.residual_cone_before_m for r in rows) * 1000:.1f} | |"
        )
        for workflow in rows[0].outcomes:
            got = [r.outcomes[workflow] for r in rows]
            after = np.abs([o.after_pp for o in got])
            lines.append(
                f"| {views} | {workflow} | {int((after <= TARGET_PP).sum())} of {len(got)} "
                f"| {after.mean():.2f} | {after.max():.2f} "
                f"| {np.mean([abs(o.vertical_pp) for o in got]):.2f} "
                f"| {np.mean([abs(o.horizontal_pp) for o in got]):.2f} "
                f"| {rms([o.dilation_mm for o in got]):.1f} "
                f"| {np.mean([o.height_mm for o in got]):+.2f} / "
                f"{rms([o.height_mm for o in got]):.2f} "
                f"| {np.mean([o.floor_fit_mm for o in got]):+.2f} / "
                f"{rms([o.floor_fit_mm for o in got]):.2f} "
                f"| {max(o.residual_after_m for o in got) * 1000:.1f} "
                f"| {max(o.residual_cone_m for o in got) * 1000:.1f} "
                f"| {np.mean([o.seconds for o in got]):.1f} |"
            )
    lines += [
        "",
        "### Every scan",
        "",
        "| views | seed | perfect (% of truth) | before (pp) | workflow | after (pp) "
        "| vertical part (pp) | horizontal part (pp) | dilation (mm) | height (mm) "
        "| residual calibration scan before / after (mm) | residual bay-cone after (mm) "
        "| ICP pairs (fitness) |",
        "| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for r in runs:
        for workflow, o in r.outcomes.items():
            lines.append(
                f"| {r.views} | {r.seed} | {r.perfect_pct:+.2f} | {r.before_pp:+.2f} "
                f"| {workflow} | {o.after_pp:+.2f} | {o.vertical_pp:+.2f} "
                f"| {o.horizontal_pp:+.2f} | {o.dilation_mm:+.1f} | {o.height_mm:+.2f} "
                f"| {o.residual_before_m * 1000:.1f} / {o.residual_after_m * 1000:.1f} "
                f"| {o.residual_cone_m * 1000:.1f} | {o.pairs} |"
            )
    return [*lines, ""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument(
        "--pool",
        type=int,
        default=1,
        metavar="N",
        help="also calibrate on N frames of the bay-cone scan pooled",
    )
    parser.add_argument(
        "--views", default=",".join(VIEWS), help=f"view sets, of {', '.join(VIEWS)}"
    )
    parser.add_argument("--out", type=Path, default=Path("bench/results/calibration_bay.md"))
    args = parser.parse_args()
    chosen = args.views.split(",")
    if set(chosen) - set(VIEWS):
        parser.error(f"--views: known view sets are {', '.join(VIEWS)}")
    settings = ReconstructionConfig()
    empty, cone = SimRig(make_scene("empty")), SimRig(make_scene("bay-cone"))
    runs = []
    for views in chosen:
        for seed in range(args.seeds):
            r = one(empty, cone, views, seed, settings, args.pool)
            runs.append(r)
            print(
                f"{views} seed {seed}: perfect {r.perfect_pct:+.2f} %, before "
                f"{r.before_pp:+.2f} pp; "
                + "; ".join(
                    f"{w}: after {o.after_pp:+.2f} pp (h {o.horizontal_pp:+.2f}, "
                    f"v {o.vertical_pp:+.2f}), residual {o.residual_after_m * 1000:.1f}"
                    f" mm, pairs {o.pairs}"
                    for w, o in r.outcomes.items()
                ),
                flush=True,
            )
    lines = header(
        "Calibration on a walled bay",
        f"injected error per camera: {ERROR[0]} deg about a random axis and "
        f"{ERROR[1] * 100:g} cm in a random direction; wall layout (cameras at "
        f"z = {cone.scene.wall_camera_z} m on the walls of the "
        f"{2 * cone.scene.wall_half_m:g} m bay); grid 2 cm; BICM defaults; "
        f"calibration defaults",
    )
    lines += report(runs)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
