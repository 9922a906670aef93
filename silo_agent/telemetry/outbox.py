"""Durable outbox: every message is on disk before paho sees it and leaves only on a broker ack.

SQLite in WAL mode with `synchronous=FULL`, so a committed message survives a power cut.
Rows are sent oldest first (ascending id) and keep the `msg_id`, `seq` and `ts` they were
made with. Bounds (count, bytes, age) drop the oldest non-retained messages first; retained
"latest" topics keep only their newest pending value. The message counter `seq`, the Sparkplug
`bdSeq` and the drop counters live in the same database, so they survive restarts with it.

A row that can never be published (paho refuses its topic, it exceeds the broker's packet
size) is dead-lettered: moved to the `dead_letter` table and counted, so it cannot block the
rows behind it. A corrupt database is moved aside at open and a fresh one started; `seq` and
`bdSeq` then continue from a small state file beside it (`<outbox>.state.json`, replaced
atomically), which always holds a `seq` at or above every one handed out.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

import structlog

from silo_agent.analysis.alarm_types import AlarmStateName
from silo_agent.base.atomic import write_atomic
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
CREATE TABLE IF NOT EXISTS dead_letter (
    id INTEGER PRIMARY KEY,       -- the row's id in messages
    topic TEXT NOT NULL,
    payload BLOB NOT NULL,
    qos INTEGER NOT NULL,
    retain INTEGER NOT NULL,
    kind TEXT NOT NULL,
    msg_id TEXT,
    seq INTEGER,
    correlation BLOB,
    created REAL NOT NULL,
    reason TEXT NOT NULL,         -- why it can never be published
    dead_at REAL NOT NULL
);
"""
DEAD_LETTER_KEEP = 1000  # newest dead letters kept for inspection; the counter counts all
SEQ_RESERVE = 1000  # seq values the state file reserves at a time (one fsync per block)
WILL_SEQ_HEADROOM = 1_000_000  # seq values a session may use below its Last Will's seq
MEMORY_MAX_MESSAGES = 10_000  # the queue held in memory while the disk cannot take it
MEMORY_MAX_BYTES = 16 * 2**20  # ... about 150 scans' results with their height maps
TEND_S = 1.0  # how often the file is checked (deleted?) or, in memory, the disk tried again
# SQLite primary result codes of a disk that cannot take a write (full, read-only, I/O error,
# gone); any other error is a bug or a corrupt file
STORAGE_ERRORS = frozenset(
    {
        sqlite3.SQLITE_FULL,
        sqlite3.SQLITE_IOERR,
        sqlite3.SQLITE_READONLY,
        sqlite3.SQLITE_CANTOPEN,
        sqlite3.SQLITE_PERM,
    }
)
T = TypeVar("T")


def _is_storage_error(exc: sqlite3.Error) -> bool:
    return (getattr(exc, "sqlite_errorcode", 0) & 0xFF) in STORAGE_ERRORS


def _close_quietly(db: sqlite3.Connection) -> None:
    """Close a connection to a file that may be gone or full (its checkpoint may fail)."""
    with contextlib.suppress(sqlite3.Error):
        db.close()


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


def _to_row(r: tuple) -> Row:
    """A Row from the columns id, topic, payload, qos, retain, kind, msg_id, seq, correlation,
    created (in that order) of a SELECT."""
    return Row(
        r[0],
        r[1],
        bytes(r[2]),
        r[3],
        bool(r[4]),
        r[5],
        r[6],
        r[7],
        None if r[8] is None else bytes(r[8]),
        r[9],
    )


