"""Live map speed: frames in memory -> live map encoded, on one core.

Four wall D455s (848x480) watch the moving-robot scene (sim/robot.py); the frames of
`--maps` instants half a second apart are rendered first (not timed), then each map is timed
from the frames to the `P/heightmap/live` bytes: LiveMap.update (points to cells, robot,
running values, changed mask) + encode_live_heightmap. 2 cm grid over the 6 x 6 m region.
Target: <= 0.15 s per map (>= 2 Hz with headroom for a gateway 2-3x slower).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy: one core means one thread
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from benchlib import header, pinned

from silo_agent.config import LiveConfig
from silo_agent.grid.grid import Grid
from silo_agent.live.map import DepthFrame, LiveMap
from silo_agent.sim.robot import RobotRig
from silo_agent.telemetry.heightmap_codec import encode_live_heightmap

TARGET_S = 0.15


def rendered(rig: RobotRig, count: int) -> list[list[DepthFrame]]:
    out = []
    for index in range(count):
        frames = rig.frames(index * 0.5, index)
        out.append(
            [
                DepthFrame.rendered(v.serial, f, v.nominal)
                for v, f in zip(rig.views, frames, strict=True)
            ]
        )
    return out


def timed(
    frames: list[list[DepthFrame]], settings: LiveConfig, grid: Grid, ceiling_z: float | None
) -> tuple[list[float], list[float], list[int]]:
    """Per map: whole time (update + encode), encode alone, payload bytes. The first map
    (every cell new, ray tables built) is timed too but reported apart by the caller."""
    live = LiveMap(grid, settings, ceiling_z)
    whole, encode, sizes = [], [], []
    for index, per_camera in enumerate(frames):
        start = time.perf_counter()
        update = live.update(per_camera, index * 0.5)
        mid = time.perf_counter()
        payload = encode_live_heightmap(
            update.heightmap,
            "bench",
            update.sequence,
            {"robots": [r.to_json() for r in update.robots]},
            {"changed": update.changed, "held": update.held},
        )
        end = time.perf_counter()
        whole.append(end - start)
        encode.append(end - mid)
        sizes.append(len(payload))
    return whole, encode, sizes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", type=int, default=12, help="maps to time (at least 2)")
    parser.add_argument("--cpu", type=int, default=0, help="pin to this CPU (-1: do not pin)")
    parser.add_argument("--note", default="", help="a provenance line, e.g. machine load")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.maps < 2:  # the first map starts the session; the others are timed
        parser.error(f"--maps: at least 2, not {args.maps}")
    if args.cpu >= 0:
        pinned(args.cpu)
    rig = RobotRig()
    site = rig.robot.base.site
    grid = Grid.over(site.region, 0.02)
    frames = rendered(rig, args.maps)
    note = f"pinned to CPU(s) {sorted(os.sched_getaffinity(0))}, OMP/OPENBLAS threads 1"
    lines = header("Live map speed", note + (f"; {args.note}" if args.note else ""))
    lines += [
        "",
        f"Four cameras 848x480, the moving-robot scene, 2 cm grid over 6 x 6 m "
        f"({grid.shape[0]} x {grid.shape[1]} cells), {args.maps} maps 0.5 s apart; time from "
        "the frames in memory to the encoded `P/heightmap/live` payload. The first map "
        f"(ray tables built, every cell new) apart. Target <= {TARGET_S} s per map.",
        "",
        "| decimation | points per map | median s | p90 s | max s | first s | encode s "
        "| maps/s at the median | payload kB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for decimation in (1, 2):
        settings = LiveConfig(decimation=decimation)
        whole, encode, sizes = timed(frames, settings, grid, site.ceiling_z)
        steady = whole[1:]
        points = sum(int(np.count_nonzero(f.depth[::decimation, ::decimation])) for f in frames[1])
        median = statistics.median(steady)
        lines.append(
            f"| {decimation} | {points:,} | {median:.3f} | {np.percentile(steady, 90):.3f} "
            f"| {max(steady):.3f} | {whole[0]:.3f} | {statistics.median(encode[1:]):.3f} "
            f"| {1 / median:.1f} | {statistics.median(sizes) / 1000:.0f} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
