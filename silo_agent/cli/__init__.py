"""`silo-agent` command line: the parser and the dispatch. Each command is a function in a
module of this package, one module per command group (`process.py`, `scan.py`, `daemon.py`,
`cache.py`, `report.py`, `realsense.py`, `calibrate.py`, `simulate.py`, `telemetry.py`), a
thin call into the service layer; the parser names it as `module:function` and only the
chosen command's module is imported, so `process` pays only for what it uses and `--help`
loads no numpy or pydantic.

Exit status (silo_agent/base/exits.py): 0 success, 1 a failed operation, 2 usage, 65 bad input
data (EX_DATAERR), 78 bad configuration (EX_CONFIG); a bad file never ends in a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn

from silo_agent.base.choices import (
    DEFAULT_GRAIN,
    DEFAULT_GRID_STEP_M,
    DEFAULT_METHOD,
    GRAINS,
    LAYOUTS,
    METHODS,
    SCENE_NAMES,
)
from silo_agent.base.exits import CONFIG_ERROR, DATA_ERROR, INTERRUPTED, OUTPUT_CLOSED
from silo_agent.cli.common import (
    calib_error,
    configure_logging,
    fail,
    grid_step,
    non_negative,
    positive,
    resolution,
    seconds,
    views,
    wait_seconds,
)

Handler = Callable[[argparse.Namespace], int]
PROCESS = "process:process"  # the handler of `process`, which exits without tearing down


class _VersionAction(argparse.Action):
    """--version, reading the installed version only when asked (importlib.metadata is slow)."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, help="show the version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *_args: object) -> None:
        from silo_agent import __version__

        print(f"silo-agent {__version__}")
        parser.exit()


