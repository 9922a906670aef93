"""The membrane fill's solvers against the hole's size and shape (issue 22).

Each case is one fill's inputs (heights, known cells, region); each is filled by the old path
(conjugate gradients warm-started from a 2x coarser fill, recursively: `_warm_cg_fill`) and by
`membrane_fill` as it is now (holes classified before solving: deep holes by pyamg's algebraic
multigrid, the rest by the old path), each in a fresh process: wall and CPU seconds, and the
peak memory of the arrays the solve allocates (tracemalloc, a second run).
Accuracy: the relative residual ||A h - b|| / ||b|| of the 5-point equations (laplace_system),
and the largest difference between the two fills.

Cases: one square hole of side S in a grid with a 20-cell margin (the hole's depth is S / 2),
heights sin + cos about 0 m, and once 2 m higher (the old path's tolerance is relative to the
right side, which the known heights make: a higher surface stops it sooner); a third of the
cells unknown at random (scattered cells); shadow strips 12 cells wide; the fill of bay scans
(benchlib.bay_scan, 1 cm: the batch of bench/silos.py section (b)). Then (`--bay-batch`, needs
CloudCompare) section (b) itself with this tree, one `process` of the batch against
CloudCompare once per scan, and (`--old-tree`) the same batch by the old code and by this
tree's again, alternating.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np

MARGIN = 20
Inputs = tuple[np.ndarray, np.ndarray, np.ndarray]


def _surface(shape: tuple[int, int], offset: float = 0.0) -> np.ndarray:
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    return offset + np.sin(cols / 30.0) + np.cos(rows / 17.0)


def square(side: int, offset: float = 0.0) -> Inputs:
    n = side + 2 * MARGIN
    known = np.ones((n, n), dtype=bool)
    known[MARGIN : MARGIN + side, MARGIN : MARGIN + side] = False
    return _surface((n, n), offset), known, np.ones((n, n), dtype=bool)


def scattered(side: int) -> Inputs:
    known = np.random.default_rng(0).random((side, side)) >= 1 / 3
    return _surface((side, side)), known, np.ones((side, side), dtype=bool)


def strips(side: int) -> Inputs:
    known = np.ones((side, side), dtype=bool)
    stripe = (np.arange(side) // 12) % 3 == 1  # 12 unknown columns in every 36
    known[MARGIN:-MARGIN, stripe] = False
    return _surface((side, side)), known, np.ones((side, side), dtype=bool)


def bay_fills(count: int) -> list[Inputs]:
    """The membrane fill's inputs of `count` bay scans, captured from reconstruct."""
    from benchlib import bay_scan, bay_scene

    import silo_agent.reconstruct as reconstruct_module
    from silo_agent.config import ReconstructionConfig
    from silo_agent.sim.simulate import SimRig

    caught: list[Inputs] = []
    real = reconstruct_module.membrane_fill

    def capture(height: np.ndarray, known: np.ndarray, domain: np.ndarray) -> np.ndarray:
        caught.append((height.copy(), known.copy(), domain.copy()))
        return real(height, known, domain)

    scene = bay_scene()
    rig = SimRig(scene)
    reconstruct_module.membrane_fill = capture
    try:
        for seed in range(count):
            # the membrane's own inputs (the bay's default fill is the repose fill, which
            # calls the membrane from its module, not through reconstruct's name)
            settings = ReconstructionConfig(grid_step_m=0.01, fill="membrane")
            reconstruct_module.reconstruct(bay_scan(scene, seed, rig), settings)
    finally:
        reconstruct_module.membrane_fill = real
    return caught


def _solver(path: str) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    from silo_agent.reconstruct import fill

    return fill._warm_cg_fill if path == "old" else fill.membrane_fill


def run_one(inputs: Path, path: str, output: Path) -> None:
    """In a fresh process: fill `inputs` by `path`, print its time and memory as JSON. Memory:
    the peak of the arrays the solve allocates (tracemalloc, which numpy reports to), from a
    second, traced run (the process's peak resident size is set by the imports already)."""
    import pyamg  # noqa: F401  imported beforehand: its import (0.5 s) is not the solve's
    import scipy.sparse.linalg  # noqa: F401

    data = np.load(inputs)
    height, known, domain = data["height"], data["known"], data["domain"]
    solve = _solver(path)
    wall, cpu = time.perf_counter(), time.process_time()
    filled = solve(height, known, domain)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    tracemalloc.start()
    solve(height, known, domain)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.save(output, filled)
    print(json.dumps({"wall_s": wall, "cpu_s": cpu, "peak_mb": peak / 2**20}))


def _residual(filled: np.ndarray, inputs: Inputs) -> float:
    from silo_agent.reconstruct.fill import laplace_system

    height, known, domain = inputs
    system = laplace_system(height, domain & ~known, domain)
    values = filled.ravel()[system.cells]
    return float(np.linalg.norm(system.matrix() @ values - system.rhs) / np.linalg.norm(system.rhs))


