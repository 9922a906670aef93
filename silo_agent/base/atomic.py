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


def _copy_access(source: Path, target: str) -> None:
    """Give `target` the permission bits, owner and group of `source`: a config installed
    root:silo-agent 0640 and rewritten by root came back root:root, and the service could no
    longer read it. Where the owner cannot be given (not root), the group must be, or the
    write is refused (OSError) and the file left as it was."""
    shutil.copymode(source, target)
    old = os.stat(source)
    new = os.stat(target)
    if (new.st_uid, new.st_gid) == (old.st_uid, old.st_gid):
        return
    try:
        os.chown(target, old.st_uid, old.st_gid)
    except PermissionError:
        if new.st_gid != old.st_gid:
            os.chown(target, -1, old.st_gid)  # PermissionError: not in its group, refused


@contextmanager
def atomic_writer(path: Path, *, keep_access: bool = False) -> Iterator[BinaryIO]:
    """A binary handle whose content replaces (or creates) the file `path` when the block
    ends, and leaves no trace if it raises. `keep_access`: the new file keeps the old one's
    permission bits, owner and group (a config file an operator restricted to the service's
    group); a new file is the writer's (0600)."""
    fd, staging = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        if keep_access:
            _copy_access(path, staging)
        os.replace(staging, path)
        fsync_directory(path.parent)
    except BaseException:
        Path(staging).unlink(missing_ok=True)
        raise


def write_atomic(path: Path, data: bytes, *, keep_access: bool = False) -> None:
    """Replace (or create) the file `path` with `data` (`atomic_writer`)."""
    with atomic_writer(path, keep_access=keep_access) as handle:
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
