"""`silo-agent devices` and `record`: the RealSense cameras themselves (pyrealsense2 loads
with this module, only for these commands)."""

from __future__ import annotations

import argparse
import sys

from silo_agent.base.exits import FAILURE, OK
from silo_agent.capture import CaptureError
from silo_agent.capture.realsense import list_devices, record_camera
from silo_agent.cli.common import fail, load_config, output_directory_problem


def devices(_args: argparse.Namespace) -> int:
    found = list_devices()
    if not found:
        print("no RealSense devices found")
        return FAILURE
    for device in found:
        print(
            f"{device.serial}  {device.name}  firmware {device.firmware or '?'}  "
            f"USB {device.usb_type or '?'}  IMU {'yes' if device.has_imu else 'no'}"
        )
        if device.usb2:
            print(
                f"silo-agent: warning: {device.serial} is on USB {device.usb_type}: depth will "
                "drop frames or fail; connect it to a USB 3 port or a powered USB 3 hub",
                file=sys.stderr,
            )
    return OK


def record(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    live = [camera for camera in config.cameras if camera.source == "realsense"]
    if not live:
        return fail(f'{args.config}: no live cameras (source = "realsense") to record', FAILURE)
    if problem := output_directory_problem(args.out):
        return fail(problem, FAILURE)
    args.out.mkdir(parents=True, exist_ok=True)
    failed = 0
    for camera in live:  # one after another: several D455s streaming at once saturate USB
        path = args.out / f"{camera.serial}.db3"
        try:
            frames = record_camera(camera, path, args.seconds)
        except CaptureError as exc:
            print(f"silo-agent: {exc}", file=sys.stderr)
            failed += 1
            continue
        print(f"{camera.serial}: {frames} frames -> {path}")
    return FAILURE if failed else OK
