"""One capture through the scan path: what `silo-agent scan` and the daemon's pipeline share.

capture -> the raw scan into the audit cache (kept even if processing fails) -> reconstruct and
detect, pile ids carried over -> the summary -> result.json, the height map and the inputs
next to the scan. A full disk evicts the oldest unprotected scans and retries once, then the
scan goes on uncached (`cache_full`, which the daemon's `cache` alarm reports). The caller
times and checks each stage through `Stages` (the daemon abandons a scan there) and decides
what a scan without a result means (a failure report; an exit status).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import structlog

from silo_agent.analysis.scan_analysis import ScanAnalysis
from silo_agent.analysis.summary import ScanSummary
from silo_agent.capture import CaptureResult, capture_all
from silo_agent.config import Config
from silo_agent.detect import Pile
from silo_agent.scan import Scan, ScanError
from silo_agent.service.scan_path import (
    CONFIG_KEY,
    analyse_with,
    keep_result,
    new_scan,
    no_result_summary,
    previous_piles,
    settings_of,
    summary_of,
)
from silo_agent.storage.audit import AuditCache, is_disk_full

log = structlog.get_logger(__name__)


@dataclass
class Stages:
    """The scan's stage timings (`<stage>_s`, seconds) and the caller's hooks: `timed(stage,
    seconds)` at each stage's end (metrics), `captured(capture)` once the cameras are done,
    and `check()` between stages (the daemon raises there to abandon the scan)."""

    timed: Callable[[str, float], None] = lambda _stage, _seconds: None
    captured: Callable[[CaptureResult], None] = lambda _capture: None
    check: Callable[[], None] = lambda: None
    timings: dict[str, float] = field(default_factory=dict)
    _since: float = field(default_factory=time.perf_counter)

    def lap(self, stage: str) -> None:
        """`stage` ends now; the next one starts."""
        now = time.perf_counter()
        self.timings[f"{stage}_s"] = now - self._since
        self._since = now
        self.timed(stage, self.timings[f"{stage}_s"])


@dataclass
class ScanRun:
    """What one capture made. `analysed` is None when the scan has no result; then `summary`
    says why (its `invalid_reason`) and `error` is the exception processing raised, if any."""

    scan_id: str
    capture: CaptureResult
    summary: ScanSummary
    scan: Scan | None = None
    directory: Path | None = None  # None: not kept in the cache (see write_error)
    write_error: str | None = None  # why the scan or its result was not kept: path, OS error
    cache_full: bool = False  # some of the scan or its result could not be kept
    analysed: ScanAnalysis | None = None
    previous: list[Pile] = field(default_factory=list)
    error: Exception | None = None


def scan_once(
    config: Config,
    cache: AuditCache,
    scan_id: str,
    started: datetime,
    stages: Stages,
    protected: Callable[[], set[str]] = set,
    scan_number: int = 0,
) -> ScanRun:
    """Capture, keep, process, summarise and keep the result of one scan. `protected` names
    the scans a full disk must not evict (the collapse baseline). Raises only what the
    `stages` hooks raise."""
    captured_at = f"{started:%Y-%m-%dT%H:%M:%SZ}"
    capture = capture_all(config, scan_number)
    stages.lap("capture")
    stages.captured(capture)
    stages.check()

    def without_result(
        reason: str,
        scan: Scan | None = None,
        directory: Path | None = None,
        write_error: str | None = None,
        error: Exception | None = None,
    ) -> ScanRun:
        summary = no_result_summary(
            config, scan_id, captured_at, reason, capture.failures, stages.timings
        )
        cache_full = scan is not None and directory is None
        return ScanRun(
            scan_id, capture, summary, scan, directory, write_error, cache_full, error=error
        )

    if not capture.clouds:
        return without_result("capture: no camera delivered a cloud")
    scan = new_scan(config, scan_id, started, capture.clouds, capture.failures)
    directory, write_error = _write(cache, scan, protected)
    stages.lap("audit")
    stages.check()

    previous = previous_piles(cache, scan_id)
    try:
        analysed = analyse_with(scan, settings_of(scan), previous)
    except Exception as exc:  # a bug or a bad model: the caller reports it
        return without_result(f"processing: {exc}", scan, directory, write_error, exc)
    stages.lap("reconstruct")
    stages.check()
    summary = summary_of(analysed, scan, stages.timings)
    cache_full = directory is None
    if directory is not None:  # kept before the alarms, so losing it raises `cache`
        write_error = _keep_result(cache, directory, summary, analysed, previous, protected)
        cache_full = write_error is not None
    return ScanRun(
        scan_id,
        capture,
        summary,
        scan,
        directory,
        write_error,
        cache_full,
        analysed,
        previous,
    )


def _write(
    cache: AuditCache, scan: Scan, protected: Callable[[], set[str]]
) -> tuple[Path | None, str | None]:
    """The raw scan into the cache: (its directory, None), or (None, why not: one line naming
    the scan's directory and the OS error). On a full disk evict and retry once."""
    snapshot = scan.extra[CONFIG_KEY]
    target = cache.directory / scan.scan_id
    for attempt in range(2):
        try:
            return cache.write_scan(scan, snapshot), None
        except OSError as exc:
            error = f"{target}: cannot write the scan: {exc.strerror or exc}"
            if not is_disk_full(exc):
                log.error(
                    "cannot write the scan to the audit cache", scan_id=scan.scan_id, error=str(exc)
                )
                return None, error
            if attempt == 0:
                removed = cache.evict_for_space(protected())
                log.warning("disk full, evicted scans", removed=removed)
        except ScanError as exc:
            log.error("cannot write the scan", scan_id=scan.scan_id, error=str(exc))
            return None, str(exc)
    log.error("disk still full, scan published uncached", scan_id=scan.scan_id)
    return None, error


def _keep_result(
    cache: AuditCache,
    directory: Path,
    summary: ScanSummary,
    result: ScanAnalysis,
    previous: list[Pile],
    protected: Callable[[], set[str]],
) -> str | None:
    """result.json, the height map and inputs.json into the scan's directory; on a full disk
    evict older scans and retry once. None once kept, else why not (one line naming the scan's
    directory and the OS error)."""
    try:
        keep_result(directory, summary, result, previous)
        return None
    except OSError as exc:
        error = exc
    if is_disk_full(error):
        removed = cache.evict_for_space(protected() | {directory.name})
        log.warning("disk full, evicted scans", removed=removed)
        try:
            keep_result(directory, summary, result, previous)
            return None
        except OSError as exc:
            error = exc
    log.error("cannot keep the result with the scan", scan_id=directory.name, error=str(error))
    return f"{directory}: cannot keep the result with the scan: {error.strerror or error}"
