"""Durable, all-or-nothing writes: a file or directory is either absent (or the old one) or
complete, even across a power cut. The one home of the fsync-rename-fsync sequence: the data
is fsynced before the rename, and the parent directory after it, or the rename itself may be
lost."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


def fsync_directory(directory: Path) -> None:
    """Make the entries of `directory` (a rename into it) durable."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_writer(path: Path, *, keep_mode: bool = False) -> Iterator[BinaryIO]:
    """A binary handle whose content replaces (or creates) the file `path` when the block
    ends, and leaves no trace if it raises. `keep_mode`: the new file keeps the old one's
    permission bits (a config file an operator restricted); a new file is the owner's (0600)."""
    fd, staging = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        if keep_mode:
            shutil.copymode(path, staging)
        os.replace(staging, path)
        fsync_directory(path.parent)
    except BaseException:
        Path(staging).unlink(missing_ok=True)
        raise


def write_atomic(path: Path, data: bytes, *, keep_mode: bool = False) -> None:
    """Replace (or create) the file `path` with `data` (`atomic_writer`)."""
    with atomic_writer(path, keep_mode=keep_mode) as handle:
        handle.write(data)


def publish_directory(staging: Path, target: Path) -> None:
    """Rename the filled `staging` directory to `target` (same parent, `target` absent) once
    every file in it is durable; `staging` is removed if that fails."""
    try:
        for item in staging.iterdir():
            with open(item, "rb") as handle:
                os.fsync(handle.fileno())
        os.rename(staging, target)
        fsync_directory(target.parent)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
