"""`silo-agent` command line. Each subcommand lives in a small function; heavy imports stay inside
them so that `process` pays only for what it uses.

Exit status (silo_agent/base/exits.py): 0 success, 1 a failed operation, 2 usage, 65 bad input
data (EX_DATAERR), 78 bad configuration (EX_CONFIG); a bad file never ends in a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from silo_agent.base.choices import (
    DEFAULT_GRAIN,
    DEFAULT_GRID_STEP_M,
    DEFAULT_METHOD,
    GRAINS,
    LAYOUTS,
    METHODS,
    SCENE_NAMES,
)
from silo_agent.base.exits import CONFIG_ERROR as EX_CONFIG
from silo_agent.base.exits import DATA_ERROR as EX_DATAERR
from silo_agent.base.exits import FAILURE, INTERRUPTED, OK, USAGE

if TYPE_CHECKING:
    from silo_agent.analysis.summary import ScanSummary
    from silo_agent.capture import CameraFailure
    from silo_agent.config import Config
    from silo_agent.scan import CameraCloud, Scan

Handler = Callable[[argparse.Namespace], int]


def _fail(message: str, status: int) -> int:
    print(f"silo-agent: {message}", file=sys.stderr)
    return status


def load_config(path: Path, service: bool = False) -> Config:
    """The validated config file; pydantic and the config models load here, on first use,
    not at start-up (about 0.1 s that `process` without --config and `--help` never pay)."""
    from silo_agent.config import load_config as load

    return load(path, service=service)


def _configure_logging(args: argparse.Namespace) -> None:
    """structlog set up for the command's --log-level (structlog loads here, not at start)."""
    from silo_agent.base.log import configure_logging

    configure_logging(args.log_level)


class _VersionAction(argparse.Action):
    """--version, reading the installed version only when asked (importlib.metadata is slow)."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, help="show the version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *_args: object) -> None:
        from silo_agent import __version__

        print(f"silo-agent {__version__}")
        parser.exit()


# ---------------------------------------------------------------- check-config


def cmd_check_config(args: argparse.Namespace) -> int:
    from silo_agent.config import config_warnings

    config = load_config(args.file, service=True)
    for warning in config_warnings(config):
        print(f"silo-agent: warning: {args.file}: {warning}", file=sys.stderr)
    print(f"{args.file}: ok (silo {config.silo.id}, {len(config.cameras)} camera(s))")
    return OK


# ---------------------------------------------------------------- process


def cmd_process(args: argparse.Namespace) -> int:
    from silo_agent.service import batch

    config = load_config(args.config) if args.config else None
    if config is not None and config.detection.onnx is not None:
        _configure_logging(args)  # the ONNX detector logs; nothing else on this path does
    options = batch.Options(config, args.grid_step, args.method, args.json)
    return batch.run(args.scan_dirs, options, args.jobs)


# ---------------------------------------------------------------- cameras


def cmd_devices(args: argparse.Namespace) -> int:
    from silo_agent.capture.realsense import list_devices

    devices = list_devices()
    if not devices:
        print("no RealSense devices found")
        return FAILURE
    for device in devices:
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


def _new_scan(
    config: Config, clouds: list[CameraCloud], failures: list[CameraFailure], started: datetime
) -> Scan:
    """A silo-scan/1 `Scan` of one capture; the scan id is the silo and the capture's UTC time."""
    from silo_agent.service.scan_path import new_scan, new_scan_id

    return new_scan(config, new_scan_id(config, started, set()), started, clouds, failures)


