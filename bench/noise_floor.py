"""How close a bin scan's volume can come to the truth on its own points: the noise floor.

Per seed, the engine's volume error beside what the points alone say of the grain's mean
height: each camera's cloud steadied as the engine steadies it (reconstruct/walls.py
`steadied`), the points over the true grain (0.15 m clear of the steel, 0.4 m inside the wall)
averaged per cell, their mean height error over the cells times the true grain area. That
mean is what any estimator that averages the points gets; its spread over seeds is the data's,
not the method's. Its offset is not the engine's (noise along rays on a slope, the margins),
so only spreads are compared: for an unbiased reading with that spread, the expected |error|
is sqrt(2 / pi) x its standard deviation, the floor under a scene's mean |volume error|.

An estimator that weighs the points could do better than their plain mean where a cell's
points differ in how well they are known: the D455 errs by z^2, so a point at 16 m is worth a
sixteenth of one at 8 m. The same mean with each point weighed by the inverse of its depth
variance (`depth_rms_m` at its depth, the textbook weights for independent errors) is the
floor of any estimator that averages the points by their range.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from accuracy import BIN_CAMERAS, BIN_STEP_M, split_views
from benchlib import header, write_report

from silo_agent.base.d455 import depth_rms_m
from silo_agent.config import ReconstructionConfig
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.walls import steadied
from silo_agent.sim.scenes import Scene, make_scene
from silo_agent.sim.simulate import SimRig, simulate

CLEAR_OF_STEEL_M = 0.15  # grain at least this far above the bin's bottom ...
INSIDE_WALL_M = 0.4  # ... and this far inside its wall
TRUTH_STEP_M = 0.01  # the true grain area, on cells this wide


@dataclass(frozen=True)
class SeedRow:
    resolution: str
    seed: int
    engine_pct: float  # signed volume error
    points_pct: float  # the points' mean height error over the grain, as a volume error
    weighted_pct: float  # the same, each point weighed by 1 / its depth variance


def grain_area_m2(scene: Scene) -> float:
    """The true grain's area in the bin: where the surface stands above the bottom."""
    assert scene.bin is not None
    r = scene.bin.radius_m
    cx, cy = scene.bin.centre
    ticks = np.arange(-r + TRUTH_STEP_M / 2, r, TRUTH_STEP_M)
    x, y = np.meshgrid(cx + ticks, cy + ticks)
    inside = np.hypot(x - cx, y - cy) < r
    grain = scene.height(x, y) > scene.bin.bottom(x, y) + 1e-6
    return float(np.sum(inside & grain)) * TRUTH_STEP_M**2


def points_mean_error_m(scene: Scene, cameras: Sequence, step: float) -> tuple[float, float]:
    """The mean over cells of the steadied points' height above the true surface, over the
    grain clear of steel and wall: (each cell's points alike, each weighed by 1 / its depth
    variance)."""
    assert scene.bin is not None
    cells, errors, weights = [], [], []
    for camera in cameras:
        moved = steadied(camera, scene.surface_factor)
        p = moved.points_in_silo().astype(np.float64)
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        truth = scene.height(x, y)
        cx, cy = scene.bin.centre
        keep = (truth > scene.bin.bottom(x, y) + CLEAR_OF_STEEL_M) & (
            np.hypot(x - cx, y - cy) < scene.bin.radius_m - INSIDE_WALL_M
        )
        column = np.floor(x[keep] / step).astype(np.int64)
        row = np.floor(y[keep] / step).astype(np.int64)
        cells.append(row * (1 << 32) + column)
        errors.append(z[keep] - truth[keep])
        depth = moved.points[keep, 2].astype(np.float64)
        rms = depth_rms_m(depth, float(camera.intrinsics["fx"]), scene.surface_factor)
        weights.append(1.0 / np.square(rms))
    _, cell = np.unique(np.concatenate(cells), return_inverse=True)
    error, weight = np.concatenate(errors), np.concatenate(weights)
    plain = np.bincount(cell, error) / np.bincount(cell)
    weighted = np.bincount(cell, error * weight) / np.bincount(cell, weight)
    return float(np.mean(plain)), float(np.mean(weighted))


