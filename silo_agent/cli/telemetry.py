"""`silo-agent publish`, `flush` and `schemas`: MQTT by hand (telemetry/client.py).

publish: queue the messages (one JSON line per queued message on stdout: topic, msg_id, seq,
ts), then send them; exit 0 when the broker has all of them, 1 if some are still pending after
--timeout (they stay in the outbox for the next run). flush: send what an earlier run left in
the outbox (then stay connected --linger seconds). Both hold the lock `run` holds (one process
per outbox: exit 1 while an agent runs on it) and connect as `<client_id>-publish` /
`-flush`, sending the outbox's rows and nothing else: `P/status`, the alarm states, Home
Assistant and Sparkplug are the agent's. schemas: write config/schemas/*.json from the payload
models, or check they are current.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

from pydantic import ValidationError

from silo_agent.analysis.alarm_types import AlarmEvent
from silo_agent.analysis.summary import ScanSummary
from silo_agent.base.exits import DATA_ERROR, FAILURE, OK
from silo_agent.cli.common import fail, load_config
from silo_agent.config import Config
from silo_agent.grid.heightmap import HeightMap
from silo_agent.service.scan_path import checked_summary
from silo_agent.service.state_lock import StateLock, StateLocked
from silo_agent.storage.audit import load_heightmap
from silo_agent.telemetry.client import Telemetry
from silo_agent.telemetry.heightmap_codec import encode_heightmap
from silo_agent.telemetry.payloads import (
    Envelope,
    alarm_payload,
    describe_errors,
    json_schemas,
    render_schema,
    write_schemas,
)

Parsed = TypeVar("Parsed")

DEFAULT_SCHEMAS = Path(__file__).resolve().parents[2] / "config" / "schemas"


def _emit(topic: str, env: Envelope) -> None:
    print(json.dumps({"topic": topic, **env.model_dump()}), flush=True)


def _locked(config: Config, why: str) -> StateLock | None:
    """The lock `run` holds on the outbox and the audit directory, taken; None, after one
    line saying so and `why`, while an agent holds it (it owns the outbox: two processes on
    one would send the same rows, and opening it passes the agent's Last Will seq)."""
    lock = StateLock.of(config)
    try:
        lock.acquire()
    except StateLocked as exc:
        fail(f"{exc}; {why}", FAILURE)
        return None
    return lock


def _send(telemetry: Telemetry, timeout: float, linger: float = 0.0) -> int:
    telemetry.start()
    end = time.monotonic() + timeout
    while telemetry.unsent() and time.monotonic() < end:
        time.sleep(0.05)
    pending = telemetry.unsent()
    if not pending and linger > 0:
        print("drained", flush=True)
        time.sleep(linger)
    telemetry.stop()
    if pending:
        print(f"silo-agent: {pending} message(s) still pending in the outbox", file=sys.stderr)
        return FAILURE
    return OK


def _read(path: Path, parse: Callable[[dict[str, Any]], Parsed]) -> Parsed:
    """A JSON file parsed; ValueError naming the file and the problem."""
    try:
        return parse(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, ValueError, RecursionError) as exc:
        raise ValueError(f"{path}: {exc}") from None


def _event(data: dict[str, Any]) -> AlarmEvent:
    """An alarm event its payload accepts, so a bad value is refused before anything is
    queued (`publish_alarm` checks it only after the result's messages are)."""
    event = AlarmEvent.from_json(data)
    try:
        alarm_payload(Envelope.new(1), event)
    except ValidationError as exc:
        raise ValueError(f"alarm event: {describe_errors(exc)}") from None
    return event


def _heightmap(path: Path, scan_id: str) -> HeightMap:
    """A kept height map that `P/heightmap` can carry (encoded once here); ValueError naming
    the file and the problem."""
    heightmap = load_heightmap(path)
    try:
        encode_heightmap(heightmap, scan_id)
    except ValueError as exc:
        raise ValueError(f"{path}: height map: {exc}") from None
    return heightmap


def publish(args: argparse.Namespace) -> int:
    config = load_config(args.config, service=True)  # its outbox, TLS files, password
    try:  # every file read and checked before anything is queued
        summary = _read(args.result, checked_summary)
        event = _read(args.alarm, _event) if args.alarm else None
        heightmap = _heightmap(args.heightmap, summary.scan_id) if args.heightmap else None
    except ValueError as exc:
        return fail(str(exc), DATA_ERROR)
    lock = _locked(config, "the running agent sends the outbox itself: stop it to publish by hand")
    if lock is None:
        return FAILURE
    try:
        return _publish(args, config, summary, event, heightmap)
    finally:
        lock.release()


def _publish(
    args: argparse.Namespace,
    config: Config,
    summary: ScanSummary,
    event: AlarmEvent | None,
    heightmap: HeightMap | None,
) -> int:
    telemetry = Telemetry.from_config(config, by_hand="publish")
    for k in range(args.repeat):
        one = summary
        if args.repeat > 1:
            one = replace(summary, scan_id=f"{summary.scan_id}-{k}")
        for topic, env in zip(
            ("scan", "volume", "heightmap"), telemetry.publish_result(one, heightmap), strict=False
        ):
            _emit(telemetry.topic(topic), env)
    if event is not None:
        _emit(telemetry.topic("alarm"), telemetry.publish_alarm(event))
    return _send(telemetry, args.timeout)


def flush(args: argparse.Namespace) -> int:
    config = load_config(args.config, service=True)
    lock = _locked(config, "the running agent sends the outbox itself")
    if lock is None:
        return FAILURE
    try:
        return _send(Telemetry.from_config(config, by_hand="flush"), args.timeout, args.linger)
    finally:
        lock.release()


def schemas(args: argparse.Namespace) -> int:
    directory: Path = args.dir or DEFAULT_SCHEMAS
    if not args.check:
        for path in write_schemas(directory):
            print(path)
        return OK
    stale = [
        name
        for name, schema in json_schemas().items()
        if not (directory / name).is_file()
        or (directory / name).read_text(encoding="utf-8") != render_schema(schema)
    ]
    if stale:
        print(f"out of date in {directory}: {', '.join(stale)}", file=sys.stderr)
        return FAILURE
    return OK