def cmd_scan(args: argparse.Namespace) -> int:
    """One capture through the daemon's scan path: the scan (with its config snapshot) into
    the cache, then processed, summarised and kept exactly as the daemon does."""
    import time

    from silo_agent.capture import capture_all
    from silo_agent.detect import ModelError
    from silo_agent.scan import ScanError
    from silo_agent.service.scan_path import (
        CONFIG_KEY,
        analyse_with,
        keep_result,
        new_scan,
        new_scan_id,
        previous_piles,
        settings_of,
        summary_of,
    )
    from silo_agent.storage.audit import AuditCache

    config = load_config(args.config)
    audit = config.audit.model_copy(update={"directory": args.out}) if args.out else config.audit
    cache = AuditCache(audit, config.silo.id)
    started = datetime.now(UTC)
    clock = time.perf_counter()
    capture = capture_all(config)
    timings = {"capture_s": time.perf_counter() - clock}
    for failure in capture.failures:
        print(f"silo-agent: warning: {failure.error}", file=sys.stderr)
    if not capture.clouds:
        return _fail("no camera delivered a cloud; no scan written", FAILURE)
    scan = new_scan(
        config,
        new_scan_id(config, started, cache.names()),
        started,
        capture.clouds,
        capture.failures,
    )
    try:  # audit first: the raw scan is kept even if processing fails
        directory = cache.write_scan(scan, scan.extra[CONFIG_KEY])
    except (ScanError, OSError) as exc:
        return _fail(f"cannot write the scan: {exc}", FAILURE)
    previous = previous_piles(cache, scan.scan_id)
    clock = time.perf_counter()
    try:
        result = analyse_with(scan, settings_of(scan), previous)
    except ModelError as exc:
        return _fail(f"{exc}; the raw scan is kept in {directory}", EX_CONFIG)
    timings["reconstruct_s"] = time.perf_counter() - clock
    summary = summary_of(result, scan, timings)
    try:
        keep_result(directory, summary, result, previous)
    except OSError as exc:
        return _fail(f"cannot keep the result with the scan in {directory}: {exc}", FAILURE)
    if args.json:
        print(json.dumps({**summary.to_json(), "scan_dir": str(directory)}, allow_nan=False))
    else:
        print(result.describe())
        print(f"scan written to {directory}" + (" (degraded)" if capture.degraded else ""))
    return OK


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"want a duration in seconds > 0, got {text!r}")
    return value


def cmd_record(args: argparse.Namespace) -> int:
    from silo_agent.capture import CaptureError
    from silo_agent.capture.realsense import record_camera

    config = load_config(args.config)
    live = [camera for camera in config.cameras if camera.source == "realsense"]
    if not live:
        return _fail(f'{args.config}: no live cameras (source = "realsense") to record', FAILURE)
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


# ---------------------------------------------------------------- calibrate


def cmd_calibrate(args: argparse.Namespace) -> int:
    from silo_agent.calibrate import (
        CalibrationError,
        ScanMismatch,
        SerialMismatch,
        calibrate,
        pool_scans,
        start_poses,
        write_calibrated_config,
    )
    from silo_agent.reconstruct import site_from_config
    from silo_agent.scan import MANIFEST, ScanError, read_scan, write_scan

    config = load_config(args.config)
    if args.captures is not None and args.scan:
        return _fail("--captures goes with --capture (give --scan once per scan instead)", USAGE)
    captures = 1 if args.captures is None else args.captures
    if captures < 1:
        return _fail(f"--captures {captures}: must be at least 1", USAGE)
    if args.scan:
        scans, names = [], []
        for directory in args.scan:
            try:
                scans.append(read_scan(directory))
            except ScanError as exc:
                return _fail(str(exc), EX_DATAERR)
            names.append(str(Path(directory) / MANIFEST))
        source = ", ".join(str(d) for d in args.scan)
    else:
        from silo_agent.capture import capture_all

        scans, names = [], []
        for number in range(captures):  # one after another; the rig does not move
            started = datetime.now(UTC)
            capture = capture_all(config, number)
            for failure in capture.failures:
                print(f"silo-agent: warning: {failure.error}", file=sys.stderr)
            if capture.failures or not capture.clouds:
                return _fail(
                    "calibration needs every camera; "
                    f"{len(capture.failures)} failed, no calibration done",
                    FAILURE,
                )
            scan = _new_scan(config, capture.clouds, capture.failures, started)
            suffix = "" if captures == 1 else f"-{number + 1}of{captures}"
            try:  # keep the calibration scan for audit, like any scan
                directory = write_scan(
                    scan, config.audit.directory / f"{scan.scan_id}-calibration{suffix}"
                )
                print(f"calibration scan written to {directory}", file=sys.stderr)
            except (ScanError, OSError) as exc:
                print(f"silo-agent: warning: calibration scan not kept: {exc}", file=sys.stderr)
            scans.append(scan)
            names.append(f"capture {number + 1} of {captures}")
        source = "capture"
    try:
        scan = pool_scans(scans, names)
    except ScanMismatch as exc:
        return _fail(str(exc), EX_DATAERR)
    try:
        start = start_poses(config, scan)
        result = calibrate(
            scan,
            config.calibration,
            floor=args.floor,
            site=site_from_config(config),
            start=start,
            grid_step=config.reconstruction.grid_step_m,
        )
    except CalibrationError as exc:
        return _fail(f"{source}: {exc}", EX_DATAERR if isinstance(exc, SerialMismatch) else FAILURE)
    backup = None
    if args.write:
        try:
            backup = write_calibrated_config(args.config, result.extrinsics())
        except CalibrationError as exc:
            return _fail(str(exc), FAILURE)
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


