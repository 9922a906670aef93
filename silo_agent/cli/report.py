"""`silo-agent report`: one self-contained HTML or PNG file of a scan (silo_agent/web/report.py;
matplotlib loads with this module, only for this command)."""

from __future__ import annotations

import argparse
from pathlib import Path

from silo_agent.base.atomic import write_atomic
from silo_agent.base.exits import DATA_ERROR, FAILURE, OK, USAGE
from silo_agent.cli.cache import scan_dir
from silo_agent.cli.common import fail, load_config
from silo_agent.scan import ScanError
from silo_agent.web.archive import load_scan_view
from silo_agent.web.report import report_html, report_png


def report(args: argparse.Namespace) -> int:
    suffix = args.out.suffix.lower()
    if suffix not in (".html", ".png"):
        return fail(f"--out {args.out}: want a .html or .png file name", USAGE)
    try:
        directory = scan_dir(args.scan, args.config)
    except ScanError as exc:
        return fail(str(exc), DATA_ERROR)
    # a scan id names a kept scan: its published result; a directory given with --config is
    # processed with the config's settings, as `process --config` does
    config = load_config(args.config) if args.config and Path(args.scan).is_dir() else None
    try:
        view = load_scan_view(directory, config)
    except ScanError as exc:
        return fail(str(exc), DATA_ERROR)
    data = report_html(view).encode() if suffix == ".html" else report_png(view)
    try:  # whole or not at all: a full disk had left a truncated report in the old one's place
        write_atomic(args.out, data, keep_access=args.out.is_file())
    except OSError as exc:
        return fail(f"cannot write {args.out}: {exc.strerror or exc}", FAILURE)
    print(args.out)
    return OK
