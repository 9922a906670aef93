"""Real file system faults for the tests (they run as root): a small tmpfs that fills up, an
ext4 image the kernel forces read-only, a directory deleted under the agent. No mock of
SQLite or of the file system: the agent meets the errors the kernel gives."""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def tmpfs(directory: Path, size: str = "1m") -> Iterator[Path]:
    """A tmpfs of `size` mounted on `directory` (created) for the block."""
    directory.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)], check=True
    )
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], check=True)


def fill(directory: Path) -> Path:
    """Fill the file system of `directory` to the last block; the filler file's path."""
    filler = directory / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        for size in (65536, 4096, 512, 1):  # to the last partial block
            with contextlib.suppress(OSError):
                while os.write(fd, b"\0" * size):
                    pass
    finally:
        os.close(fd)
    return filler


def leave_inodes(disk: Path, free: int) -> None:
    """Take every inode of the tmpfs `disk` (mounted with nr_inodes) but `free` of them, with
    empty filler files."""
    fillers = []
    try:
        while True:
            fillers.append(disk / f"inode-{len(fillers)}")
            fillers[-1].touch()
    except OSError as exc:
        assert exc.errno == 28  # ENOSPC: out of inodes
        fillers.pop()
    for path in fillers[:free]:
        path.unlink()


@contextlib.contextmanager
def ext4(directory: Path, image: Path, size_mb: int = 16) -> Iterator[Path]:
    """An ext4 image loop-mounted on `directory` with errors=remount-ro, so that
    `force_read_only` turns it read-only under open files, as a failing disk does."""
    subprocess.run(["truncate", "-s", f"{size_mb}M", str(image)], check=True)
    subprocess.run(["mkfs.ext4", "-q", "-F", str(image)], check=True)
    directory.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        ["mount", "-o", "loop,errors=remount-ro", str(image), str(directory)], check=True
    )
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], check=True)


def force_read_only(directory: Path) -> None:
    """The kernel's own error path: ext4 records an error and remounts read-only (the
    `emergency_ro` state of a disk that failed); a remount would be refused while files are
    open for writing."""
    device = next(
        line.split()[0]
        for line in Path("/proc/mounts").read_text().splitlines()
        if line.split()[1] == str(directory)
    )
    name = os.path.basename(os.path.realpath(device))
    Path(f"/sys/fs/ext4/{name}/trigger_fs_error").write_text("silo-agent fault test\n")


def delete(directory: Path) -> None:
    """Remove the directory and everything in it, open files included. It may be gone already:
    a mended read-only disk is a fresh file system, where the directory exists again only once
    the agent has written there, and on a loaded machine the next case can come first (seen in
    CI: the outbox's directory missing when its `deleted` case began)."""
    if directory.exists():
        shutil.rmtree(directory)


def kill_thread(thread: threading.Thread, timeout: float = 20) -> None:
    """End a Python thread from outside, as an error nobody caught would: SystemExit raised
    in it at its next bytecode (CPython's PyThreadState_SetAsyncExc). Raised again while the
    thread lives: one that lands in a finaliser is ignored by Python."""
    assert thread.ident is not None
    for _ in range(int(timeout)):
        done = ctypes.pythonapi.PyThreadState_SetAsyncExc(
            ctypes.c_ulong(thread.ident), ctypes.py_object(SystemExit)
        )
        assert done == 1, f"no such thread: {thread.name}"
        thread.join(1.0)
        if not thread.is_alive():
            return
    raise AssertionError(f"thread {thread.name} would not die")
