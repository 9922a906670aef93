"""The audit cache: every scan kept as a silo-scan/1 directory, bounded, replayable.

A scan directory is written atomically (staging directory, fsync, rename, fsync of the parent)
before it is processed, so a raw capture survives a crash in processing. It carries the config
snapshot it was taken with, the software version and the SHA-256 of each cloud; the published
result (`result.json`), the height map (`heightmap.npz`) and what processing needed besides the
scan (`inputs.json`: the previous piles that gave pile ids) are added atomically afterwards.
`replay` processes a cached scan again with its own settings and compares with what was
published. Retention removes the oldest scans first, never one an alarm baseline refers to,
and only this silo's own scans: directories named like its scan ids (`<silo>-<UTC time>[-k]`,
and the calibration scans `calibrate --capture` keeps) whose scan.json names this silo.
Anything else in `audit.directory` (another silo's scans, `.git`, a note) is never touched.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import re
import shutil
import tarfile
import tempfile
import time
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from silo_agent import __version__
from silo_agent.base.atomic import atomic_writer, publish_directory, write_atomic
from silo_agent.base.limits import MAX_MANIFEST_BYTES
from silo_agent.config import AuditConfig
from silo_agent.grid.heightmap import HeightMap
from silo_agent.scan import MANIFEST, Scan, ScanError, json_object, manifest_of, write_ply

log = structlog.get_logger(__name__)

RESULT = "result.json"
HEIGHTMAP = "heightmap.npz"
INPUTS = "inputs.json"
HEIGHTMAP_KEYS = ("origin", "step", "heights", "observed", "inside")  # heightmap.npz's arrays
UNREPRODUCIBLE = ("timings", "timings_s")  # wall-clock durations: differ on every run
FRESH_NS = 2_000_000_000  # `entries` keeps no directory changed this recently (FAT's 2 s mtime)


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def dump_json(data: Any) -> bytes:
    return (json.dumps(data, allow_nan=False, indent=2) + "\n").encode()


@dataclass(frozen=True)
class Entry:
    """One cached scan."""

    scan_id: str
    path: Path
    captured_at: datetime
    bytes: int


def _tree_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def scan_id_pattern(silo_id: str) -> re.Pattern[str]:
    """Names of the scan directories silo `silo_id` writes (pipeline.new_scan_id, calibrate)."""
    return re.compile(rf"{re.escape(silo_id)}-\d{{8}}T\d{{6}}Z(-\d+)?(-calibration(-\d+of\d+)?)?")


class AuditCache:
    """This silo's scan directories under `audit.directory`, bounded by `max_bytes` and
    `max_age_days`."""

    def __init__(self, cfg: AuditConfig, silo_id: str) -> None:
        self.cfg = cfg
        self.directory = Path(cfg.directory)
        self.silo_id = silo_id
        self._ours = scan_id_pattern(silo_id)
        # name -> (the directory's mtime when read, its entry; None: not this silo's scan)
        self._read: dict[str, tuple[int, Entry | None]] = {}

    # ------------------------------------------------------------ writing

    def write_scan(self, scan: Scan, config_snapshot: dict[str, Any]) -> Path:
        """Write the raw scan atomically with its config snapshot, version and cloud hashes.

        Raises OSError (ENOSPC on a full disk) with nothing left behind."""
        self.directory.mkdir(parents=True, exist_ok=True)
        target = self.directory / scan.scan_id
        if target.exists():
            raise ScanError(f"{target}: already exists; scans are never overwritten")
        staging = Path(tempfile.mkdtemp(prefix=f".{scan.scan_id}.", dir=self.directory))
        try:
            hashes = {}
            for camera in scan.cameras:
                path = staging / f"{camera.serial}.ply"
                write_ply(path, camera.points, camera.colors)
                hashes[camera.serial] = sha256_of(path)
            manifest = manifest_of(scan)
            for entry in manifest["cameras"]:
                entry["cloud_sha256"] = hashes[entry["serial"]]
            config_text = json.dumps(config_snapshot, sort_keys=True, separators=(",", ":"))
            manifest["software_version"] = __version__
            manifest["config"] = config_snapshot
            manifest["config_sha256"] = hashlib.sha256(config_text.encode()).hexdigest()
            (staging / MANIFEST).write_bytes(dump_json(manifest))
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        publish_directory(staging, target)
        return target

    @staticmethod
    def add_result(
        directory: Path,
        summary: dict[str, Any],
        heightmap: HeightMap | None,
        inputs: dict[str, Any],
    ) -> None:
        """Keep the published result, its height map and processing inputs with the scan."""
        write_atomic(directory / INPUTS, dump_json(inputs))
        if heightmap is not None:
            buffer = io.BytesIO()
            np.savez_compressed(
                buffer,
                origin=np.asarray(heightmap.origin),
                step=np.asarray(heightmap.step),
                heights=heightmap.heights,
                observed=heightmap.observed,
                inside=heightmap.inside,
            )
            write_atomic(directory / HEIGHTMAP, buffer.getvalue())
        write_atomic(directory / RESULT, dump_json(summary))

    # ------------------------------------------------------------ reading

    def entries(self) -> list[Entry]:
        """This silo's cached scans, oldest first: a directory named like its scan ids whose
        scan.json says this silo (staging directories, strays, other silos' are not).

        A directory is read again (its manifest, its files' sizes) only when its mtime moved:
        the agent replaces a scan's files, never edits them in place (`write_atomic` renames
        into the directory), so any change moves it; one stat a scan otherwise. Read every
        time, 8,000 scans of eight clouds took 7.1 s a call (now 0.04 s), and a scan makes two
        or three calls (retention, pile ids, the page); bench/results/cache.md. A directory
        changed within the last FRESH_NS is not kept (a file system that stamps times
        coarsely)."""
        if not self.directory.is_dir():
            return []
        known, kept, out = self._read, {}, []
        now = time.time_ns()
        with os.scandir(self.directory) as items:
            for item in items:
                if not self._ours.fullmatch(item.name) or not item.is_dir(follow_symlinks=False):
                    continue
                mtime = item.stat(follow_symlinks=False).st_mtime_ns
                cached = known.get(item.name)
                if cached is not None and cached[0] == mtime:
                    entry = cached[1]
                else:
                    entry = self._entry(Path(item.path))
                if now - mtime >= FRESH_NS:
                    kept[item.name] = (mtime, entry)
                if entry is not None:
                    out.append(entry)
        self._read = kept
        return sorted(out, key=lambda e: (e.captured_at, e.scan_id))

    def _entry(self, path: Path) -> Entry | None:
        """The entry of a scan directory; None if its manifest is not this silo's."""
        try:
            manifest = json.loads((path / MANIFEST).read_text(encoding="utf-8"))
            if manifest["silo_id"] != self.silo_id:
                return None
        except (OSError, ValueError, KeyError, TypeError, RecursionError):
            return None  # not a scan this agent can vouch for: never counted, never removed
        try:
            when = datetime.fromisoformat(manifest["captured_at"].replace("Z", "+00:00"))
        except (ValueError, KeyError, TypeError, AttributeError):
            when = datetime.fromtimestamp(path.stat().st_mtime, UTC)
        return Entry(path.name, path, when, _tree_bytes(path))

    def latest_result(self, *, valid: bool = False) -> dict[str, Any]:
        """The published result (`result.json`) of the newest cached scan that has one (with
        `valid`: the newest valid one, a volume); ValueError saying why when there is none or
        the newest cannot be read."""
        for entry in reversed(self.entries()):
            try:
                summary = read_kept(entry.path / RESULT)
            except ScanError as exc:
                raise ValueError(str(exc)) from None
            if summary is None:
                continue  # a scan that failed before a result: an older one may have one
            if valid and not (
                summary.get("valid") is True and summary.get("volume_m3") is not None
            ):
                continue
            return summary
        kind = "valid " if valid else ""
        raise ValueError(f"no scan in {self.directory} has a {kind}{RESULT}")

    def names(self) -> set[str]:
        """Names taken in the cache directory (cheap: no manifest read, no sizes)."""
        if not self.directory.is_dir():
            return set()
        return {p.name for p in self.directory.iterdir()}

    def find(self, scan_id: str) -> Path:
        path = self.directory / scan_id
        if "/" in scan_id or scan_id.startswith(".") or not (path / MANIFEST).is_file():
            raise ScanError(f"{scan_id}: no such scan in {self.directory}")
        return path

    def heightmap(self, scan_id: str) -> HeightMap | None:
        """The height map kept with a cached scan; None if the scan or the map is gone."""
        return read_heightmap(self.directory / scan_id)

    # ------------------------------------------------------------ retention

    def _remove(self, entry: Entry, why: str) -> None:
        shutil.rmtree(entry.path, ignore_errors=True)
        log.info("audit scan removed", scan_id=entry.scan_id, reason=why, bytes=entry.bytes)

    def enforce(self, protected: Iterable[str] = (), now: datetime | None = None) -> list[str]:
        """Remove scans past `max_age_days`, then oldest first while over `max_bytes`;
        `protected` scans (alarm baselines) stay. Returns the ids removed."""
        keep = set(protected)
        now = now or datetime.now(UTC)
        cutoff = now - timedelta(days=self.cfg.max_age_days)
        removed = []
        entries = self.entries()
        total = sum(e.bytes for e in entries)
        for entry in entries:
            if entry.scan_id in keep:
                continue
            if entry.captured_at < cutoff:
                why = "older than audit.max_age_days"
            elif total > self.cfg.max_bytes:
                why = "audit.max_bytes exceeded"
            else:
                continue
            self._remove(entry, why)
            total -= entry.bytes
            removed.append(entry.scan_id)
        self._clean_staging()
        return removed

    def evict_for_space(self, protected: Iterable[str] = (), share: float = 0.1) -> list[str]:
        """Disk full: remove the oldest `share` of the unprotected scans (at least one)."""
        keep = set(protected)
        candidates = [e for e in self.entries() if e.scan_id not in keep]
        count = max(1, int(len(candidates) * share)) if candidates else 0
        for entry in candidates[:count]:
            self._remove(entry, "disk full")
        self._clean_staging()
        return [e.scan_id for e in candidates[:count]]

    def _clean_staging(self) -> None:
        """This silo's staging directories left by a crash mid-write (`.<scan id>.<random>`
        of tempfile.mkdtemp in write_scan); other hidden entries are not ours."""
        if not self.directory.is_dir():
            return
        for path in self.directory.glob(".*.*"):
            scan_id = path.name[1:].rpartition(".")[0]
            if self._ours.fullmatch(scan_id) and path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
                log.info(
                    "audit staging directory removed",
                    path=str(path),
                    reason="left by an interrupted scan write",
                )

    # ------------------------------------------------------------ export

    def export(self, scan_id: str, out: Path) -> Path:
        """A .tar.gz of one scan directory, for a support ticket or another machine; written
        whole or not at all (`atomic_writer`: a missing directory or a full disk leaves no half
        archive), OSError saying why. An `out` that exists (the page's private temporary file)
        keeps its mode."""
        path = self.find(scan_id)
        if out.is_dir():  # refused before the archive is written, not at the rename
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(out))
        with (
            atomic_writer(out, keep_access=out.exists()) as handle,
            tarfile.open(fileobj=handle, mode="w:gz") as tar,
        ):
            tar.add(path, arcname=scan_id)
        return out


