"""Live map with the raking robot: map age, grain accuracy away from the robot, and how far the
map stands above the grain in the robot's footprint, per camera setup.

The moving-robot scene (sim/robot.py: wall cameras, a robot raking the first of two heaps at
0.3 m/s, D455 noise with mixed pixels along depth edges), or the same robot raking a round
bin's heap under its eave cameras (`in_bin`: the far wall in view, the bin's noise), is
rendered at the instants of a 2 Hz session (`--seconds` long; not timed). Then:

- accuracy: `LiveMap.update` on each instant's frames, against the scene's exact surface:
  grain RMS over the observed cells more than 0.5 m outside the robot's footprint, and the
  map's highest cell above the grain inside the footprint (the robot leaking into the map);
  the first `--warm-up-s` (running values averaging the noise down, nothing yet known under
  the robot, which stands in the bay from the start) are reported apart;
- age: the real `LiveSession` (its pacing, its map builds, the encoding) at 2 Hz on frames
  served as a camera serves them (the newest rendered instant), one core: the share of maps
  at least a period old when sent;
- the session-start check (live/coverage.py): whether the setup is accepted;
- in a bin, the highest cell within 0.5 m of the wall above the grain, and the robots found
  away from the robot.

Targets (#25): 4 wall cameras at 424x240: <= 10 % of maps a period old, RMS <= 20 mm, footprint
never more than 30 mm above the grain; at 848x480 <= 10 mm and <= 20 mm.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy: one core means one thread
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from benchlib import big_bin, header, pinned

from silo_agent.config import Config, LiveConfig, parse_config
from silo_agent.grid.grid import Grid
from silo_agent.live.coverage import session_problem
from silo_agent.live.map import DepthFrame, LiveMap
from silo_agent.live.session import LiveSession
from silo_agent.sim.grains import grain
from silo_agent.sim.robot import RakingRobot, RobotRig, in_bin, mounded_bay
from silo_agent.sim.scenes import bin_scene

RATE_HZ = 2.0
AWAY_M = 0.5
WALL_RING_M = 0.5  # a bin's cells this near its wall: where its wall's points would land
PHANTOM_M = 1.0  # a robot found farther than this from the robot is none
EAVE_4, EAVE_8 = ("A1", "A3", "A5", "A7"), tuple(f"A{k}" for k in range(1, 9))
SETUPS = {  # name -> scene, views, width, height
    "4 wall cameras, 848x480": ("bay", ("A2", "A4", "A6", "A8"), 848, 480),
    "4 wall cameras, 424x240": ("bay", ("A2", "A4", "A6", "A8"), 424, 240),
    "2 wall cameras, 424x240": ("bay", ("A2", "A6"), 424, 240),
    "4 wall cameras, 320x180": ("bay", ("A2", "A4", "A6", "A8"), 320, 180),
    "8 m bin, 4 eave cameras, 848x480": ("bin-8", EAVE_4, 848, 480),
    "8 m bin, 8 eave cameras, 424x240": ("bin-8", EAVE_8, 424, 240),
    "8 m bin, 8 eave cameras, 848x480": ("bin-8", EAVE_8, 848, 480),
    "8 m bin, 8 eave cameras, 1280x720": ("bin-8", EAVE_8, 1280, 720),
    "8 m side-draw bin, 8 eave cameras, 1280x720": ("bin-8-side", EAVE_8, 1280, 720),
    "10 m bin, 8 eave cameras, 1280x720": ("bin-10", EAVE_8, 1280, 720),
    "12 m bin, 8 eave cameras, 1280x720": ("bin-12", EAVE_8, 1280, 720),
}
BAY_SETUPS = [name for name, setup in SETUPS.items() if setup[0] == "bay"]


def robot_for(scene: str) -> RakingRobot:
    """The raking robot in the bay, or across the heap of a round bin (8 m, eave 6 m: a bin
    whose eight eave cameras pass the session check at 1280x720, heaped or drawn down at the
    side; 10 m: the simulator's
    default bin, eave 7 m; 12 m: bench/silos.py's, eave 8 m)."""
    if scene == "bay":
        return RakingRobot(mounded_bay(grain("wheat")))
    if scene == "bin-8":
        return in_bin(
            bin_scene(
                grain("wheat"), name="bin-8m", diameter_m=8.0, eave_m=6.0, feature_radius_m=3.0
            )
        )
    if scene == "bin-8-side":  # drawn down at the wall (+x), level 1.5 m elsewhere
        return in_bin(
            bin_scene(
                grain("wheat"),
                name="bin-8m-side",
                diameter_m=8.0,
                eave_m=6.0,
                surface="side",
                level_m=1.5,
                feature_radius_m=3.0,
            )
        )
    if scene == "bin-10":
        return in_bin(bin_scene(grain("wheat"), name="bin-10m"))
    return in_bin(big_bin(12.0))


@dataclass
class Accuracy:
    rms_mm: list[float]
    excess_mm: list[float]
    median_mm: list[float]
    held_share: list[float]
    times: list[float]
    wall_mm: list[float]  # a bin's cells by the wall: their highest above the grain
    phantoms: list[int]  # robots found away from the robot


def render(rig: RobotRig, times: np.ndarray) -> list[list[DepthFrame]]:
    return [
        [
            DepthFrame.rendered(v.serial, f, v.nominal)
            for v, f in zip(rig.views, rig.frames(float(t), i), strict=True)
        ]
        for i, t in enumerate(times)
    ]


def accuracy(
    rig: RobotRig,
    frames: list[list[DepthFrame]],
    times: np.ndarray,
    bare: bool = False,
    settings: LiveConfig | None = None,
) -> Accuracy:
    """The live map's errors at each instant; `bare`: without the bin's wall verdict."""
    site = rig.robot.base.site
    settings = settings or LiveConfig()
    grid = Grid.over(site.region, settings.grid_step_m)
    live = LiveMap(
        grid,
        settings,
        site.ceiling_z,
        shape=None if bare else site.bin,
        noise_factor=rig.robot.base.surface_factor,  # what the site's config says
    )
    xs, ys = grid.centres()
    ring = np.zeros(grid.shape, dtype=bool)
    if site.bin is not None:
        cx, cy = site.bin.centre
        ring = (site.bin.radius_m - np.hypot(xs - cx, ys - cy) < WALL_RING_M) & (grid.inside > 0)
    out = Accuracy([], [], [], [], [], [], [])
    for per_camera, t in zip(frames, times, strict=True):
        update = live.update(per_camera, float(t))
        truth = rig.robot.height(float(t))(xs, ys)
        pose = rig.robot.pose(float(t))
        if ring.any():
            out.wall_mm.append(float(np.max(update.heightmap.heights[ring] - truth[ring])) * 1000)
        away = [r for r in update.robots if np.hypot(r.x - pose.x, r.y - pose.y) > PHANTOM_M]
        out.phantoms.append(len(away))
        under = pose.footprint(xs, ys)
        cells = update.heightmap.observed & ~pose.footprint(xs, ys, AWAY_M)
        error = update.heightmap.heights[cells] - truth[cells]
        out.rms_mm.append(float(np.sqrt(np.mean(error**2))) * 1000)
        excess = update.heightmap.heights[under] - truth[under]
        out.excess_mm.append(float(np.max(excess)) * 1000)
        out.median_mm.append(float(np.median(excess)) * 1000)
        out.held_share.append(float(update.held[under].mean()))
        out.times.append(float(t))
    return out


class RenderedSource:
    """A camera's newest frame: the last rendered instant at or before the session's time."""

    def __init__(self, frames: list[list[DepthFrame]], times: np.ndarray) -> None:
        self.frames_at, self.times = frames, times

    def frames(self, elapsed_s: float, color: bool = False) -> list[DepthFrame]:
        index = int(np.searchsorted(self.times, elapsed_s, side="right")) - 1
        return self.frames_at[max(0, min(index, len(self.times) - 1))]

    def close(self) -> None:
        """Nothing to release."""


def config_for(rig: RobotRig, live: dict[str, object] | None = None) -> Config:
    """The setup as a site's config: the bay's sim cameras by their views; a bin's cameras by
    their extrinsics (the session check places sim views in the bay) and its `[silo.bin]`."""
    site = rig.robot.base.site
    shape = site.bin
    cameras = [
        {
            "serial": v.serial,
            "source": "sim",
            "view": v.key,
            "width": v.intrinsics.width,
            "height": v.intrinsics.height,
        }
        if shape is None
        else {
            "serial": v.serial,
            "extrinsic": v.nominal.tolist(),
            "width": v.intrinsics.width,
            "height": v.intrinsics.height,
        }
        for v in rig.views
    ]
    silo: dict[str, object] = {"id": "bench", "region": site.region.tolist()}
    if site.ceiling_z is not None:
        silo["ceiling_z"] = site.ceiling_z
    if shape is not None:
        assert shape.diameter_m is not None
        silo["bin"] = {
            "diameter_m": shape.diameter_m,
            "centre": list(shape.centre),
            "eave_height_m": shape.eave_z - site.floor_z,
        }
    # the site's cameras are as noisy as the scene's simulated ones
    reconstruction = {"depth_noise_factor": rig.robot.base.surface_factor}
    data = {"silo": silo, "cameras": cameras, "reconstruction": reconstruction}
    return parse_config(data | ({"live": live} if live else {}), "bench")


def ages(config: Config, source: RenderedSource, maps: int) -> list[float]:
    """Capture-to-send age of each map of a real session at RATE_HZ."""
    captured: list[float] = []
    sent: list[float] = []
    done = threading.Event()

    class Timed(RenderedSource):
        def frames(self, elapsed_s: float, color: bool = False) -> list[DepthFrame]:
            captured.append(time.monotonic())
            return super().frames(elapsed_s, color)

    timed = Timed(source.frames_at, source.times)

    def publish(_payload: bytes, _period: float) -> None:
        sent.append(time.monotonic())
        if len(sent) >= maps:
            done.set()

    session = LiveSession(
        config,
        "bench",
        RATE_HZ,
        3600.0,
        publish,
        lambda _reason: done.set(),
        open_frames=lambda _config: timed,
    )
    session.start()
    done.wait(maps / RATE_HZ * 10 + 60)
    session.stop("bench over")
    return [s - c for c, s in zip(captured, sent, strict=False)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=16.0)
    parser.add_argument("--warm-up-s", type=float, default=3.0)
    parser.add_argument("--setups", nargs="+", default=BAY_SETUPS, choices=list(SETUPS))
    parser.add_argument(
        "--bare", action="store_true", help="also each bin without the wall verdict (the old map)"
    )
    parser.add_argument("--decimation", type=int, default=1, help="[live] decimation")
    parser.add_argument("--seed", type=int, default=0, help="the scene's noise draws")
    parser.add_argument("--cpu", type=int, default=0, help="pin to this CPU (-1: do not pin)")
    parser.add_argument("--note", default="", help="a provenance line, e.g. machine load")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.cpu >= 0:
        pinned(args.cpu)
    times = np.arange(0.0, args.seconds, 1.0 / RATE_HZ)
    period = 1.0 / RATE_HZ
    lines = header("Live map with the raking robot", args.note)
    lines += [
        "",
        f"Moving-robot scene (noise seed {args.seed}), {args.seconds:g} s at {RATE_HZ:g} Hz "
        f"({len(times)} maps), 2 cm grid "
        f"over the region (the bay's 6 x 6 m; a bin's wall), default `[live]` but "
        f"`decimation = {args.decimation}`; mixed pixels "
        f"along depth edges (half the edge pixels); in a bin the robot rakes its heap down to "
        f"the level by the wall, eave cameras, the bin's D455 noise (2.5x the ideal target's). "
        f"RMS: observed cells > {AWAY_M} m outside the footprint; footprint: the map's highest "
        f"cell above the grain under the robot (the worst map), and the median cell's (the "
        f"median map; negative: below); 'all' includes the first {args.warm_up_s:g} s. Age: "
        f"the real session at {RATE_HZ:g} Hz, pinned to one core. Wall ring: a bin's cells "
        f"within {WALL_RING_M:g} m of the wall, their highest above the grain (the worst map "
        f"after warm-up); phantoms: robots found more than {PHANTOM_M:g} m from the robot "
        f"(the most in a map after warm-up). 'without the wall verdict': the same frames "
        f"through the map as it was before it knew the bin's wall.",
        "",
        "| setup | session check | maps >= a period old | median age s | RMS mm (median, worst) "
        "| footprint mm, worst after warm-up | footprint mm, worst of all "
        "| footprint mm, median | footprint held | wall ring mm | phantoms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in args.setups:
        scene, views, width, height = SETUPS[name]
        rig = RobotRig(robot_for(scene), views=views, width=width, height=height, seed=args.seed)
        config = config_for(rig, {"decimation": args.decimation})
        problem = session_problem(config, [v.serial for v in rig.views])
        frames = render(rig, times)
        runs = [(name, accuracy(rig, frames, times, settings=config.live))]
        if args.bare and rig.robot.base.bin is not None:
            bare = accuracy(rig, frames, times, True, config.live)
            runs.append((f"{name}, without the wall verdict", bare))
        age = ages(config, RenderedSource(frames, times), len(times))
        old = float(np.mean(np.asarray(age) >= period)) if age else float("nan")
        for label, acc in runs:
            warm = [k for k, t in enumerate(acc.times) if t >= args.warm_up_s]
            rms = [acc.rms_mm[k] for k in warm]
            wall = f"{max(acc.wall_mm[k] for k in warm):.0f}" if acc.wall_mm else "-"
            lines.append(
                f"| {label} | {'accepted' if problem is None else 'refused'} | {old:.0%} "
                f"| {np.median(age):.3f} | {np.median(rms):.1f}, {max(rms):.1f} "
                f"| {max(acc.excess_mm[k] for k in warm):.0f} | {max(acc.excess_mm):.0f} "
                f"| {np.median([acc.median_mm[k] for k in warm]):.0f} "
                f"| {min(acc.held_share):.0%} | {wall} | {max(acc.phantoms[k] for k in warm)} |"
            )
            print(lines[-1], flush=True)
        if problem is not None:
            lines.append(f"|  | refused: {problem} | | | | | | | | | |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
