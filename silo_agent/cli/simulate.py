"""`silo-agent simulate`: a simulated scene into a silo-scan/1 directory (and recordings)."""

from __future__ import annotations

import argparse

from silo_agent.base.exits import FAILURE, OK, USAGE
from silo_agent.cli.common import fail, output_directory_problem
from silo_agent.scan import ScanError, write_scan
from silo_agent.sim import make_scene
from silo_agent.sim import simulate as render
from silo_agent.sim.simulate import SimRig, plan_views


def simulate(args: argparse.Namespace) -> int:
    for directory in (args.out.parent, args.record):  # before anything is rendered
        if directory is not None and (problem := output_directory_problem(directory)):
            return fail(problem, FAILURE)
    scene = make_scene(args.scene, args.grain)
    rig = SimRig(scene)
    try:
        scan = render(
            scene,
            args.views,
            args.seed,
            args.calib_error,
            args.grid_step,
            layout=args.layout,
            color=args.color,
            rig=rig,
            resolution=args.resolution,
        )
    except ValueError as exc:  # a layout that does not fit the scene
        return fail(str(exc), USAGE)
    blind = [c.serial for c in scan.cameras if len(c.points) == 0]
    if blind:  # a scan with an empty cloud is no silo-scan/1 directory (scan.py reads none)
        return fail(
            f"camera(s) {', '.join(blind)} see nothing of the scene (--calib-error "
            f"{args.calib_error[0]:g},{args.calib_error[1]:g} moves the cameras that far)",
            USAGE,
        )
    try:
        write_scan(scan, args.out)
    except ScanError as exc:
        return fail(str(exc), FAILURE)
    except OSError as exc:
        return fail(f"{args.out}: cannot write the scan: {exc.strerror or exc}", FAILURE)
    points = sum(len(c.points) for c in scan.cameras)
    print(
        f"{args.out}: {scene.name} ({scene.grain.name}), {len(scan.cameras)} camera(s), "
        f"{points} points, truth {scene.volume_m3:.4f} m³"
    )
    if args.record is not None:
        from silo_agent.capture.sim_recording import record_views  # pyrealsense2: only here

        views = plan_views(
            scene, args.views, args.seed, args.calib_error, args.layout, args.resolution
        )
        for path in record_views(
            rig, views, args.seed, args.record, args.record_frames, args.color
        ):
            print(f"{path}: {args.record_frames} depth frames")
    return OK
