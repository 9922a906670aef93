"""`python -m silo_agent.telemetry`: publish by hand, flush an outbox, keep the schemas in sync.

publish --config FILE --result RESULT.json [--heightmap MAP.npz] [--alarm EVENT.json]
        [--repeat N] [--timeout S]
    queue the messages (one JSON line per queued message on stdout: topic, msg_id, seq, ts),
    then send them; exit 0 when the broker has all of them, 1 if some are still pending
    after --timeout (they stay in the outbox for the next run)
flush --config FILE [--timeout S] [--linger S]
    send what an earlier run left in the outbox (then stay connected --linger seconds)
schemas [--check] [DIR]
    write config/schemas/*.json from the payload models, or check they are current
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from silo_agent.analysis.alarm_types import AlarmEvent
from silo_agent.analysis.summary import ScanSummary
from silo_agent.base.exits import CONFIG_ERROR as EX_CONFIG
from silo_agent.config import ConfigError, load_config
from silo_agent.grid.heightmap import HeightMap
from silo_agent.telemetry.client import Telemetry
from silo_agent.telemetry.payloads import Envelope, json_schemas, render_schema, write_schemas

DEFAULT_SCHEMAS = Path(__file__).resolve().parents[2] / "config" / "schemas"


def load_heightmap(path: Path) -> HeightMap:
    """A height map saved with numpy.savez(origin=, step=, heights=, observed=, inside=)."""
    with np.load(path) as data:
        return HeightMap(
            origin=(float(data["origin"][0]), float(data["origin"][1])),
            step=float(data["step"]),
            heights=data["heights"],
            observed=data["observed"].astype(bool),
            inside=data["inside"],
        )


def _emit(topic: str, env: Envelope) -> None:
    print(json.dumps({"topic": topic, **env.model_dump()}), flush=True)


def _send(telemetry: Telemetry, timeout: float, linger: float = 0.0) -> int:
    telemetry.start()
    end = time.monotonic() + timeout
    while telemetry.outbox.size()[0] and time.monotonic() < end:
        time.sleep(0.05)
    pending = telemetry.outbox.size()[0]
    if not pending and linger > 0:
        print("drained", flush=True)
        time.sleep(linger)
    telemetry.stop()
    if pending:
        print(f"silo-agent: {pending} message(s) still pending in the outbox", file=sys.stderr)
        return 1
    return 0


def cmd_publish(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    telemetry = Telemetry.from_config(config)
    summary = ScanSummary.from_json(json.loads(args.result.read_text(encoding="utf-8")))
    heightmap = load_heightmap(args.heightmap) if args.heightmap else None
    for k in range(args.repeat):
        one = summary
        if args.repeat > 1:
            one = replace(summary, scan_id=f"{summary.scan_id}-{k}")
        for topic, env in zip(
            ("scan", "volume", "heightmap"), telemetry.publish_result(one, heightmap), strict=False
        ):
            _emit(telemetry.topic(topic), env)
    if args.alarm:
        event = AlarmEvent.from_json(json.loads(args.alarm.read_text(encoding="utf-8")))
        _emit(telemetry.topic("alarm"), telemetry.publish_alarm(event))
    return _send(telemetry, args.timeout)


def cmd_flush(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    return _send(Telemetry.from_config(config), args.timeout, args.linger)


def cmd_schemas(args: argparse.Namespace) -> int:
    if not args.check:
        for path in write_schemas(args.dir):
            print(path)
        return 0
    stale = [
        name
        for name, schema in json_schemas().items()
        if not (args.dir / name).is_file()
        or (args.dir / name).read_text(encoding="utf-8") != render_schema(schema)
    ]
    if stale:
        print(f"out of date in {args.dir}: {', '.join(stale)}", file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m silo_agent.telemetry",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--log-level", default="info", choices=["debug", "info", "warning", "error"]
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("publish", help="queue and send one result (and an alarm)")
    p.add_argument("--config", type=Path, required=True)
    p.add_argument("--result", type=Path, required=True, help="result summary JSON")
    p.add_argument(
        "--heightmap", type=Path, help=".npz with origin, step, heights, observed, inside"
    )
    p.add_argument("--alarm", type=Path, help="alarm event JSON")
    p.add_argument("--repeat", type=int, default=1, help="publish N results, scan ids suffixed -k")
    p.add_argument("--timeout", type=float, default=30.0)
    p.set_defaults(handler=cmd_publish)
    p = sub.add_parser("flush", help="send what the outbox holds")
    p.add_argument("--config", type=Path, required=True)
    p.add_argument("--timeout", type=float, default=30.0)
    p.add_argument("--linger", type=float, default=0.0, help="stay connected after flushing")
    p.set_defaults(handler=cmd_flush)
    p = sub.add_parser("schemas", help="write or check config/schemas/*.json")
    p.add_argument("--check", action="store_true")
    p.add_argument("dir", type=Path, nargs="?", default=DEFAULT_SCHEMAS)
    p.set_defaults(handler=cmd_schemas)
    args = parser.parse_args(argv)

    from silo_agent.base.log import configure_logging

    configure_logging(args.log_level)
    try:
        return args.handler(args)
    except ConfigError as exc:
        print(f"silo-agent: {exc}", file=sys.stderr)
        return EX_CONFIG


if __name__ == "__main__":
    raise SystemExit(main())
