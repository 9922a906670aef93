"""Durable outbox: every message is on disk before paho sees it and leaves only on a broker ack.

SQLite in WAL mode with `synchronous=FULL`, so a committed message survives a power cut.
Rows are sent oldest first (ascending id) and keep the `msg_id`, `seq` and `ts` they were
made with. Bounds (count, bytes, age) drop the oldest non-retained messages first; retained
"latest" topics keep only their newest pending value. The message counter `seq`, the Sparkplug
`bdSeq` and the drop counters live in the same database, so they survive restarts with it.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import structlog

from silo_agent.config import MqttConfig
from silo_agent.telemetry.payloads import Envelope

log = structlog.get_logger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS messages (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    topic TEXT NOT NULL,
    payload BLOB NOT NULL,
    qos INTEGER NOT NULL,
    retain INTEGER NOT NULL,
    latest INTEGER NOT NULL,      -- 1: only the newest pending row of this topic matters
    kind TEXT NOT NULL,           -- "json", "binary" or "sparkplug" (seq set when sent)
    msg_id TEXT,
    seq INTEGER,
    correlation BLOB,             -- MQTT 5 Correlation Data of a command reply
    created REAL NOT NULL,        -- unix time, for the age bound and Sparkplug is_historical
    size INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
"""


@dataclass(frozen=True)
class OutboxLimits:
    """The outbox's bounds; the defaults are the `[mqtt]` config's."""

    max_messages: int = MqttConfig.model_fields["outbox_max_messages"].default
    max_bytes: int = MqttConfig.model_fields["outbox_max_bytes"].default
    max_age_s: float = MqttConfig.model_fields["outbox_max_age_days"].default * 86400.0


@dataclass(frozen=True)
class Row:
    id: int
    topic: str
    payload: bytes
    qos: int
    retain: bool
    kind: str
    msg_id: str | None
    seq: int | None
    correlation: bytes | None
    created: float


class Outbox:
    """Thread-safe: producers enqueue from any thread, the MQTT thread reads and acks."""

    def __init__(self, path: Path, limits: OutboxLimits | None = None) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.limits = limits or OutboxLimits()
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(SCHEMA)

    @contextmanager
    def _tx(self) -> Iterator[None]:
        """One IMMEDIATE transaction under the lock: committed (fsynced) or rolled back."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # ------------------------------------------------------------ counters

    def _bump(self, name: str, by: int = 1) -> int:
        self._db.execute(
            "INSERT INTO counters(name, value) VALUES (?, ?) "
            "ON CONFLICT(name) DO UPDATE SET value = value + excluded.value",
            (name, by),
        )
        return self._counter(name)

    def _counter(self, name: str) -> int:
        row = self._db.execute("SELECT value FROM counters WHERE name = ?", (name,)).fetchone()
        return int(row[0]) if row else 0

    def counter(self, name: str) -> int:
        with self._lock:
            return self._counter(name)

    def next_envelope(self) -> Envelope:
        """A fresh envelope for a message that is sent directly (session state, not queued)."""
        with self._tx():
            return Envelope.new(self._bump("seq"))

    def next_bd_seq(self) -> int:
        """Sparkplug bdSeq for the next MQTT session, 0..255, persisted before it is used."""
        with self._tx():
            self._bump("bd_seq")
            return (self._counter("bd_seq") - 1) % 256

    # ------------------------------------------------------------ queue

    def enqueue(
        self,
        topic: str,
        build: Callable[[Envelope | None], bytes],
        *,
        qos: int = 1,
        retain: bool = False,
        latest: bool = False,
        kind: str = "json",
        correlation: bytes | None = None,
        with_envelope: bool = True,
    ) -> Envelope | None:
        """Commit one message; `build` turns the envelope (seq taken in the same transaction)
        into the payload. `latest` drops older pending rows of the same topic."""
        with self._tx():
            env = Envelope.new(self._bump("seq")) if with_envelope else None
            payload = build(env)
            if latest:
                self._db.execute(
                    "DELETE FROM messages WHERE topic = ? AND latest = 1", (topic,)
                )
            self._db.execute(
                "INSERT INTO messages(topic, payload, qos, retain, latest, kind, msg_id, seq,"
                " correlation, created, size) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    topic, payload, qos, int(retain), int(latest), kind,
                    env.msg_id if env else None, env.seq if env else None,
                    correlation, time.time(), len(payload) + len(topic),
                ),
            )
            dropped = self._enforce_bounds()
        if dropped:
            log.warning(
                "outbox bound reached, oldest messages dropped",
                dropped=dropped, total_dropped=self.counter("dropped"),
            )
        return env

    def _enforce_bounds(self) -> int:
        """Drop by age, then by count and bytes; non-retained first. Returns rows dropped."""
        limits = self.limits
        dropped = self._db.execute(
            "DELETE FROM messages WHERE retain = 0 AND created < ?",
            (time.time() - limits.max_age_s,),
        ).rowcount
        count, size = self._db.execute(
            "SELECT COUNT(*), COALESCE(SUM(size), 0) FROM messages"
        ).fetchone()
        if count > limits.max_messages or size > limits.max_bytes:
            # oldest non-retained first, then oldest retained, never the newest row
            victims = self._db.execute(
                "SELECT id, size FROM messages WHERE id < (SELECT MAX(id) FROM messages) "
                "ORDER BY retain ASC, id ASC"
            )
            doomed = []
            for row_id, row_size in victims:
                if count <= limits.max_messages and size <= limits.max_bytes:
                    break
                doomed.append((row_id,))
                count -= 1
                size -= row_size
            self._db.executemany("DELETE FROM messages WHERE id = ?", doomed)
            dropped += len(doomed)
        if dropped:
            self._bump("dropped", dropped)
        return dropped

    def pending(
        self, after_id: int = 0, limit: int = 100, kinds: tuple[str, ...] | None = None
    ) -> list[Row]:
        """Oldest pending rows with id > after_id (of the given kinds)."""
        where, args = "id > ?", [after_id]
        if kinds is not None:
            where += f" AND kind IN ({', '.join('?' * len(kinds))})"
            args.extend(kinds)
        with self._lock:
            rows = self._db.execute(
                "SELECT id, topic, payload, qos, retain, kind, msg_id, seq, correlation, created "
                f"FROM messages WHERE {where} ORDER BY id LIMIT ?",
                (*args, limit),
            ).fetchall()
        return [
            Row(r[0], r[1], bytes(r[2]), r[3], bool(r[4]), r[5], r[6], r[7],
                None if r[8] is None else bytes(r[8]), r[9])
            for r in rows
        ]

    def ack(self, row_ids: list[int]) -> None:
        """The broker has these messages: forget them (one transaction)."""
        with self._tx():
            self._db.executemany("DELETE FROM messages WHERE id = ?", [(i,) for i in row_ids])

    def reject(self, row_id: int) -> None:
        """The broker refused the message for good (e.g. ACL): forget it, but count it."""
        with self._tx():
            self._db.execute("DELETE FROM messages WHERE id = ?", (row_id,))
            self._bump("rejected")

    def discard_kind(self, kind: str) -> None:
        """Forget pending messages of a kind that is no longer sent (not counted as drops)."""
        with self._tx():
            self._db.execute("DELETE FROM messages WHERE kind = ?", (kind,))

    def size(self) -> tuple[int, int]:
        """(pending messages, pending bytes)."""
        with self._lock:
            count, size = self._db.execute(
                "SELECT COUNT(*), COALESCE(SUM(size), 0) FROM messages"
            ).fetchone()
        return int(count), int(size)
