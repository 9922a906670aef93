"""What the page and the report read from the audit cache, memoised so a page left open costs
a directory listing per refresh, not a pass over every scan.

A scan is looked up only among the ids the cache lists (`AuditCache.entries`: this silo's scan
directories), so no URL can name a file outside the cache. A scan's picture needs its height
map and each camera's footprint (the cells its points fell in), read once from the scan's own
files and kept for the few most recent scans asked for.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from silo_agent.config import Config
from silo_agent.grid.geometry import gravity_angle_deg
from silo_agent.grid.heightmap import HeightMap
from silo_agent.scan import MANIFEST, CameraCloud, ScanError, gravity_of, read_scan
from silo_agent.storage.audit import RESULT, AuditCache, read_heightmap

KEPT_VIEWS = 4  # scans whose layers stay in memory: the latest and a few an operator opened
HISTORY_RANGES = {"day": timedelta(days=1), "week": timedelta(days=7), "all": None}


class ScanNotFound(LookupError):
    """No scan of this silo by that id in the audit cache."""


@dataclass(frozen=True)
class ScanRecord:
    """One row of the scan list and one point of the history."""

    scan_id: str
    captured_at: datetime
    volume_m3: float | None
    mass_t: float | None
    valid: bool
    degraded: bool
    has_result: bool

    def to_json(self) -> dict[str, Any]:
        return {
            "scan_id": self.scan_id,
            "captured_at": f"{self.captured_at:%Y-%m-%dT%H:%M:%SZ}",
            "volume_m3": self.volume_m3,
            "mass_t": self.mass_t,
            "valid": self.valid,
            "degraded": self.degraded,
            "has_result": self.has_result,
        }


@dataclass(frozen=True)
class CameraView:
    """One camera of a scan as the picture and the report show it."""

    serial: str
    position: tuple[float, float, float]  # silo frame, metres
    points: int
    footprint: np.ndarray  # bool, the height map's shape: cells its points fell in
    coverage: float  # share of the region's area it observed
    gravity_deg: float | None  # IMU gravity vs the vertical its extrinsic claims (drift)


@dataclass(frozen=True)
class ScanView:
    """Everything the picture, the page and the report say about one scan."""

    scan_id: str
    captured_at: str
    directory: Path
    summary: dict[str, Any]  # the result as published on P/scan (result.json) or processed now
    heightmap: HeightMap | None
    region: np.ndarray  # (V, 2) silo-frame polygon: the walls
    floor_z: float
    cameras: list[CameraView]
    config: dict[str, Any]  # the config snapshot the scan was taken with, else its scan.json site
    kept: bool  # the result is the one the agent kept (published), not processed here

    @property
    def published(self) -> dict[str, Any]:
        """`P/volume`'s fields for this result, built by the publisher's own code."""
        return published_volume(self.summary)


def published_volume(summary: dict[str, Any]) -> dict[str, Any]:
    """What `P/volume` carries for a result summary, without the envelope (msg_id, seq, ts)."""
    from silo_agent.analysis.summary import ScanSummary
    from silo_agent.telemetry.payloads import Envelope, volume_payload

    typed = ScanSummary.from_json(summary)
    payload = volume_payload(Envelope.new(1), typed).model_dump(mode="json", by_alias=True)
    return {k: v for k, v in payload.items() if k not in ("msg_id", "seq", "ts")}


def footprint(camera: CameraCloud, hm: HeightMap) -> np.ndarray:
    """Cells of the map that hold at least one of the camera's points (silo frame)."""
    points = camera.points_in_silo()
    rows, cols = hm.shape
    col = np.floor((points[:, 0] - hm.origin[0]) / hm.step).astype(np.int64)
    row = np.floor((points[:, 1] - hm.origin[1]) / hm.step).astype(np.int64)
    keep = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    mask = np.zeros(rows * cols, dtype=bool)
    mask[row[keep] * cols + col[keep]] = True
    return mask.reshape(rows, cols)


def camera_views(cameras: list[CameraCloud], hm: HeightMap | None) -> list[CameraView]:
    out = []
    area = float(np.sum(hm.inside)) if hm is not None else 0.0
    for camera in cameras:
        if hm is not None:
            cells = footprint(camera, hm)
            covered = float(np.sum(hm.inside[cells])) / area if area > 0 else 0.0
        else:
            cells, covered = np.zeros((0, 0), dtype=bool), 0.0
        gravity = gravity_of(camera)
        angle = None if gravity is None else gravity_angle_deg(gravity, camera.extrinsic)
        x, y, z = (float(v) for v in camera.extrinsic[:3, 3])
        out.append(CameraView(camera.serial, (x, y, z), len(camera.points), cells, covered, angle))
    return out


def load_scan_view(directory: Path, config: Config | None = None) -> ScanView:
    """A scan directory as the page and the report show it: the kept result and height map
    when the agent kept them, else the scan processed now as `process` would (with `config`'s
    settings if given). Raises ScanError for a bad directory or a damaged kept result."""
    from silo_agent.service.scan_path import config_snapshot, process_directory, read_result

    directory = Path(directory)
    scan = read_scan(directory)
    snapshot = config_snapshot(scan, str(directory / MANIFEST))
    summary = read_result(directory) if config is None else None
    kept = summary is not None
    if summary is not None:
        heightmap = read_heightmap(directory)
    else:
        scan, result, processed = process_directory(directory, config)
        summary = processed.to_json()  # as result.json holds it
        heightmap = result.reconstruction.heightmap
    return ScanView(
        scan_id=scan.scan_id,
        captured_at=str(summary.get("captured_at") or scan.captured_at),
        directory=directory,
        summary=summary,
        heightmap=heightmap,
        region=np.asarray(scan.site.region, dtype=float),
        floor_z=float(scan.site.floor_z),
        cameras=camera_views(scan.cameras, heightmap),
        # a scan without a snapshot (simulated, or written by hand) still says its site
        config=dict(snapshot)
        or {"silo": scan.site.to_json(), "reconstruction": scan.reconstruction},
        kept=kept,
    )


