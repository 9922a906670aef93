"""Durable writes have one home (silo_agent/base/atomic.py), and every writer gets all of it: the
data fsynced before the rename and the parent directory after it. The calibration's config
rewrite used to skip the directory, so the new config could vanish in a power cut."""

from __future__ import annotations

import ast
import os
import stat
from pathlib import Path

import numpy as np
import pytest

import silo_agent
from silo_agent.base.atomic import publish_directory, write_atomic
from silo_agent.calibrate import write_calibrated_config

ROOT = Path(silo_agent.__file__).parent
CONFIG = """\
[silo]
id = "sim"
region = [[-2, -2], [2, -2], [2, 2], [-2, 2]]

[[cameras]]
serial = "cam"   # the only camera
extrinsic = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
"""


@pytest.fixture
def synced_directories(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The inodes of the directories os.fsync is called on (the real fsync still runs)."""
    inodes: list[int] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            inodes.append(info.st_ino)
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return inodes


def test_config_rewrite_syncs_the_directory_and_keeps_the_mode(
    tmp_path: Path, synced_directories: list[int]
) -> None:
    path = tmp_path / "silo.toml"
    path.write_text(CONFIG)
    path.chmod(0o640)
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.2, 3.0]
    write_calibrated_config(path, {"cam": pose})
    assert tmp_path.stat().st_ino in synced_directories
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    assert "# the only camera" in path.read_text()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_config_rewrite_through_a_symlink_rewrites_its_target_and_keeps_the_link(
    tmp_path: Path,
) -> None:
    """A config kept elsewhere and linked (/etc/silo-agent.toml -> a deployment's file): the
    file it names takes the new extrinsics, the link stays a link."""
    target = tmp_path / "deploy" / "silo.toml"
    target.parent.mkdir()
    target.write_text(CONFIG)
    link = tmp_path / "silo.toml"
    link.symlink_to(target)
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.2, 3.0]
    backup = write_calibrated_config(link, {"cam": pose})
    assert link.is_symlink() and link.resolve() == target
    assert "[0, 1, 0, 0.2]" in target.read_text() and "# the only camera" in target.read_text()
    assert backup.parent == target.parent and backup.read_text() == CONFIG


def test_write_atomic_replaces_and_leaves_nothing_on_failure(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    write_atomic(path, b"one")
    write_atomic(path, b"two")
    assert path.read_bytes() == b"two"
    with pytest.raises(FileNotFoundError):
        write_atomic(tmp_path / "missing" / "x.json", b"three")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]


def test_publish_directory_syncs_the_parent(tmp_path: Path, synced_directories: list[int]) -> None:
    staging = tmp_path / ".staging"
    staging.mkdir()
    (staging / "a.ply").write_bytes(b"points")
    publish_directory(staging, tmp_path / "scan")
    assert (tmp_path / "scan" / "a.ply").read_bytes() == b"points" and not staging.exists()
    assert tmp_path.stat().st_ino in synced_directories


def test_only_atomic_py_syncs_to_disk() -> None:
    """Another os.fsync in silo_agent would be a second, possibly weaker, durable write."""
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Attribute)
                and node.attr in {"fsync", "fdatasync"}
                and isinstance(node.value, ast.Name)
                and node.value.id == "os"
            ):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert found and all(f.startswith("base/atomic.py:") for f in found), found
