"""One agent per state: an exclusive lock on a file beside the outbox and one in the audit
directory, held while `run` runs. Two agents on one outbox would take over each other's MQTT
client id in turn (each takeover an `offline` Last Will and a jump of `seq`); two on one
audit cache would evict each other's scans and overwrite the alarm state."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from silo_agent.config import Config

AUDIT_LOCK = ".silo-agent.lock"  # in audit.directory; not a scan, retention never touches it


class StateLocked(Exception):
    """Another agent holds the lock (or it cannot be taken); the message says which."""


class StateLock:
    """flock(2) locks: released by the kernel when the process ends, however it ends."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths
        self._fds: list[int] = []

    @classmethod
    def of(cls, config: Config) -> StateLock:
        outbox = config.mqtt.outbox_path
        return cls(
            [outbox.with_name(outbox.name + ".lock"), Path(config.audit.directory) / AUDIT_LOCK]
        )

    def acquire(self) -> None:
        """Take every lock, or none: StateLocked names the agent that has one."""
        try:
            for path in self.paths:
                self._fds.append(self._take(path))
        except StateLocked:
            self.release()
            raise

    def _take(self, path: Path) -> int:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise StateLocked(f"cannot create the lock file {path}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise StateLocked(
                f"another silo-agent (pid {holder}) is running on {path.parent} "
                f"(it holds {path.name}): one agent per outbox and audit directory"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return fd

    def release(self) -> None:
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds.clear()
