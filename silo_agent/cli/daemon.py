"""`silo-agent run` (the service, service/daemon.py) and `check-config`."""

from __future__ import annotations

import argparse
import json
import sys

from silo_agent.analysis.summary import ScanSummary
from silo_agent.base.exits import FAILURE, OK
from silo_agent.cli.common import fail, load_config
from silo_agent.config import config_warnings
from silo_agent.service.daemon import Agent
from silo_agent.service.state_lock import StateLocked
from silo_agent.telemetry.prometheus import Metrics


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config, service=True)  # bad: ConfigError -> 78, nothing started
    metrics = Metrics()
    if config.metrics.enabled:  # its port bound now too: one in use is a 78, as the web's
        metrics.bind(config.metrics)
    companions = []
    if config.web.enabled:  # the port bound now: one in use is a 78 before anything starts
        from silo_agent.web.server import WebServer  # Starlette and uvicorn: only with [web]

        companions.append(WebServer.bind(config.web))
    try:
        agent = Agent(
            args.config, config, max_scans=args.scans, companions=companions, metrics=metrics
        )
    except StateLocked as exc:
        return fail(str(exc), FAILURE)
    status = agent.run()
    last = agent.last_outcome
    if args.scans is not None and last is not None and last.summary is not None:
        summary = last.summary
        print(json.dumps(summary.to_json(), allow_nan=False) if args.json else describe(summary))
    if args.scans is not None and agent.failed_scans and status == OK:
        # a one-off or cron `run --scans N` says so when a scan gave no result, as `scan` does
        failed, done = agent.failed_scans, agent.scans_done
        return fail(f"{failed} of {done} scans gave no result (see the log)", FAILURE)
    return status


def describe(summary: ScanSummary) -> str:
    """A few human-readable lines of a published summary."""
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


def check_config(args: argparse.Namespace) -> int:
    config = load_config(args.file, service=True)
    for warning in config_warnings(config):
        print(f"silo-agent: warning: {args.file}: {warning}", file=sys.stderr)
    print(f"{args.file}: ok (silo {config.silo.id}, {len(config.cameras)} camera(s))")
    return OK