def handler_of(name: str) -> Handler:
    """`module:function` of this package, imported now."""
    module, function = name.split(":")
    handler: Handler = getattr(importlib.import_module(f"silo_agent.cli.{module}"), function)
    return handler


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="silo-agent", description="Grain silo inventory from RealSense depth cameras."
    )
    parser.add_argument("--version", action=_VersionAction)
    parser.add_argument(
        "--log-level", default="info", choices=["debug", "info", "warning", "error"]
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="the service: scan on schedule and on request, publish")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument("--scans", type=positive, metavar="N", help="stop after N scans")
    p.add_argument("--json", action="store_true", help="with --scans: the last result as JSON")
    p.set_defaults(handler="daemon:run")

    p = sub.add_parser("replay", help="re-process a cached scan, compare with the published")
    p.add_argument("scan", metavar="SCAN_ID|DIR")
    p.add_argument("--config", type=Path, metavar="FILE", help="to find SCAN_ID in its cache")
    p.set_defaults(handler="cache:replay")

    p = sub.add_parser("report", help="one self-contained HTML or PNG report of a scan")
    p.add_argument("scan", metavar="SCAN_DIR|SCAN_ID")
    p.add_argument("--config", type=Path, metavar="FILE", help="to find SCAN_ID in its cache")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.html|FILE.png")
    p.set_defaults(handler="report:report")

    p = sub.add_parser("scans", help="the audit cache: list, show or export scans")
    p.add_argument("action", choices=["list", "show", "export"])
    p.add_argument("scan_id", nargs="?", metavar="SCAN_ID")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument("--out", type=Path, metavar="FILE.tar.gz", help="export: where to write")
    p.set_defaults(handler="cache:scans")

    p = sub.add_parser("check-config", help="validate a configuration file and exit")
    p.add_argument("file", type=Path)
    p.set_defaults(handler="daemon:check_config")

    p = sub.add_parser("process", help="reconstruct silo-scan/1 directories offline")
    p.add_argument(
        "scan_dirs",
        type=Path,
        nargs="+",
        metavar="DIR",
        help="a scan directory, or a directory of them (an audit cache)",
    )
    p.add_argument("--config", type=Path, help="config file whose settings override the scan's")
    p.add_argument("--grid-step", type=grid_step, metavar="METRES")
    p.add_argument(
        "--method",
        choices=METHODS,
        help=f"reconstruction method (baselines for comparison); default {DEFAULT_METHOD}",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="one JSON object per scan, one per line, with its scan_dir",
    )
    p.add_argument(
        "--jobs",
        type=positive,
        default=1,
        metavar="N",
        help="process N scans at a time in worker processes (default 1)",
    )
    p.set_defaults(handler=PROCESS)

    p = sub.add_parser("devices", help="list connected RealSense cameras")
    p.set_defaults(handler="realsense:devices")

    p = sub.add_parser("scan", help="capture all cameras once, write the scan, process it")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument(
        "--out", type=Path, metavar="DIR", help="where to write the scan; default: audit.directory"
    )
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(handler="scan:scan")

    p = sub.add_parser("record", help="record each live camera to DIR/<serial>.db3")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument("--out", type=Path, required=True, metavar="DIR")
    p.add_argument("--seconds", type=seconds, default=5.0, metavar="S", help="default 5")
    p.set_defaults(handler="realsense:record")

    p = sub.add_parser("calibrate", help="level and register the cameras from calibration scans")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--scan",
        type=Path,
        metavar="DIR",
        action="append",
        help="a silo-scan/1 calibration scan; repeat it to pool several scans "
        "taken one after another (their noise averages)",
    )
    source.add_argument("--capture", action="store_true", help="capture with every camera")
    p.add_argument(
        "--captures",
        type=int,
        metavar="N",
        help="with --capture: take N captures in a row and pool them (default 1)",
    )
    p.add_argument(
        "--floor",
        action="store_true",
        help="the floor z = floor_z is visible around the grain: level on it",
    )
    p.add_argument(
        "--write",
        action="store_true",
        help="update the config's extrinsics in place (comments kept, backup made)",
    )
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(handler="calibrate:calibrate")

    p = sub.add_parser("simulate", help="render a simulated scene into a silo-scan/1 directory")
    p.add_argument(
        "--scene",
        required=True,
        choices=SCENE_NAMES,
    )
    p.add_argument(
        "--views",
        required=True,
        type=views,
        metavar="A1,A5",
        help="camera positions A1-A8 (midpoints A1 A3 A5 A7, corners A2 A4 A6 A8)",
    )
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="new scan directory")
    p.add_argument("--seed", type=non_negative, default=0)
    p.add_argument(
        "--calib-error",
        type=calib_error,
        default=(0.0, 0.0),
        metavar="DEG,M",
        help="true poses off the written extrinsics by DEG degrees and M metres",
    )
    p.add_argument(
        "--grid-step",
        type=grid_step,
        metavar="M",
        default=DEFAULT_GRID_STEP_M,
        help="grid step written into the scan's reconstruction settings",
    )
    p.add_argument("--grain", default=DEFAULT_GRAIN, choices=GRAINS)
    p.add_argument(
        "--layout",
        choices=LAYOUTS,
        help="paper: 5 m square, 1 m high; wall: high on the walls; eave: under a round "
        "bin's eave (default per scene)",
    )
    p.add_argument(
        "--resolution",
        type=resolution,
        default=(848, 480),
        metavar="WxH",
        help="depth image size: 848x480 (default) or the D455's full 1280x720",
    )
    p.add_argument("--color", action="store_true", help="colour the points (normal shading)")
    p.add_argument(
        "--record",
        type=Path,
        metavar="DIR",
        help="also write one rosbag2 <serial>.db3 recording per camera into DIR",
    )
    p.add_argument(
        "--record-frames",
        type=positive,
        default=40,
        metavar="N",
        help="depth frames per recording (default 40: 30 warm-up + 10 aggregated)",
    )
    p.set_defaults(handler="simulate:simulate")

    p = sub.add_parser("publish", help="MQTT by hand: queue and send one result (and an alarm)")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument("--result", type=Path, required=True, help="result summary JSON (result.json)")
    p.add_argument(
        "--heightmap", type=Path, help=".npz with origin, step, heights, observed, inside"
    )
    p.add_argument("--alarm", type=Path, help="alarm event JSON")
    p.add_argument(
        "--repeat", type=positive, default=1, help="publish N results, scan ids suffixed -k"
    )
    p.add_argument("--timeout", type=wait_seconds, default=30.0, metavar="S")
    p.set_defaults(handler="telemetry:publish")

    p = sub.add_parser("flush", help="send what the MQTT outbox holds, then exit")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument("--timeout", type=wait_seconds, default=30.0, metavar="S")
    p.add_argument(
        "--linger",
        type=wait_seconds,
        default=0.0,
        metavar="S",
        help="stay connected after flushing",
    )
    p.set_defaults(handler="telemetry:flush")

    p = sub.add_parser("schemas", help="write or check the payload JSON Schemas (config/schemas)")
    p.add_argument("--check", action="store_true", help="exit 1 if any is out of date")
    p.add_argument("dir", type=Path, nargs="?", help="default: the repository's config/schemas")
    p.set_defaults(handler="telemetry:schemas")

    return parser


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line, as argparse reads it, but for `process`: scan directories may follow
    its options too (`process a --json b`; argparse takes positionals given as one run only)."""
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if rest and args.handler == PROCESS and not any(r.startswith("-") for r in rest):
        args.scan_dirs += [Path(r) for r in rest]
    elif rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    return _dispatch(parse(argv))


def entry() -> NoReturn:
    """`silo-agent` and `python -m silo_agent`: `main`, then exit with its status.

    After `process` the interpreter is not torn down: its output is flushed and the process
    ends at once, which saves a one-off `process` about 0.03 s of freeing modules and objects
    that the system reclaims anyway (`process` writes no file and holds no lock)."""
    args = parse()
    status = _dispatch(args)
    if args.handler == PROCESS:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:  # a closed pipe loses the output either way; the status still says what ran
            os._exit(status)
    raise SystemExit(status)


def _dispatch(args: argparse.Namespace) -> int:
    # pydantic scans every installed package for plugins at its first model (~0.02 s, paid by
    # every one-off `process`); the agent uses none. An explicit setting, even empty, wins.
    os.environ.setdefault("PYDANTIC_DISABLE_PLUGINS", "__all__")
    # OpenBLAS starts a thread per core whose workers spin between calls; the engine's BLAS
    # calls are small (3x3 and 4x4 fits, N x 3 by 3 x 3 products), so the spinning is all they
    # add: a 12 m silo's `process` at 1 cm, unpinned on 2 cores, 5.5-5.7 s of user CPU against
    # 4.0-4.4 s with one thread, and no faster. Set before numpy is imported.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from silo_agent.base.heap import keep_freed_memory, small_pages

    small_pages()  # numpy is not imported yet (the parser needs none of it)
    keep_freed_memory()
    if args.handler != PROCESS:  # process sets logging up itself, only when it will log
        configure_logging(args)
    try:
        return handler_of(args.handler)(args)
    except KeyboardInterrupt:
        return INTERRUPTED
    except BrokenPipeError:  # `| head` took what it wanted: no traceback, nor one at exit
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return OUTPUT_CLOSED
    except Exception as exc:  # bad input met where no command expected it: still one line
        from silo_agent.base.limits import LimitExceeded
        from silo_agent.config import ConfigError  # loaded already if one was raised
        from silo_agent.scan import ScanError

        if isinstance(exc, ConfigError):
            return fail(str(exc), CONFIG_ERROR)
        if isinstance(exc, ScanError | LimitExceeded):
            return fail(str(exc), DATA_ERROR)
        raise


if __name__ == "__main__":
    entry()
