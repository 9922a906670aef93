"""`silo-agent calibrate`: level and register the cameras (service/calibration.py)."""

from __future__ import annotations

import argparse
import json

from silo_agent.base.exits import DATA_ERROR, FAILURE, OK, USAGE
from silo_agent.calibrate import (
    CalibrationError,
    ScanMismatch,
    SerialMismatch,
    write_calibrated_config,
)
from silo_agent.cli.common import fail, load_config
from silo_agent.scan import ScanError
from silo_agent.service.calibration import (
    CaptureFailed,
    calibrate_scans,
    capture_scans,
    read_scans,
)


def calibrate(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.captures is not None and args.scan:
        return fail("--captures goes with --capture (give --scan once per scan instead)", USAGE)
    captures = 1 if args.captures is None else args.captures
    if captures < 1:
        return fail(f"--captures {captures}: must be at least 1", USAGE)
    try:
        if args.scan:
            scans, names = read_scans(args.scan)
            source = ", ".join(str(d) for d in args.scan)
        else:
            scans, names = capture_scans(config, captures)
            source = "capture"
    except ScanError as exc:
        return fail(str(exc), DATA_ERROR)
    except CaptureFailed as exc:
        return fail(str(exc), FAILURE)
    try:
        result = calibrate_scans(config, scans, names, args.floor)
    except ScanMismatch as exc:
        return fail(str(exc), DATA_ERROR)
    except CalibrationError as exc:
        return fail(f"{source}: {exc}", DATA_ERROR if isinstance(exc, SerialMismatch) else FAILURE)
    backup = None
    if args.write:
        try:
            backup = write_calibrated_config(args.config, result.extrinsics())
        except CalibrationError as exc:
            return fail(str(exc), FAILURE)
    if args.json:
        out = result.to_json()
        out["config_written"] = bool(args.write)
        out["backup"] = None if backup is None else str(backup)
        print(json.dumps(out, allow_nan=False))
    else:
        print(result.describe())
        if backup is not None:
            print(f"{args.config}: extrinsics updated (previous file kept as {backup})")
        else:
            print("config not changed (use --write to update it)")
    return OK