def _depth(inputs: Inputs) -> int:
    from scipy import ndimage

    _, known, domain = inputs
    distance = ndimage.distance_transform_cdt(~(known & domain), metric="chessboard")
    return int(distance[domain & ~known].max())


def measure(name: str, inputs: Inputs, root: Path) -> str:
    height, known, domain = inputs
    source = root / "inputs.npz"
    np.savez(source, height=height, known=known, domain=domain)
    runs, fills = {}, {}
    for path in ("old", "new"):
        output = root / f"{path}.npy"
        done = subprocess.run(
            [sys.executable, __file__, "--one", str(source), path, str(output)],
            capture_output=True,
            text=True,
            check=True,
        )
        runs[path] = json.loads(done.stdout.strip().splitlines()[-1])
        fills[path] = np.load(output)
    unknown = domain & ~known
    difference = float(np.nanmax(np.abs(fills["old"] - fills["new"])[unknown]))
    old, new = runs["old"], runs["new"]
    line = (
        f"| {name} | {int(unknown.sum()):,} | {_depth(inputs)} | {old['wall_s']:.3f} /"
        f" {old['cpu_s']:.3f} | {new['wall_s']:.3f} / {new['cpu_s']:.3f} |"
        f" {old['peak_mb']:.1f} / {new['peak_mb']:.1f} |"
        f" {_residual(fills['old'], inputs):.1e} / {_residual(fills['new'], inputs):.1e} |"
        f" {difference:.1e} |"
    )
    print(line, flush=True)
    return line


def bay_batch(root: Path, old_tree: Path | None) -> list[str]:
    """bench/silos.py section (b) with this tree, then the same batch by `old_tree`'s code and
    by this tree's again, alternating (one `process CACHE` of the 12 scans each)."""
    from benchlib import CLOUDCOMPARE_ENV, PROCESS, bay_cache, measured
    from silos import section_bay

    lines = section_bay(root)
    if old_tree is None:
        return lines
    cache = bay_cache(root)
    command = [*PROCESS, str(cache), "--grid-step", "0.01", "--json"]
    trees = {"old": old_tree.resolve(), "new": Path(__file__).resolve().parent.parent}
    rows = []
    for name, tree in [*trees.items(), *trees.items()]:
        run = measured(command, None, CLOUDCOMPARE_ENV | {"PYTHONPATH": str(tree)})
        commit = subprocess.run(
            ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        count = len(run.stdout.splitlines())
        rows.append(
            f"| {name} (`{commit}`) | {run.wall_s / count:.3f} | {run.cpu_s / count:.3f} |"
            f" {run.peak_mb:.0f} |"
        )
    return [
        *lines,
        "The same cached batch, old code against new, alternating:",
        "",
        "| code | wall s per scan | CPU s per scan | peak MB |",
        "|---|---|---|---|",
        *rows,
        "",
    ]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--one", nargs=3, metavar=("INPUTS", "PATH", "OUTPUT"), help=argparse.SUPPRESS)
    p.add_argument("--sides", default="100,200,400,632", help="square holes' sides, cells")
    p.add_argument("--bay-scans", type=int, default=3)
    p.add_argument("--bay-batch", action="store_true", help="bench/silos.py section (b) too")
    p.add_argument("--old-tree", type=Path, help="a checkout of the old code, for the bay batch")
    p.add_argument("--out", type=Path, default=Path("bench/results/fill.md"))
    args = p.parse_args(argv)
    if args.one:
        run_one(Path(args.one[0]), args.one[1], Path(args.one[2]))
        return
    load_before = os.getloadavg()
    cases: list[tuple[str, Inputs]] = [
        (f"square hole, side {side}", square(side)) for side in map(int, args.sides.split(","))
    ]
    cases += [("square hole, side 400, surface 2 m higher", square(400, offset=2.0))]
    cases += [("scattered third, 700 x 700", scattered(700))]
    cases += [("shadow strips 12 wide, 700 x 700", strips(700))]
    cases += [(f"bay scan {k}, 1 cm", inputs) for k, inputs in enumerate(bay_fills(args.bay_scans))]
    lines = [
        "| case | unknowns | depth (cells) | old wall / CPU s | new wall / CPU s |"
        " old / new peak array MB | old / new residual | max difference |",
        "|---|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    with tempfile.TemporaryDirectory(prefix="silo-fill-") as tmp:
        lines += [measure(name, inputs, Path(tmp)) for name, inputs in cases]
        if args.bay_batch:
            lines += ["", *bay_batch(Path(tmp), args.old_tree)]
    from benchlib import header, write_report

    head = header("Membrane fill: solver against hole size and shape")
    write_report(args.out, head, load_before, lines, "times are under that load")


if __name__ == "__main__":
    main()