def run_seed(scene_name: str, cameras: int, seed: int, resolution: tuple[int, int]) -> SeedRow:
    scene = make_scene(scene_name)
    scan = simulate(
        scene,
        split_views(BIN_CAMERAS[cameras]),
        seed=seed,
        rig=SimRig(scene),
        resolution=resolution,
    )
    truth = scan.extra["truth"]["volume_m3"]
    settings = ReconstructionConfig.model_validate(
        {"grid_step_m": BIN_STEP_M, "depth_noise_factor": scene.surface_factor}
    )
    volume = reconstruct(scan, settings).volume_m3
    assert volume is not None
    plain, weighted = points_mean_error_m(scene, scan.cameras, BIN_STEP_M)
    as_volume = 100 * grain_area_m2(scene) / truth
    return SeedRow(
        f"{resolution[0]}x{resolution[1]}",
        seed,
        100 * (volume - truth) / truth,
        plain * as_volume,
        weighted * as_volume,
    )


def summary(rows: list[SeedRow], resolutions: Sequence[str]) -> list[str]:
    lines = [
        "| depth images | seeds | engine: mean signed % | engine: mean abs % | engine: SD pp |"
        " points' mean: SD pp | correlation | floor: sqrt(2/pi) x points' SD, % |"
        " weighed by 1/depth variance: mean signed %, SD pp, floor % |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for size in resolutions:
        mine = [r for r in rows if r.resolution == size]
        engine = np.array([r.engine_pct for r in mine])
        points = np.array([r.points_pct for r in mine])
        correlation = float(np.corrcoef(engine, points)[0, 1])
        floor = np.sqrt(2 / np.pi) * points.std(ddof=1)
        weighted = np.array([r.weighted_pct for r in mine])
        lines.append(
            f"| {size} | {len(mine)} | {engine.mean():+.2f} | {np.abs(engine).mean():.2f} |"
            f" {engine.std(ddof=1):.2f} | {points.std(ddof=1):.2f} | {correlation:.2f} |"
            f" {floor:.2f} | {weighted.mean():+.2f}, {weighted.std(ddof=1):.2f},"
            f" {np.sqrt(2 / np.pi) * weighted.std(ddof=1):.2f} |"
        )
    return lines


def per_seed(rows: list[SeedRow]) -> list[str]:
    lines = [
        "| depth images | seed | engine volume err % | points' mean err, as volume % |"
        " weighed by 1/depth variance % |",
        "|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r.resolution, r.seed)):
        lines.append(
            f"| {r.resolution} | {r.seed} | {r.engine_pct:+.2f} | {r.points_pct:+.2f} |"
            f" {r.weighted_pct:+.2f} |"
        )
    return lines


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="hopper-low")
    p.add_argument("--cameras", type=int, choices=sorted(BIN_CAMERAS), default=4)
    p.add_argument("--seeds", type=int, default=20, help="seeds 0..N-1 (default 20)")
    p.add_argument(
        "--resolutions",
        type=lambda s: s.split(","),
        default=["848x480", "1280x720"],
        metavar="WxH,WxH",
    )
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path("bench/results/noise-floor.md"))
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    load = os.getloadavg()
    start = time.perf_counter()
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.resolutions]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = [
            pool.submit(run_seed, args.scene, args.cameras, seed, (w, h))
            for w, h in sizes
            for seed in range(args.seeds)
        ]
        rows = [f.result() for f in futures]
    minutes = (time.perf_counter() - start) / 60
    head = header(
        f"Noise floor: {args.scene}, {args.cameras} eave cameras",
        f"grid {BIN_STEP_M} m; seeds 0-{args.seeds - 1}; true grain area"
        f" {grain_area_m2(make_scene(args.scene)):.1f} m²; {len(rows)} scans in {minutes:.1f} min",
    )
    explained = [part.replace("\n", " ") for part in (__doc__ or "").strip().split("\n\n")[1:]]
    lines = [
        *(line for part in explained for line in (part, "")),
        *summary(rows, args.resolutions),
        "",
        *per_seed(rows),
    ]
    write_report(args.out, head, load, lines, "the scans' seconds, not their errors")


if __name__ == "__main__":
    main()