def read_kept(path: Path) -> dict[str, Any] | None:
    """A JSON object kept next to a scan (result.json, inputs.json: `add_result`); None when
    there is none, ScanError naming the file and what is wrong with it when it is damaged."""
    if not path.exists() and not path.is_symlink():
        return None
    return json_object(path, MAX_MANIFEST_BYTES)


def read_heightmap(directory: Path) -> HeightMap | None:
    """The height map kept in a scan directory (`add_result`); None if it is missing or
    unreadable."""
    try:
        return load_heightmap(directory / HEIGHTMAP)
    except ValueError:
        return None


def load_heightmap(path: Path) -> HeightMap:
    """A height map as `add_result` keeps it (numpy.savez of HEIGHTMAP_KEYS); ValueError
    naming the file and what is wrong with it."""
    problem = f"{path}: height map"
    expected = f"an .npz of {', '.join(HEIGHTMAP_KEYS)}"
    try:
        loaded = np.load(path)  # pickles refused
    except OSError as exc:
        raise ValueError(f"{problem}: cannot read it ({exc.strerror or exc})") from None
    except (EOFError, ValueError, zipfile.BadZipFile):  # empty, a pickle, a damaged zip
        raise ValueError(f"{problem}: not {expected}") from None
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise ValueError(f"{problem}: a single array, not {expected}")
    with loaded as data:
        missing = [key for key in HEIGHTMAP_KEYS if key not in data.files]
        if missing:
            raise ValueError(f"{problem}: no {', '.join(missing)} in it (not {expected})")
        try:
            origin, step = data["origin"], data["step"]
            heights, observed, inside = data["heights"], data["observed"], data["inside"]
        except (OSError, EOFError, ValueError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{problem}: unreadable ({exc})") from None
    arrays = {"origin": origin, "step": step, "heights": heights, "inside": inside}
    for name, values in {**arrays, "observed": observed}.items():
        if values.dtype.kind not in ("biuf" if name == "observed" else "iuf"):
            raise ValueError(f"{problem}: {name} holds {values.dtype}, not numbers")
    if origin.shape != (2,) or step.shape != () or not np.all(np.isfinite(origin)):
        raise ValueError(f"{problem}: origin must be 2 finite numbers and step one number")
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"{problem}: step must be a positive number, got {step}")
    if heights.ndim != 2 or observed.shape != heights.shape or inside.shape != heights.shape:
        raise ValueError(
            f"{problem}: heights must be 2-D and observed and inside of its shape, got "
            f"{heights.shape}, {observed.shape}, {inside.shape}"
        )
    return HeightMap(
        origin=(float(origin[0]), float(origin[1])),
        step=float(step),
        heights=heights,
        observed=observed.astype(bool),
        inside=inside,
    )


def is_disk_full(exc: OSError) -> bool:
    return exc.errno in (errno.ENOSPC, errno.EDQUOT)


# ---------------------------------------------------------------- replay


def comparable(summary: dict[str, Any]) -> dict[str, Any]:
    """The published result without what legitimately differs run to run (timings)."""
    return {k: v for k, v in summary.items() if k not in UNREPRODUCIBLE}


def differences(published: dict[str, Any], again: dict[str, Any], prefix: str = "") -> list[str]:
    """`key: published -> replayed` for every leaf that is not identical (floats bit for bit,
    compared through their shortest round-trip repr)."""
    out = []
    for key in sorted(set(published) | set(again)):
        a, b = published.get(key, "<absent>"), again.get(key, "<absent>")
        name = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += differences(a, b, name + ".")
        elif json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
            out.append(f"{name}: published {json.dumps(a)} -> replayed {json.dumps(b)}")
    return out
