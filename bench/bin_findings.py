"""Piles and collapses on round bins seen from their eaves, with and without the cameras' noise
model: what pile detection and the collapse alarm find where the noise is not the bench's.

Each scene is scanned by eight eave cameras (the simulator's `eave` layout, A1-A8) at each
resolution, seeds 0..N-1. For each scan:

- piles: `detect_piles` as `analyse` runs it, without the noise model (`information=None`: one
  `min_prominence_m` everywhere, as before 2026-12-05) and with it (`Reconstruction.information`:
  a peak must also stand out of the cameras' noise there, detect/geometric.py NOISE_SIGMAS);
- collapses (bin-18 only): `find_collapses` between the seed's map and the next seed's, nothing
  changed (any collapse is false), and the same pair with a cone-shaped funnel of 1 m radius
  cut into the next seed's map at several places and depths (found if a collapse lies within
  1 m of it), without and with the noise model (alarms.py `noise_shape`).

Writes Markdown with its provenance (bench/results/bin-findings.md holds a run).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from benchlib import header, write_report

from silo_agent.analysis.alarms import find_collapses
from silo_agent.config import AlarmsConfig, DetectionConfig, ReconstructionConfig
from silo_agent.detect.geometric import Surface, detect_piles
from silo_agent.grid.heightmap import HeightMap
from silo_agent.reconstruct import Reconstruction, reconstruct
from silo_agent.sim import make_scene, simulate

VIEWS = [f"A{k}" for k in range(1, 9)]
HEAPS = {"bin-18": 1, "bin-heap": 1, "hopper-heap": 1, "bin-side": 1}  # scene: piles it holds
FUNNEL_RADIUS_M = 1.0
FUNNEL_DEPTHS_M = (0.3, 0.5)
FUNNEL_PLACES = ((0.0, 0.0), (2.0, 0.0), (4.0, 0.0), (7.0, 0.0), (0.0, -7.0))  # bin-18: R 9 m


def scans(name: str, resolution: tuple[int, int], seeds: int, step: float) -> list[Reconstruction]:
    settings = ReconstructionConfig(grid_step_m=step)
    return [
        reconstruct(
            simulate(name, VIEWS, seed=seed, layout="eave", resolution=resolution), settings
        )
        for seed in range(seeds)
    ]


def pile_count(result: Reconstruction, with_model: bool) -> int:
    hm = result.heightmap
    assert hm is not None
    information = result.information if with_model else None
    surface = Surface.for_piles(hm, "floor", hm.floor_z or 0.0, None, information)
    return len(detect_piles(surface, DetectionConfig()))


def collapses(
    before: HeightMap, after: HeightMap, information: np.ndarray | None
) -> list[tuple[float, float]]:
    cfg = AlarmsConfig()
    found = find_collapses(
        before,
        after,
        cfg.collapse_depth_m,
        cfg.collapse_min_area_m2,
        cfg.collapse_noise_k,
        information,
    )
    return [c.centroid for c in found]


def funnel_rows(results: list[Reconstruction], label: str) -> list[str]:
    rows = []
    for first, second in itertools.pairwise(results):
        before, after = first.heightmap, second.heightmap
        assert before is not None and after is not None
        x, y = after.cell_centres()
        for with_model in (False, True):
            information = second.information if with_model else None
            false = len(collapses(before, after, information))
            cells = []
            for depth in FUNNEL_DEPTHS_M:
                found = []
                for cx, cy in FUNNEL_PLACES:
                    cone = depth * np.clip(1 - np.hypot(x - cx, y - cy) / FUNNEL_RADIUS_M, 0, None)
                    cut = replace(after, heights=(after.heights - cone).astype(after.heights.dtype))
                    near = [
                        c
                        for c in collapses(before, cut, information)
                        if np.hypot(c[0] - cx, c[1] - cy) < 1.0
                    ]
                    found.append("yes" if near else "no")
                cells.append(" / ".join(found))
            model = "with" if with_model else "without"
            rows.append(f"| {label} | {model} | {false} | " + " | ".join(cells) + " |")
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3, help="seeds per scene and resolution")
    p.add_argument("--step", type=float, default=0.02, help="grid step (m)")
    p.add_argument("--resolutions", default="424x240,848x480,1280x720")
    p.add_argument("--scenes", default=",".join(HEAPS))
    p.add_argument("--out", type=Path, default=Path("bench/results/bin-findings.md"))
    args = p.parse_args(argv)
    load = os.getloadavg()
    resolutions = [tuple(int(v) for v in r.split("x")) for r in args.resolutions.split(",")]
    pile_lines = [
        "| scene | depth images | seed | piles it holds | found without the noise model"
        " | found with it |",
        "|---|---|---|---|---|---|",
    ]
    funnel_lines = [
        "| bin-18, depth images, seeds | noise model | false collapses (nothing changed) | "
        + " | ".join(
            f"{d} m funnel found at " + " / ".join(f"({x:g}, {y:g})" for x, y in FUNNEL_PLACES)
            for d in FUNNEL_DEPTHS_M
        )
        + " |",
        "|---|---|---|" + "---|" * len(FUNNEL_DEPTHS_M),
    ]
    for width, height in resolutions:
        for name in args.scenes.split(","):
            results = scans(name, (width, height), args.seeds, args.step)
            for seed, result in enumerate(results):
                pile_lines.append(
                    f"| {name} | {width}x{height} | {seed} | {HEAPS[name]} |"
                    f" {pile_count(result, False)} | {pile_count(result, True)} |"
                )
                print(pile_lines[-1], file=sys.stderr, flush=True)
            if name == "bin-18":
                for seed in range(len(results) - 1):
                    label = f"{width}x{height}, {seed} -> {seed + 1}"
                    funnel_lines += funnel_rows(results[seed : seed + 2], label)
                    print(funnel_lines[-1], file=sys.stderr, flush=True)
    truth = make_scene("bin-18")
    lines = [
        "## Piles",
        "",
        f"Eight eave cameras, {args.step * 100:g} cm grid; the geometric detector with the"
        " default `[detection]` settings (min_prominence_m 0.10).",
        "",
        *pile_lines,
        "",
        "## Collapses on bin-18",
        "",
        f"bin-18 ({truth.volume_m3:.0f} m³ of wheat, an 18 m bin, a 6 m heap), eight eave"
        f" cameras, {args.step * 100:g} cm grid, the default `[alarms]` (collapse_depth_m 0.10,"
        " collapse_min_area_m2 0.25, collapse_noise_k 5). Each pair is two scans of the same"
        " bin (seeds n and n + 1); a funnel is a cone 1 m in radius cut into the second map at"
        " (x, y), silo frame, the bin's centre at (0, 0): the heap spans r < 6 m, the level"
        " ring 6-9 m.",
        "",
        *funnel_lines,
        "",
    ]
    head = header("Piles and collapses on round bins seen from their eaves")
    write_report(args.out, head, load, lines, "counts only; no timing here")


if __name__ == "__main__":
    main()
