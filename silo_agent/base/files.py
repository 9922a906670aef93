"""Files and directories a user named, whatever they turn out to be. Only a regular file is
read (a FIFO would block, a device such as /dev/zero never ends, a directory is no file), and
never more than a bound; a directory to write into is tried, not guessed. The callers say
which path and raise their own error (ScanError, ConfigError) with the problem given here."""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


class FileProblem(ValueError):
    """Why a file could not be read, without its path (the caller names it)."""


@contextmanager
def open_regular(path: Path) -> Iterator[BinaryIO]:
    """A binary handle on `path` if it is a regular file (through symlinks); FileProblem if
    it cannot be opened or is no regular file."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO: no wait for a writer
    except OSError as exc:
        raise FileProblem(f"cannot read: {exc.strerror or exc}") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):  # checked before fdopen, which refuses a directory unnamed
        os.close(fd)
        raise FileProblem("not a regular file" + (" (a directory)" if stat.S_ISDIR(mode) else ""))
    with os.fdopen(fd, "rb") as handle:
        yield handle


def read_regular(path: Path, limit: int) -> bytes:
    """The bytes of the regular file `path`, at most `limit` of them; FileProblem otherwise."""
    with open_regular(path) as handle:
        try:
            raw = handle.read(limit + 1)
        except OSError as exc:
            raise FileProblem(f"cannot read: {exc.strerror or exc}") from None
    if len(raw) > limit:
        raise FileProblem(f"larger than the limit of {limit:,} bytes")
    return raw


def missing_directories(directory: Path) -> list[Path]:
    """`directory` and those of its ancestors that do not exist yet, deepest first: what
    creating it makes (and what a command that made them removes again if it writes nothing)."""
    missing = []
    while not directory.exists() and directory != directory.parent:
        missing.append(directory)
        directory = directory.parent
    return missing


def writable_directory_problem(directory: Path) -> str | None:
    """Why the agent could not create and write `directory`, or None. The nearest existing
    ancestor must be a directory the agent can create entries in (tried, and undone: nothing
    is left behind, so a command that then writes nothing leaves no trace)."""
    try:
        missing = missing_directories(directory)
        existing = missing[-1].parent if missing else directory
        if not existing.is_dir():
            return f"{existing} is not a directory"
    except OSError as exc:  # a name the file system cannot hold (ENAMETOOLONG)
        return f"cannot use {directory}: {exc.strerror or exc}"
    try:
        tempfile.TemporaryDirectory(prefix=".silo-agent-check.", dir=existing).cleanup()
    except OSError as exc:
        return f"cannot create files in {existing}: {exc.strerror or exc}"
    return None
