"""`silo-agent replay` and `scans`: the audit cache (storage/audit.py, service/scan_path.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from silo_agent.base.exits import DATA_ERROR, FAILURE, OK, USAGE
from silo_agent.cli.common import fail, load_config
from silo_agent.scan import ScanError, read_manifest
from silo_agent.service.scan_path import read_result
from silo_agent.service.scan_path import replay as replayed
from silo_agent.storage.audit import RESULT, AuditCache, comparable, differences


def scan_dir(target: str, config_path: Path | None) -> Path:
    """A scan directory given as a path, or as a scan id in the config's audit cache."""
    path = Path(target)
    if path.is_dir():
        return path
    if config_path is None:  # a bad scan directory (65), as docs/limits.md says
        problem = "not a directory" if path.exists() else "no such scan directory"
        raise ScanError(f"{target}: {problem} (a scan id needs --config to look it up)")
    config = load_config(config_path)
    return AuditCache(config.audit, config.silo.id).find(target)


def replay(args: argparse.Namespace) -> int:
    try:
        directory = scan_dir(args.scan, args.config)
        published, again = replayed(directory)
    except ScanError as exc:
        return fail(str(exc), DATA_ERROR)
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


def scans(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    cache = AuditCache(config.audit, config.silo.id)
    if args.action == "list":
        return _list(cache)
    if args.scan_id is None:
        return fail(f"scans {args.action} needs a SCAN_ID", USAGE)
    try:
        path = cache.find(args.scan_id)
    except ScanError as exc:
        return fail(str(exc), FAILURE)
    if args.action == "show":
        try:
            manifest = read_manifest(path)  # bounded and checked, like any scan directory
            result = read_result(path)
        except ScanError as exc:
            return fail(str(exc), DATA_ERROR)
        manifest.pop("config", None)
        report = {"scan_dir": str(path), "manifest": manifest}
        if result is not None:
            report["result"] = result
        print(json.dumps(report, indent=2))
        return OK
    out = args.out or Path(f"{args.scan_id}.tar.gz")
    try:
        print(cache.export(args.scan_id, out))
    except OSError as exc:
        return fail(f"cannot write {out}: {exc.strerror or exc}", FAILURE)
    return OK


def _list(cache: AuditCache) -> int:
    """One line per cached scan; a damaged result.json is marked on its line and named with
    its problem on stderr, and the listing goes on (exit 65 at the end)."""
    entries = cache.entries()
    damaged = []
    for e in entries:
        try:
            result = read_result(e.path)
        except ScanError as exc:
            damaged.append(str(exc))
            what = f"DAMAGED {RESULT}"
        else:
            if result is None:
                what = "no result"
            else:
                volume = result.get("volume_m3")
                what = (f"{volume:.4f} m³" if volume is not None else "no volume") + (
                    "" if result.get("valid") else " (invalid)"
                )
        print(f"{e.scan_id}  {e.captured_at:%Y-%m-%dT%H:%M:%SZ}  {e.bytes / 1e6:8.2f} MB  {what}")
    total = sum(e.bytes for e in entries)
    print(
        f"{len(entries)} scan(s), {total / 1e6:.2f} MB of {cache.cfg.max_bytes / 1e6:.0f} MB"
        f" in {cache.directory}"
    )
    for problem in damaged:
        fail(problem, DATA_ERROR)
    return DATA_ERROR if damaged else OK