class Outbox:
    """Thread-safe: producers enqueue from any thread, the MQTT thread reads and acks."""

    def __init__(self, path: Path, limits: OutboxLimits | None = None) -> None:
        self.path = Path(path)
        self.limits = limits or OutboxLimits()
        self.state_path = self.path.with_name(self.path.name + ".state.json")
        self.moved_aside: Path | None = None  # where a corrupt outbox went at open, if it was
        self.fault: str | None = None  # why the queue is held in memory, not on disk
        self.on_fault: Callable[[AlarmStateName, str], None] | None = None  # change, why
        self._events: list[tuple[AlarmStateName, str]] = []  # fault changes not announced yet
        self._lock = threading.Lock()
        self._identity: tuple[int, int] | None = None  # (device, inode) of the open file
        self._tended_at = 0.0
        try:
            try:
                self._db = self._open_disk()
            except sqlite3.DatabaseError as exc:
                if _is_storage_error(exc):
                    raise
                self.moved_aside = self._move_aside(exc)
                self._db = self._open_disk()
        except (sqlite3.Error, OSError) as exc:  # full, read-only, unreachable: in memory
            self._db = self._memory_db(self._read_only_disk())
            self._set_fault(f"cannot open {self.path}: {exc}")
        self._state = self._read_state()
        self._resume_counters()

    def _open_disk(self, check: bool = True) -> sqlite3.Connection:
        """The database file (created, with its directory, if missing); remembers which file
        it is, so that `tend` notices when it is deleted or replaced."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        db = self._connect(check)
        stat = os.stat(self.path)
        self._identity = (stat.st_dev, stat.st_ino)
        return db

    def _read_only_disk(self) -> sqlite3.Connection | None:
        """The database file opened read-only, if it can be read at all (a full or read-only
        disk still holds the messages queued before)."""
        if not self.path.is_file():
            return None
        try:
            db = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro", uri=True)
            db.execute("SELECT COUNT(*) FROM messages").fetchone()
            return db
        except (sqlite3.Error, OSError):
            return None

    def _memory_db(self, source: sqlite3.Connection | None) -> sqlite3.Connection:
        """An in-memory database with the schema, holding a copy of `source` if given."""
        memory = sqlite3.connect(":memory:", check_same_thread=False, isolation_level=None)
        if source is not None:
            try:
                source.backup(memory)
            except sqlite3.Error as exc:
                log.error("cannot read the outbox database", path=str(self.path), error=str(exc))
            finally:
                _close_quietly(source)
        memory.executescript(SCHEMA)
        return memory

    def _connect(self, check: bool = True) -> sqlite3.Connection:
        """Open (and `check`) the database; sqlite3.DatabaseError if it is not a sound one."""
        db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            db.executescript(SCHEMA)
            (verdict,) = db.execute("PRAGMA quick_check").fetchone() if check else ("ok",)
            if verdict != "ok":
                raise sqlite3.DatabaseError(f"integrity check failed: {verdict}")
        except sqlite3.DatabaseError:
            db.close()
            raise
        return db

    def _move_aside(self, exc: sqlite3.DatabaseError) -> Path:
        """Rename the corrupt database (and its WAL and shared-memory files) with a UTC
        timestamp, so that the agent starts and the file stays for inspection."""
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        for suffix in ("", "-wal", "-shm"):
            source = self.path.with_name(self.path.name + suffix)
            if source.exists():
                os.replace(source, aside.with_name(aside.name + suffix))
        log.error(
            "outbox database is corrupt: moved aside, starting with an empty outbox",
            path=str(self.path),
            moved_to=str(aside),
            error=str(exc),
        )
        return aside

    # ------------------------------------------------------------ state file

    def _read_state(self) -> dict[str, int]:
        """The counters of the state file; empty if there is none or it is unreadable."""
        try:
            data = json.loads(self.state_path.read_text(encoding="utf-8"))
            state = {name: int(data[name]) for name in ("seq", "bd_seq")}
            state["corrupt_alarm"] = int(data.get("corrupt_alarm", 0))
            return state
        except FileNotFoundError:
            return {}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning(
                "outbox state file unreadable, ignored", path=str(self.state_path), error=str(exc)
            )
            return {}

    def _write_state(self) -> None:
        """Replace the state file atomically (write, fsync, rename, fsync the directory)."""
        try:
            write_atomic(self.state_path, json.dumps(self._state).encode("utf-8"))
        except OSError as exc:
            log.warning(
                "cannot write the outbox state file", path=str(self.state_path), error=str(exc)
            )

    def _resume_counters(self) -> None:
        """A database without a `seq` (new, emptied or replaced) continues from the state
        file, so `seq` and `bdSeq` never go back."""

        def body() -> None:
            if self._db.execute("SELECT 1 FROM counters WHERE name = 'seq'").fetchone() is None:
                for name in ("seq", "bd_seq"):
                    if self._state.get(name, 0) > self._counter(name):
                        self._bump(name, self._state[name] - self._counter(name))
            self._pass_will()
            self._state = {
                "seq": max(self._state.get("seq", 0), self._counter("seq")),
                "bd_seq": self._counter("bd_seq"),
                "corrupt_alarm": self._state.get("corrupt_alarm", 0),
            }

        self._write(body)

    @property
    def corrupt_raised(self) -> bool:
        """The `outbox` alarm raised for a corrupt database moved aside is still on."""
        return bool(self._state.get("corrupt_alarm"))

    def corrupt_alarm_change(self) -> AlarmStateName | None:
        """ "raised" when a corrupt outbox was just moved aside, "cleared" at the first start
        after the alarm was raised that finds no moved-aside copy left, else None."""
        change: AlarmStateName
        if self.moved_aside is not None:
            change, flag = "raised", 1
        elif self._state["corrupt_alarm"] and not self.corrupt_copies():
            change, flag = "cleared", 0
        else:
            return None
        with self._lock:
            self._state["corrupt_alarm"] = flag
            self._write_state()
        return change

    def corrupt_alarm_raised(self) -> bool:
        """Whether the `outbox` alarm stands raised (persisted in the state file)."""
        return bool(self._state["corrupt_alarm"])

    def corrupt_copies(self) -> list[Path]:
        """The corrupt outboxes moved aside and still beside this one."""
        return list(self.path.parent.glob(self.path.name + ".corrupt-*"))

    def _write(self, body: Callable[[], T]) -> T:
        """Run `body` in one IMMEDIATE transaction under the lock: committed (fsynced) or
        rolled back. When the disk cannot take it (full, read-only, gone), the queue moves
        into memory and `body` runs there: a producer never fails for the disk's sake."""
        with self._lock:
            try:
                result = self._transaction(body)
            except sqlite3.Error as exc:
                if self.fault is not None or not _is_storage_error(exc):
                    raise
                self._spill(f"cannot write {self.path}: {exc}")
                result = self._transaction(body)
        self.announce()
        return result

    def _transaction(self, body: Callable[[], T]) -> T:
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            result = body()
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:  # SQLite may have rolled it back itself (disk full)
                with contextlib.suppress(sqlite3.Error):
                    db.execute("ROLLBACK")
            raise
        return result

    def _spill(self, reason: str) -> None:
        """Hold the queue in memory (a copy of the database, cut to the memory bounds, newest
        kept) until the disk takes it again (`tend`)."""
        disk = self._db
        self._db = self._memory_db(disk)
        self._set_fault(reason)
        dropped = self._transaction(self._enforce_bounds)
        if dropped:
            log.warning("outbox in memory: oldest messages dropped to fit", dropped=dropped)

    def _set_fault(self, reason: str | None) -> None:
        if reason is not None and self.fault is None:
            log.error(
                "outbox database cannot be written: messages are held in memory until it can",
                path=str(self.path),
                error=reason,
                keep_messages=MEMORY_MAX_MESSAGES,
                keep_bytes=MEMORY_MAX_BYTES,
            )
            self._events.append(
                (
                    "raised",
                    f"{reason}; the newest messages (up to {MEMORY_MAX_MESSAGES:,}, "
                    f"{MEMORY_MAX_BYTES // 2**20} MiB) are held in memory and lost if the agent "
                    "stops before the disk takes them",
                )
            )
        elif reason is None and self.fault is not None:
            log.info("outbox database writable again", path=str(self.path))
            self._events.append(("cleared", f"outbox database {self.path} writable again"))
        self.fault = reason

    def announce(self) -> None:
        """Tell `on_fault` of the fault changes met so far (never under the lock: it queues
        the `outbox` alarm through this outbox)."""
        if self.on_fault is None:
            return
        with self._lock:
            events, self._events = self._events, []
        for change, message in events:
            self.on_fault(change, message)

    def tend(self) -> None:
        """Called often by the network thread; every TEND_S: notice a database file deleted
        or replaced under the agent (writes would go to a file nobody reads again) and
        recreate it; while the queue is in memory, try the disk again."""
        now = time.monotonic()
        if now < self._tended_at + TEND_S:
            return
        self._tended_at = now
        with self._lock:
            if self.fault is None:
                self._check_file()
            else:
                self._recover()
        self.announce()

    def _check_file(self) -> None:
        try:
            stat = os.stat(self.path)
            if (stat.st_dev, stat.st_ino) == self._identity:
                return
        except OSError:
            pass
        pending = self._db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
        log.error(
            "outbox database deleted or replaced while running: recreating it",
            path=str(self.path),
            pending=pending,
        )
        self._events.append(
            (
                "raised",
                f"outbox database {self.path} was deleted or replaced while the agent ran; "
                f"recreating it with the {pending} messages pending",
            )
        )
        old = self._db
        try:
            new = self._open_disk(check=False)
        except (sqlite3.Error, OSError) as exc:
            self._spill(f"cannot recreate {self.path}: {exc}")
            return
        try:
            old.backup(new)
        except sqlite3.Error as exc:
            _close_quietly(new)
            self._spill(f"cannot recreate {self.path}: {exc}")
            return
        self._db = new
        _close_quietly(old)
        self._events.append(("cleared", f"outbox database {self.path} recreated"))

    def _recover(self) -> None:
        """Copy the queue held in memory onto the disk; on success, work on disk again."""
        try:
            disk = self._open_disk(check=False)
        except sqlite3.DatabaseError as exc:
            if _is_storage_error(exc):
                return
            self.moved_aside = self._move_aside(exc)  # corrupt meanwhile: start it afresh
            return
        except OSError:
            return
        try:
            self._db.backup(disk)
        except sqlite3.Error:
            _close_quietly(disk)
            return
        memory, self._db = self._db, disk
        memory.close()
        self._set_fault(None)

    def close(self) -> None:
        with self._lock:
            if self.fault is not None:
                self._recover()
            if self.fault is not None:
                pending = self._db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
                log.error(
                    "outbox database still cannot be written: the messages held in memory are lost",
                    path=str(self.path),
                    lost=pending,
                    error=self.fault,
                )
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

    def _next_seq(self) -> int:
        """The next `seq`; past the state file's reservation, reserve the next block first."""
        seq = self._bump("seq")
        if seq > self._state["seq"]:
            self._state["seq"] = seq + SEQ_RESERVE
            self._write_state()
        return seq

    def will_seq(self) -> int:
        """The `seq` of the next session's Last Will: WILL_SEQ_HEADROOM above the current one,
        so the `offline` status sorts after everything the session sends. Attempts that never
        connected leave it armed, so it is reused while there is room below it."""

        def body() -> int:
            seq, will = self._counter("seq"), self._counter("will_seq")
            if will - seq < WILL_SEQ_HEADROOM // 2:
                self._bump("will_seq", seq + WILL_SEQ_HEADROOM - will)
                will = seq + WILL_SEQ_HEADROOM
                if will > self._state["seq"]:  # a lost database must continue above it too
                    self._state["seq"] = will
                    self._write_state()
            return will

        return self._write(body)

    def near_will_seq(self, will_seq: int) -> bool:
        """The session whose Last Will carries `will_seq` is about to reach it: a new session
        must arm a higher one before the `offline` would sort before what was sent."""
        return self.last_seq >= will_seq - WILL_SEQ_HEADROOM // 10

    def _pass_will(self) -> None:
        gap = self._counter("will_seq") - self._counter("seq")
        if gap > 0:
            self._bump("seq", gap)

    def pass_will(self) -> None:
        """A session ended and the broker may have published its Last Will: what follows
        must sort after it."""
        self._write(self._pass_will)

    def disarm_will(self) -> None:
        """A clean shutdown said `stopped`: no Last Will was sent, the next start need not
        skip over it."""
        self._write(lambda: self._db.execute("DELETE FROM counters WHERE name = 'will_seq'"))

    @property
    def last_seq(self) -> int:
        return self.counter("seq")

    def next_envelope(self) -> Envelope:
        """A fresh envelope for a message that is sent directly (session state, not queued)."""
        return self._write(lambda: Envelope.new(self._next_seq()))

    def bd_seq(self) -> int:
        """Sparkplug bdSeq, 0..255, for the Last Will of the next CONNECT. It stays the same
        until a session is accepted (`advance_bd_seq`), so attempts that never get one (broker
        down, refused) do not skip numbers."""
        with self._lock:
            return self._counter("bd_seq") % 256

    def advance_bd_seq(self) -> None:
        """The broker accepted a session with the current bdSeq: the next CONNECT takes the
        next one. Committed (and in the state file) before that session's NBIRTH, so no later
        session, in this process or the next, births with the same bdSeq."""

        def body() -> None:
            self._state["bd_seq"] = self._bump("bd_seq")
            self._write_state()

        self._write(body)

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

        def body() -> tuple[Envelope | None, int]:
            env = Envelope.new(self._next_seq()) if with_envelope else None
            payload = build(env)
            if latest:
                self._db.execute("DELETE FROM messages WHERE topic = ? AND latest = 1", (topic,))
            self._db.execute(
                "INSERT INTO messages(topic, payload, qos, retain, latest, kind, msg_id, seq,"
                " correlation, created, size) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    topic,
                    payload,
                    qos,
                    int(retain),
                    int(latest),
                    kind,
                    env.msg_id if env else None,
                    env.seq if env else None,
                    correlation,
                    time.time(),
                    len(payload) + len(topic),
                ),
            )
            return env, self._enforce_bounds()

        env, dropped = self._write(body)
        if dropped:
            log.warning(
                "outbox bound reached, oldest messages dropped",
                dropped=dropped,
                total_dropped=self.counter("dropped"),
            )
        return env

    def _enforce_bounds(self) -> int:
        """Drop by age, then by count and bytes; non-retained first. Returns rows dropped.
        In memory the bounds are MEMORY_MAX_MESSAGES and MEMORY_MAX_BYTES at most."""
        limits = self.limits
        if self.fault is not None:
            limits = replace(
                limits,
                max_messages=min(limits.max_messages, MEMORY_MAX_MESSAGES),
                max_bytes=min(limits.max_bytes, MEMORY_MAX_BYTES),
            )
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
        where = "id > ?"
        args: list[int | str] = [after_id]
        if kinds is not None:
            where += f" AND kind IN ({', '.join('?' * len(kinds))})"
            args.extend(kinds)
        return self._rows(f"{where} ORDER BY id LIMIT ?", (*args, limit))

    def row(self, row_id: int) -> Row | None:
        """One pending row, if it is still there."""
        rows = self._rows("id = ?", (row_id,))
        return rows[0] if rows else None

    def _rows(self, condition: str, args: tuple) -> list[Row]:
        with self._lock:
            rows = self._db.execute(
                "SELECT id, topic, payload, qos, retain, kind, msg_id, seq, correlation, created "
                f"FROM messages WHERE {condition}",
                args,
            ).fetchall()
        return [_to_row(r) for r in rows]

    def ack(self, row_ids: list[int]) -> None:
        """The broker has these messages: forget them (one transaction)."""
        self._write(
            lambda: self._db.executemany(
                "DELETE FROM messages WHERE id = ?", [(i,) for i in row_ids]
            )
        )

    def reject(self, row_id: int) -> None:
        """The broker refused the message for good (e.g. ACL): forget it, but count it."""

        def body() -> None:
            self._db.execute("DELETE FROM messages WHERE id = ?", (row_id,))
            self._bump("rejected")

        self._write(body)

    def dead_letter(self, row_id: int, reason: str) -> None:
        """This row can never be published: move it to `dead_letter`, count it, keep the
        newest DEAD_LETTER_KEEP there."""

        def body() -> None:
            moved = self._db.execute(
                "INSERT INTO dead_letter(id, topic, payload, qos, retain, kind, msg_id, seq,"
                " correlation, created, reason, dead_at) SELECT id, topic, payload, qos, retain,"
                " kind, msg_id, seq, correlation, created, ?, ? FROM messages WHERE id = ?",
                (reason, time.time(), row_id),
            ).rowcount
            self._db.execute("DELETE FROM messages WHERE id = ?", (row_id,))
            self._db.execute(
                "DELETE FROM dead_letter WHERE id NOT IN"
                " (SELECT id FROM dead_letter ORDER BY id DESC LIMIT ?)",
                (DEAD_LETTER_KEEP,),
            )
            if moved:
                self._bump("dead_lettered")

        self._write(body)

    def dead_letters(self) -> list[tuple[Row, str]]:
        """The dead letters kept, oldest first, with the reason of each."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id, topic, payload, qos, retain, kind, msg_id, seq, correlation, created,"
                " reason FROM dead_letter ORDER BY id"
            ).fetchall()
        return [(_to_row(r), r[10]) for r in rows]

    def discard_kind(self, kind: str) -> None:
        """Forget pending messages of a kind that is no longer sent (not counted as drops)."""
        self._write(lambda: self._db.execute("DELETE FROM messages WHERE kind = ?", (kind,)))

    def size(self, kinds: tuple[str, ...] | None = None) -> tuple[int, int]:
        """(pending messages, pending bytes), of the given kinds."""
        where = ""
        args: tuple[str, ...] = ()
        if kinds is not None:
            where, args = f" WHERE kind IN ({', '.join('?' * len(kinds))})", kinds
        with self._lock:
            count, size = self._db.execute(
                f"SELECT COUNT(*), COALESCE(SUM(size), 0) FROM messages{where}", args
            ).fetchone()
        return int(count), int(size)
