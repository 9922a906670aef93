"""`silo-agent scan`: one capture through the daemon's own scan path (service/scan_once.py)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from datetime import UTC, datetime
from pathlib import Path

from silo_agent.base.exits import CONFIG_ERROR, FAILURE, OK
from silo_agent.base.files import missing_directories
from silo_agent.cli.common import fail, load_config, output_directory_problem
from silo_agent.detect import ModelError
from silo_agent.service.scan_once import Stages, scan_once
from silo_agent.service.scan_path import new_scan_id
from silo_agent.storage.audit import AuditCache


def scan(args: argparse.Namespace) -> int:
    """The scan (with its config snapshot) into the cache, then processed, summarised and
    kept exactly as the daemon does; the summary (or a description) on stdout."""
    config = load_config(args.config)
    audit = config.audit.model_copy(update={"directory": args.out}) if args.out else config.audit
    cache = AuditCache(audit, config.silo.id)
    if problem := output_directory_problem(cache.directory):  # before the cameras capture
        return fail(problem, FAILURE)
    made = missing_directories(cache.directory)  # what writing the scan will create
    started = datetime.now(UTC)
    run = scan_once(config, cache, new_scan_id(config, started, cache.names()), started, Stages())
    for failure in run.capture.failures:
        print(f"silo-agent: warning: {failure.error}", file=sys.stderr)
    if run.scan is None:
        return fail("no camera delivered a cloud; no scan written", FAILURE)
    if run.directory is None:  # a full disk, a failing one: nothing of the scan is left
        _remove_empty(made)
        return fail(f"{run.write_error}; no scan written", FAILURE)
    if run.analysed is None:
        if isinstance(run.error, ModelError):
            return fail(f"{run.error}; the raw scan is kept in {run.directory}", CONFIG_ERROR)
        assert run.error is not None
        raise run.error
    if run.cache_full:  # the raw scan is the measurement: kept, to `process` once there is room
        return fail(f"{run.write_error}; the raw scan is kept without it", FAILURE)
    if args.json:
        out = {**run.summary.to_json(), "scan_dir": str(run.directory)}
        print(json.dumps(out, allow_nan=False))
    else:
        print(run.analysed.describe())
        degraded = " (degraded)" if run.capture.degraded else ""
        print(f"scan written to {run.directory}{degraded}")
    return OK


def _remove_empty(directories: list[Path]) -> None:
    """Remove the directories this command made (deepest first), each only if it is empty:
    anything another process put there since stays, and so do the directories above it."""
    for directory in directories:
        try:
            os.rmdir(directory)
        except OSError:
            return
