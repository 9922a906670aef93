"""`silo-agent calibrate`: level and register the cameras (service/calibration.py)."""

from __future__ import annotations

import argparse
import json

from silo_agent.base.exits import DATA_ERROR, FAILURE, OK, USAGE
from silo_agent.base.limits import MAX_CALIBRATION_CAPTURES
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
    if not 1 <= captures <= MAX_CALIBRATION_CAPTURES:  # each is a scan kept in the audit cache
        return fail(f"--captures {captures}: must be 1 to {MAX_CALIBRATION_CAPTURES}", USAGE)
    try:
        if args.scan:
            scans, names = read_scans(args.scan)
            source = ", ".join(str(d) for d in args.scan)
            for scan, name in zip(scans, names, strict=True):  # another silo's: nonsense poses
                if scan.silo_id != config.silo.id:
                    return fail(
                        f"{name}: silo_id {scan.silo_id!r} is not the config's silo.id "
                        f"{config.silo.id!r}; calibrate with scans of the silo it describes",
                        DATA_ERROR,
                    )
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
    backup = write_error = None
    if args.write:  # refused or failed: the result is still printed, the config unchanged
        try:
            backup = write_calibrated_config(args.config, result.extrinsics())
        except CalibrationError as exc:
            write_error = str(exc)
        except OSError as exc:
            write_error = f"{args.config}: cannot write it: {exc.strerror or exc}; not changed"
    if args.json:
        out = result.to_json()
        out["config_written"] = backup is not None
        out["backup"] = None if backup is None else str(backup)
        print(json.dumps(out, allow_nan=False))
    else:
        print(result.describe())
        if backup is not None:
            print(f"{args.config}: extrinsics updated (previous file kept as {backup})")
        elif write_error is None:
            print("config not changed (use --write to update it)")
    return fail(write_error, FAILURE) if write_error is not None else OK