# ---------------------------------------------------------------- simulate


def _views(text: str) -> list[str]:
    from silo_agent.sim.layouts import VIEWS

    views = [v.strip().upper() for v in text.split(",") if v.strip()]
    unknown = [v for v in views if v not in VIEWS]
    if not views or unknown or len(set(views)) != len(views):
        raise argparse.ArgumentTypeError(f"want distinct views among {', '.join(VIEWS)}")
    return views


def _calib_error(text: str) -> tuple[float, float]:
    try:
        degrees, metres = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("want DEG,M, e.g. 0.5,0.01") from None
    if degrees < 0 or metres < 0:
        raise argparse.ArgumentTypeError("DEG and M must be >= 0")
    return degrees, metres


def _resolution(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError("want WIDTHxHEIGHT, e.g. 1280x720") from None
    if not (16 <= width <= 1280 and 16 <= height <= 800):
        raise argparse.ArgumentTypeError("want 16-1280 x 16-800 pixels")
    return width, height


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"want a whole number >= 1, got {text!r}")
    return value


def cmd_simulate(args: argparse.Namespace) -> int:
    from silo_agent.scan import ScanError, write_scan
    from silo_agent.sim import make_scene, simulate
    from silo_agent.sim.simulate import SimRig, plan_views

    scene = make_scene(args.scene, args.grain)
    rig = SimRig(scene)
    try:
        scan = simulate(
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
        return _fail(str(exc), USAGE)
    try:
        write_scan(scan, args.out)
    except ScanError as exc:
        return _fail(str(exc), FAILURE)
    points = sum(len(c.points) for c in scan.cameras)
    print(
        f"{args.out}: {scene.name} ({scene.grain.name}), {len(scan.cameras)} camera(s), "
        f"{points} points, truth {scene.volume_m3:.4f} m³"
    )
    if args.record is not None:
        from silo_agent.capture.sim_recording import record_views

        views = plan_views(
            scene, args.views, args.seed, args.calib_error, args.layout, args.resolution
        )
        for path in record_views(
            rig, views, args.seed, args.record, args.record_frames, args.color
        ):
            print(f"{path}: {args.record_frames} depth frames")
    return OK


# ---------------------------------------------------------------- daemon and audit cache


def cmd_run(args: argparse.Namespace) -> int:
    from silo_agent.service.daemon import Agent
    from silo_agent.service.state_lock import StateLocked

    config = load_config(args.config, service=True)  # bad: ConfigError -> 78, nothing started
    companions = []
    if config.web.enabled:  # the port bound now: one in use is a 78 before anything starts
        from silo_agent.web.server import WebServer

        companions.append(WebServer.bind(config.web))
    try:
        agent = Agent(args.config, config, max_scans=args.scans, companions=companions)
    except StateLocked as exc:
        return _fail(str(exc), FAILURE)
    status = agent.run()
    last = agent.last_outcome
    if args.scans is not None and last is not None and last.summary is not None:
        print(
            json.dumps(last.summary.to_json(), allow_nan=False)
            if args.json
            else _describe_summary(last.summary)
        )
    return status


def _describe_summary(summary: ScanSummary) -> str:
    volume, level = summary.volume_m3, summary.level
    lines = [f"scan      {summary.scan_id}  ({summary.captured_at})"]
    if volume is None:
        lines.append("volume    unknown")
    else:
        mass = summary.mass_t
        lines.append(f"volume    {volume:.4f} m³" + (f"   mass {mass:.3f} t" if mass else ""))
    lines.append(f"coverage  {summary.coverage * 100:.1f} % of the region observed")
    if level is not None:
        lines.append(
            f"level     min {level.min:.3f}  mean {level.mean:.3f}  "
            f"max {level.max:.3f} m above floor"
        )
    valid = "yes" if summary.valid else f"NO: {summary.invalid_reason}"
    lines.append(f"valid     {valid}")
    lines.append(f"piles     {len(summary.piles)}")
    for f in summary.cameras.failed:
        lines.append(f"camera    {f.serial} failed: {f.error}")
    return "\n".join(lines)


def _scan_dir(target: str, config_path: Path | None) -> Path:
    """A scan directory given as a path, or as a scan id in the config's audit cache."""
    path = Path(target)
    if path.is_dir():
        return path
    if config_path is None:
        from silo_agent.config import ConfigError

        raise ConfigError(f"{target}: not a directory; give --config to look it up by scan id")
    from silo_agent.storage.audit import AuditCache

    config = load_config(config_path)
    return AuditCache(config.audit, config.silo.id).find(target)


def cmd_replay(args: argparse.Namespace) -> int:
    from silo_agent.scan import ScanError
    from silo_agent.service.scan_path import replay
    from silo_agent.storage.audit import comparable, differences

    try:
        directory = _scan_dir(args.scan, args.config)
        published, again = replay(directory)
    except ScanError as exc:
        return _fail(str(exc), EX_DATAERR)
    diff = differences(comparable(published), comparable(again))
    if diff:
        print(f"{directory.name}: replay DIFFERS from the published result:")
        for line in diff:
            print(f"  {line}")
        return FAILURE
    print(
        f"{directory.name}: replay identical to the published result "
        f"(volume {again.get('volume_m3')} m³; timings not compared)"
    )
    return OK


def cmd_report(args: argparse.Namespace) -> int:
    """One self-contained HTML or PNG file of a scan (silo_agent/web/report.py)."""
    from silo_agent.scan import ScanError

    suffix = args.out.suffix.lower()
    if suffix not in (".html", ".png"):
        return _fail(f"--out {args.out}: want a .html or .png file name", USAGE)
    try:
        directory = _scan_dir(args.scan, args.config)
    except ScanError as exc:
        return _fail(str(exc), EX_DATAERR)
    from silo_agent.web.archive import load_scan_view
    from silo_agent.web.report import report_html, report_png

    # a scan id names a kept scan: its published result; a directory given with --config is
    # processed with the config's settings, as `process --config` does
    config = load_config(args.config) if args.config and Path(args.scan).is_dir() else None
    try:
        view = load_scan_view(directory, config)
    except ScanError as exc:
        return _fail(str(exc), EX_DATAERR)
    data = report_html(view).encode() if suffix == ".html" else report_png(view)
    try:
        args.out.write_bytes(data)
    except OSError as exc:
        return _fail(f"cannot write {args.out}: {exc.strerror or exc}", FAILURE)
    print(args.out)
    return OK


def cmd_scans(args: argparse.Namespace) -> int:
    from silo_agent.scan import ScanError, read_manifest
    from silo_agent.storage.audit import RESULT, AuditCache

    config = load_config(args.config)
    cache = AuditCache(config.audit, config.silo.id)
    if args.action == "list":
        entries = cache.entries()
        for e in entries:
            try:
                result = json.loads((e.path / RESULT).read_text(encoding="utf-8"))
                volume = result.get("volume_m3")
                what = (f"{volume:.4f} m³" if volume is not None else "no volume") + (
                    "" if result.get("valid") else " (invalid)"
                )
            except (OSError, ValueError):
                what = "no result"
            print(
                f"{e.scan_id}  {e.captured_at:%Y-%m-%dT%H:%M:%SZ}  {e.bytes / 1e6:8.2f} MB  {what}"
            )
        total = sum(e.bytes for e in entries)
        print(
            f"{len(entries)} scan(s), {total / 1e6:.2f} MB of {cache.cfg.max_bytes / 1e6:.0f} MB"
            f" in {cache.directory}"
        )
        return OK
    if args.scan_id is None:
        return _fail(f"scans {args.action} needs a SCAN_ID", USAGE)
    try:
        path = cache.find(args.scan_id)
    except ScanError as exc:
        return _fail(str(exc), FAILURE)
    if args.action == "show":
        manifest = read_manifest(path)  # bounded and checked, like any scan directory
        manifest.pop("config", None)
        report = {"scan_dir": str(path), "manifest": manifest}
        if (path / RESULT).is_file():
            report["result"] = json.loads((path / RESULT).read_text(encoding="utf-8"))
        print(json.dumps(report, indent=2))
        return OK
    out = args.out or Path(f"{args.scan_id}.tar.gz")
    print(cache.export(args.scan_id, out))
    return OK


# ---------------------------------------------------------------- wiring


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
    p.add_argument("--scans", type=_positive, metavar="N", help="stop after N scans")
    p.add_argument("--json", action="store_true", help="with --scans: the last result as JSON")
    p.set_defaults(handler=cmd_run)

    p = sub.add_parser("replay", help="re-process a cached scan, compare with the published")
    p.add_argument("scan", metavar="SCAN_ID|DIR")
    p.add_argument("--config", type=Path, metavar="FILE", help="to find SCAN_ID in its cache")
    p.set_defaults(handler=cmd_replay)

    p = sub.add_parser("report", help="one self-contained HTML or PNG report of a scan")
    p.add_argument("scan", metavar="SCAN_DIR|SCAN_ID")
    p.add_argument("--config", type=Path, metavar="FILE", help="to find SCAN_ID in its cache")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.html|FILE.png")
    p.set_defaults(handler=cmd_report)

    p = sub.add_parser("scans", help="the audit cache: list, show or export scans")
    p.add_argument("action", choices=["list", "show", "export"])
    p.add_argument("scan_id", nargs="?", metavar="SCAN_ID")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument("--out", type=Path, metavar="FILE.tar.gz", help="export: where to write")
    p.set_defaults(handler=cmd_scans)

    p = sub.add_parser("check-config", help="validate a configuration file and exit")
    p.add_argument("file", type=Path)
    p.set_defaults(handler=cmd_check_config)

    p = sub.add_parser("process", help="reconstruct silo-scan/1 directories offline")
    p.add_argument(
        "scan_dirs",
        type=Path,
        nargs="+",
        metavar="DIR",
        help="a scan directory, or a directory of them (an audit cache)",
    )
    p.add_argument("--config", type=Path, help="config file whose settings override the scan's")
    p.add_argument("--grid-step", type=float, metavar="METRES")
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
        type=_positive,
        default=1,
        metavar="N",
        help="process N scans at a time in worker processes (default 1)",
    )
    p.set_defaults(handler=cmd_process)

    p = sub.add_parser("devices", help="list connected RealSense cameras")
    p.set_defaults(handler=cmd_devices)

    p = sub.add_parser("scan", help="capture all cameras once, write the scan, process it")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument(
        "--out", type=Path, metavar="DIR", help="where to write the scan; default: audit.directory"
    )
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(handler=cmd_scan)

    p = sub.add_parser("record", help="record each live camera to DIR/<serial>.db3")
    p.add_argument("--config", type=Path, required=True, metavar="FILE")
    p.add_argument("--out", type=Path, required=True, metavar="DIR")
    p.add_argument("--seconds", type=_seconds, default=5.0, metavar="S", help="default 5")
    p.set_defaults(handler=cmd_record)

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
    p.set_defaults(handler=cmd_calibrate)

    p = sub.add_parser("simulate", help="render a simulated scene into a silo-scan/1 directory")
    p.add_argument(
        "--scene",
        required=True,
        choices=SCENE_NAMES,
    )
    p.add_argument(
        "--views",
        required=True,
        type=_views,
        metavar="A1,A5",
        help="camera positions A1-A8 (midpoints A1 A3 A5 A7, corners A2 A4 A6 A8)",
    )
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="new scan directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--calib-error",
        type=_calib_error,
        default=(0.0, 0.0),
        metavar="DEG,M",
        help="true poses off the written extrinsics by DEG degrees and M metres",
    )
    p.add_argument(
        "--grid-step",
        type=float,
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
        type=_resolution,
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
        type=_positive,
        default=40,
        metavar="N",
        help="depth frames per recording (default 40: 30 warm-up + 10 aggregated)",
    )
    p.set_defaults(handler=cmd_simulate)

    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return _dispatch(build_parser().parse_args(argv))


def entry() -> NoReturn:
    """`silo-agent` and `python -m silo_agent`: `main`, then exit with its status.

    After `process` the interpreter is not torn down: its output is flushed and the process
    ends at once, which saves a one-off `process` about 0.03 s of freeing modules and objects
    that the system reclaims anyway (`process` writes no file and holds no lock)."""
    args = build_parser().parse_args()
    status = _dispatch(args)
    if args.handler is cmd_process:
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
    from silo_agent.base.heap import keep_freed_memory

    keep_freed_memory()
    handler: Handler = args.handler
    if handler is not cmd_process:  # process sets logging up itself, only when it will log
        _configure_logging(args)
    try:
        return handler(args)
    except KeyboardInterrupt:
        return INTERRUPTED
    except Exception as exc:  # bad input met where no command expected it: still one line
        from silo_agent.base.limits import LimitExceeded
        from silo_agent.config import ConfigError  # loaded already if one was raised
        from silo_agent.scan import ScanError

        if isinstance(exc, ConfigError):
            return _fail(str(exc), EX_CONFIG)
        if isinstance(exc, ScanError | LimitExceeded):
            return _fail(str(exc), EX_DATAERR)
        raise


if __name__ == "__main__":
    entry()
