"""One agent per state: an exclusive lock on the audit directory and on the outbox database,
held while `run` runs. Two agents on one outbox would take over each other's MQTT client id
in turn (each takeover an `offline` Last Will and a jump of `seq`); two on one audit cache
would evict each other's scans and overwrite the alarm state.

flock(2) on the directory and the database file themselves: no lock file to leave behind or
to take an inode of a full disk, and SQLite's own locks (fcntl byte ranges) are independent
of it. The kernel drops the locks when the process ends, however it ends."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from silo_agent.config import Config


class StateLocked(Exception):
    """Another agent holds the lock (or it cannot be taken); the message says which."""


def _holder(fd: int) -> str:
    """The pid holding a flock on the file open as `fd`, from /proc/locks ("unknown" if the
    kernel does not say)."""
    inode = os.fstat(fd).st_ino
    with contextlib.suppress(OSError):
        for line in Path("/proc/locks").read_text().splitlines():
            fields = line.split()
            if "FLOCK" in fields and len(fields) > 5 and fields[5].endswith(f":{inode}"):
                return fields[4]
    return "unknown"


class StateLock:
    def __init__(self, directory: Path, outbox: Path) -> None:
        self.targets = [directory, outbox]  # the directory first: refused before the outbox
        self._fds: list[int] = []

    @classmethod
    def of(cls, config: Config) -> StateLock:
        return cls(Path(config.audit.directory), config.mqtt.outbox_path)

    def acquire(self) -> None:
        """Take both locks, or none: StateLocked names the agent that has one."""
        try:
            for target in self.targets:
                self._fds.append(self._take(target))
        except StateLocked:
            self.release()
            raise

    def _take(self, target: Path) -> int:
        try:
            if target == self.targets[0]:
                target.mkdir(parents=True, exist_ok=True)
                fd = os.open(target, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                fd = os.open(target, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise StateLocked(f"cannot open {target} to lock it: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _holder(fd)
            os.close(fd)
            raise StateLocked(
                f"another silo-agent (pid {holder}) is running on {target}: "
                "one agent per outbox and audit directory"
            ) from None
        return fd

    def release(self) -> None:
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds.clear()
