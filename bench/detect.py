"""Pile detection time per scan (issue 8, "Benchmark"), for both detectors.

The simulated `piles` scene from the paper's four views A1 A3 A5 A7 (848 x 480, colour on), one
reconstruction, then median wall times of:

- geometric: height map -> piles as `analyse` finds them (`Surface.for_piles`, whose map is
  no finer than 2 cm, then `detect_piles`), at 2 cm and 1 cm grids;
- onnx: everything silo-agent does around the model for the four cameras (colour image from the
  cloud, letterbox, decode, class-aware NMS, box -> silo point, radius clustering of the fused
  cloud, per-pile measures). No model ships with silo-agent, so the network is a stand-in built
  here with the output of a 640 px YOLO export ([1, 4 + 2, 8400], 12 boxes above the
  threshold): its inference costs nothing, and a real YOLO11n adds its own CPU time per camera.

Writes Markdown with its provenance to stdout (bench/results/detect.md holds a run).
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from silo_agent.config import DetectionConfig, ReconstructionConfig
from silo_agent.detect import fused_points, onnx_piles
from silo_agent.detect.geometric import Surface, detect_piles, detection_map
from silo_agent.detect.onnx_yolo import YoloModel, locate
from silo_agent.reconstruct import reconstruct
from silo_agent.sim import make_scene, simulate

REPO = Path(__file__).resolve().parents[1]
VIEWS = ["A1", "A3", "A5", "A7"]
CANDIDATES = 8400  # a 640 px YOLO export's anchor count
ABOVE = 12  # candidates above the confidence threshold (duplicates around 4 piles)


def median_ms(fn: Callable[[], object], runs: int) -> float:
    """Median wall time in ms of `runs` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1000


def stand_in_model(path: Path, seed: int = 0) -> Path:
    """An ONNX graph with a YOLO export's input, output and metadata; output = constants."""
    rng = np.random.default_rng(seed)
    out = np.zeros((1, 6, CANDIDATES), dtype=np.float32)
    out[0, 0] = rng.uniform(0, 640, CANDIDATES)
    out[0, 1] = rng.uniform(80, 560, CANDIDATES)
    out[0, 2:4] = rng.uniform(10, 200, (2, CANDIDATES))
    out[0, 4:6] = rng.uniform(0, 0.3, (2, CANDIDATES))
    out[0, 4, :ABOVE] = rng.uniform(0.6, 0.95, ABOVE)
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["mean"], keepdims=0),
        helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
        helper.make_node("Add", ["table", "nothing"], ["output0"]),
    ]
    inits = [
        helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0]),
        helper.make_tensor("table", TensorProto.FLOAT, list(out.shape), out.ravel().tolist()),
    ]
    graph = helper.make_graph(
        nodes,
        "stand-in",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 640, 640])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(out.shape))],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"names": "{0: 'pile', 1: 'robot'}", "imgsz": "[640, 640]"})
    onnx.save(model, path)
    return path


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [
            ln.split(":", 1)[1].strip()
            for ln in cpuinfo.read_text().splitlines()
            if ln.startswith("model name")
        ]
        cpu = names[0] if names else cpu
    return f"{cpu}, {os.cpu_count()} logical CPUs, {platform.system()} {platform.release()}"


def commit() -> str:
    done = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
        capture_output=True,
        text=True,
        check=False,
    )
    return done.stdout.strip() or "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20, help="timed runs per figure")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    scene = make_scene("piles")
    scan = simulate(scene, VIEWS, seed=args.seed, color=True)
    detection = DetectionConfig()
    rows: list[tuple[str, float, int | None]] = []
    for step in (0.02, 0.01):
        result = reconstruct(scan, ReconstructionConfig(grid_step_m=step))
        if result.heightmap is None:
            raise RuntimeError(f"no height map at a {step} m step: {result.invalid_reason}")
        hm = result.heightmap

        def geometric(hm=hm) -> list:
            surface = Surface.for_piles(hm, scan.site.base, scan.site.floor_z, None)
            return detect_piles(surface, detection)

        piles = geometric()
        rows.append(
            (
                f"geometric, {step * 100:g} cm grid ({hm.shape[0]} x {hm.shape[1]} cells,"
                f" searched on {detection_map(hm).step * 100:g} cm)",
                median_ms(geometric, args.runs),
                len(piles),
            )
        )

    with tempfile.TemporaryDirectory() as tmp:
        model = YoloModel(stand_in_model(Path(tmp) / "stand-in.onnx"))
        surface = Surface.for_piles(hm, scan.site.base, scan.site.floor_z, None)
        cloud = fused_points(scan.cameras)

        def onnx_path() -> list:
            found = locate(model, scan.cameras, 0.5, 0.45)
            return onnx_piles(found, ["pile"], cloud, surface, 0.98)

        piles = onnx_path()
        points = sum(len(c.points) for c in scan.cameras)
        rows.append(
            (
                f"onnx around the model, 4 cameras, {points} points, 1 cm grid",
                median_ms(onnx_path, max(3, args.runs // 4)),
                len(piles),
            )
        )
        single = scan.cameras[0]
        one = median_ms(lambda: locate(model, [single], 0.5, 0.45), args.runs)
        rows.append(
            ("onnx, one camera: image, letterbox, run, decode, NMS, box -> point", one, None)
        )

    command = "PYTHONPATH=. python " + shlex.join(["bench/detect.py", *sys.argv[1:]])
    lines = [
        "# Pile detection time per scan",
        "",
        f"- command: `{command}`",
        f"- date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- commit: `{commit()}`",
        f"- machine: {machine()}",
        f"- scan: simulated `piles` scene, views {' '.join(VIEWS)}, seed {args.seed}, colour on",
        "- the ONNX network is a constant stand-in (no model ships): add the model's own "
        "inference time per camera",
        "",
        "| detector | median ms per scan | piles |",
        "|---|---:|---:|",
    ]
    for name, ms, count in rows:
        lines.append(f"| {name} | {ms:.1f} | {'' if count is None else count} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