def _kept_result(directory: Path) -> dict[str, Any] | None:
    """The result kept with a scan as every output reads it (`read_result`: checked as its
    payloads are; a NaN volume had made the scan list a 500); None without one, or damaged
    (logged, naming the file: the page lists the scan without a result)."""
    from silo_agent.service.scan_path import read_result

    try:
        return read_result(directory)
    except ScanError as exc:
        import structlog

        structlog.get_logger(__name__).warning("damaged scan result", error=str(exc))
        return None


class Archive:
    """The audit cache as the page reads it; safe to call from the server's threads."""

    def __init__(self, cache: AuditCache) -> None:
        self.cache = cache
        self._lock = threading.Lock()
        self._names: set[str] | None = None
        self._records: list[ScanRecord] = []  # oldest first
        self._positions: dict[str, int] = {}  # scan id -> its index in `_records`
        self._views: OrderedDict[str, ScanView] = OrderedDict()
        self._damaged: set[str] = set()  # scans whose kept result did not read

    def records(self) -> list[ScanRecord]:
        """This silo's cached scans, oldest first."""
        with self._lock:
            self._refresh()
            return list(self._records)

    def page(self, limit: int, before: str | None = None) -> tuple[list[ScanRecord], bool]:
        """Up to `limit` scans, newest first, from the newest or, with `before`, from the scan
        just older than that one; and whether older scans remain. A scan id and not a position
        marks where a page starts, so scans that arrive meanwhile shift nothing: the next page
        neither repeats nor skips a scan. ScanNotFound for a `before` not listed (removed by
        retention since)."""
        with self._lock:
            self._refresh()
            end = len(self._records) if before is None else self._positions.get(before)
            if end is None:
                raise ScanNotFound(before)
            start = max(0, end - limit)
            return self._records[start:end][::-1], start > 0

    def _refresh(self) -> None:
        """Bring the list up to date (hold the lock). The manifests are read again only when
        the directory's entries change; a scan still waiting for its result is looked at
        again."""
        names = self.cache.names()
        if names != self._names:
            old = {r.scan_id: r for r in self._records}
            self._records = [
                old.get(e.scan_id) or self._record(e.path, e.captured_at)
                for e in self.cache.entries()
            ]
            self._positions = {r.scan_id: k for k, r in enumerate(self._records)}
            self._names = names
        for k, record in enumerate(self._records):
            if record.has_result or record.scan_id in self._damaged:
                continue
            kept = self.cache.directory / record.scan_id / RESULT
            if kept.is_file():
                self._records[k] = again = self._record(kept.parent, record.captured_at)
                if not again.has_result:  # read once, logged once: not at every poll
                    self._damaged.add(record.scan_id)

    @staticmethod
    def _record(path: Path, captured_at: datetime) -> ScanRecord:
        summary = _kept_result(path)
        if summary is None:
            return ScanRecord(path.name, captured_at, None, None, False, False, False)
        return ScanRecord(
            path.name,
            captured_at,
            _number(summary.get("volume_m3")),
            _number(summary.get("mass_t")),
            summary.get("valid") is True,
            summary.get("degraded") is True,
            True,
        )

    def directory(self, scan_id: str) -> Path:
        """The directory of a listed scan; ScanNotFound for any other name."""
        with self._lock:
            self._refresh()
            if scan_id not in self._positions:
                raise ScanNotFound(scan_id)
        return self.cache.directory / scan_id

    def latest(self) -> ScanRecord | None:
        """The newest scan with a result: the one `P/volume` speaks of."""
        return next((r for r in reversed(self.records()) if r.has_result), None)

    def summary(self, scan_id: str) -> dict[str, Any]:
        summary = _kept_result(self.directory(scan_id))
        if summary is None:
            raise ScanNotFound(f"{scan_id} has no result")
        return summary

    def view(self, scan_id: str) -> ScanView:
        """One scan's layers and cameras, kept for the few scans last asked for."""
        directory = self.directory(scan_id)
        with self._lock:
            if scan_id in self._views:
                self._views.move_to_end(scan_id)
                return self._views[scan_id]
        if not (directory / MANIFEST).is_file() or not (directory / RESULT).is_file():
            raise ScanNotFound(f"{scan_id} has no result")
        try:
            view = load_scan_view(directory)
        except ScanError as exc:
            raise ScanNotFound(f"{scan_id}: {exc}") from None
        with self._lock:
            self._views[scan_id] = view
            while len(self._views) > KEPT_VIEWS:
                self._views.popitem(last=False)
        return view

    def history(self, span: str, now: datetime | None = None) -> list[ScanRecord]:
        """Scans with a volume within `span` (day, week, all) before `now`."""
        window = HISTORY_RANGES[span]
        since = None if window is None else (now or datetime.now(UTC)) - window
        return [
            r
            for r in self.records()
            if r.volume_m3 is not None and (since is None or r.captured_at >= since)
        ]


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None
