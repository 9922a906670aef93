"""The one scan path shared by `scan`, `process`, `replay` and the daemon.

A scan carries the config snapshot it was taken with (`scan.json` key `config`, next to its
`reconstruction` settings and `site`), and the analysis arguments are always derived from the
scan itself (`settings_of`), so a later `replay` processes it exactly as it was processed when
it was published, `[calibration]` included. Every path builds its summary with `summary_of`
(`analysis.summary.ScanSummary`) and keeps it with `keep_result`, atomically, through the
audit cache.

`process` goes through here too, so structlog, the audit cache and the version lookup are
imported where they are used, not at the top: a one-off `process` never needs them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from pydantic import BaseModel, ValidationError

from silo_agent.config import (
    CalibrationConfig,
    ConfigError,
    DetectionConfig,
    ReconstructionConfig,
    describe_validation_error,
)
from silo_agent.scan import MANIFEST, Scan, ScanError, Site, read_scan

if TYPE_CHECKING:
    from silo_agent.analysis.scan_analysis import ScanAnalysis
    from silo_agent.analysis.summary import FailedCamera, ScanSummary
    from silo_agent.capture import CameraFailure
    from silo_agent.config import Config
    from silo_agent.detect import Pile
    from silo_agent.scan import CameraCloud
    from silo_agent.storage.audit import AuditCache

Model = TypeVar("Model", bound=BaseModel)

CONFIG_KEY = "config"  # scan.json: the config snapshot the scan was taken and processed with


@dataclass(frozen=True)
class AnalysisSettings:
    """Everything `analysis.analyse` is called with besides the scan and the previous piles."""

    settings: ReconstructionConfig
    detection: DetectionConfig
    site: Site
    calibration: CalibrationConfig


def new_scan_id(config: Config, started: datetime, taken: set[str]) -> str:
    """`<silo>-<UTC yyyymmddThhmmssZ>`, suffixed when that second already has a scan."""
    base = f"{config.silo.id}-{started:%Y%m%dT%H%M%SZ}"
    scan_id, k = base, 1
    while scan_id in taken:
        scan_id, k = f"{base}-{k}", k + 1
    return scan_id


def new_scan(
    config: Config,
    scan_id: str,
    started: datetime,
    clouds: list[CameraCloud],
    failures: list[CameraFailure],
) -> Scan:
    """A silo-scan/1 `Scan` of one capture, carrying the config snapshot it is processed with."""
    from silo_agent import __version__
    from silo_agent.reconstruct import site_from_config

    return Scan(
        scan_id=scan_id,
        captured_at=f"{started:%Y-%m-%dT%H:%M:%SZ}",
        silo_id=config.silo.id,
        site=site_from_config(config),
        cameras=clouds,
        reconstruction=config.reconstruction.model_dump(mode="json"),
        extra={
            "software_version": __version__,
            "degraded": bool(failures),
            "failures": [{"serial": f.serial, "error": f.error} for f in failures],
            CONFIG_KEY: config.model_dump(mode="json"),
        },
    )


def settings_of(scan: Scan, manifest: Path | None = None) -> AnalysisSettings:
    """The analysis arguments a scan was (or is to be) processed with: its reconstruction
    settings and site, the detection and calibration of its config snapshot (defaults for a
    scan without one, e.g. a simulated scan). `manifest`: the scan.json it was read from, which
    a ScanError names (else the scan id does)."""
    source = str(manifest) if manifest is not None else f"scan {scan.scan_id}"
    snapshot = config_snapshot(scan, source)
    settings = _validated(ReconstructionConfig, scan.reconstruction, f"{source}: reconstruction")
    detection = _validated(
        DetectionConfig, snapshot.get("detection") or {}, f"{source}: {CONFIG_KEY}.detection"
    )
    calibration = _validated(
        CalibrationConfig, snapshot.get("calibration") or {}, f"{source}: {CONFIG_KEY}.calibration"
    )
    return AnalysisSettings(settings, detection, scan.site, calibration)


def config_snapshot(scan: Scan, source: str) -> dict[str, Any]:
    """The config snapshot a scan carries ({} for a scan without one); ScanError naming
    `source` (its scan.json) when it is not a JSON object."""
    snapshot = scan.extra.get(CONFIG_KEY) or {}
    if not isinstance(snapshot, dict):
        raise ScanError(f"{source}: {CONFIG_KEY}: must be a JSON object, got {snapshot!r:.40}")
    return snapshot


def _validated(model: type[Model], data: dict[str, Any], source: str) -> Model:
    """`data` as `model`, without the keys it does not know: silo-scan/1 readers ignore keys
    they do not know (docs/scan-format.md), so a scan written by a newer agent still reads."""
    if isinstance(data, dict):
        data = {key: value for key, value in data.items() if key in model.model_fields}
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ScanError(describe_validation_error(exc, source).splitlines()[0]) from None


def overridden(
    analysis: AnalysisSettings,
    config: Config | None,
    grid_step_m: float | None = None,
    method: str | None = None,
) -> AnalysisSettings:
    """`process`: the scan's own analysis, then what `config` sets, then the flags (later wins)."""
    from silo_agent.reconstruct import site_from_config

    merged = analysis.settings.model_dump()
    if config is not None:
        merged.update(config.reconstruction.model_dump(exclude_unset=True))
        analysis = AnalysisSettings(
            analysis.settings, config.detection, site_from_config(config), config.calibration
        )
    if grid_step_m is not None:
        merged["grid_step_m"] = grid_step_m
    if method is not None:
        merged["method"] = method
    try:
        return replace(analysis, settings=ReconstructionConfig.model_validate(merged))
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, "reconstruction settings")) from None


def analyse_with(
    scan: Scan, analysis: AnalysisSettings, previous: list[Pile], release_points: bool = False
) -> ScanAnalysis:
    """Reconstruct and detect, as every path does it (`release_points`: `analysis.analyse`)."""
    from silo_agent.analysis.scan_analysis import analyse

    return analyse(
        scan,
        analysis.settings,
        analysis.detection,
        site=analysis.site,
        previous=previous,
        calibration=analysis.calibration,
        release_points=release_points,
    )


def failed_cameras(scan: Scan) -> list[FailedCamera]:
    """The cameras that failed during the scan's capture (its `failures`)."""
    from silo_agent.analysis.summary import FailedCamera

    return [FailedCamera(f["serial"], f["error"]) for f in scan.extra.get("failures") or []]


def summary_of(result: ScanAnalysis, scan: Scan, timings: dict[str, float]) -> ScanSummary:
    """`analysis.summary.summarise` of a scan's analysis, as every path publishes it."""
    from silo_agent.analysis.summary import summarise

    return summarise(result, scan.captured_at, failed_cameras(scan), timings)


def no_result_summary(
    config: Config,
    scan_id: str,
    captured_at: str,
    reason: str,
    failures: Sequence[CameraFailure],
    timings: dict[str, float],
) -> ScanSummary:
    """The summary of a scan that produced no result (`reason` says why)."""
    from silo_agent.analysis.summary import FailedCamera, NoResult, summarise

    outcome = NoResult(
        scan_id, config.reconstruction.method, config.reconstruction.grid_step_m, reason
    )
    failed = [FailedCamera(f.serial, f.error) for f in failures]
    return summarise(outcome, captured_at, failed, timings)


def previous_piles(cache: AuditCache, scan_id: str) -> list[Pile]:
    """Piles of the latest cached scan before `scan_id` with a result, so pile ids carry over;
    none when there is no readable one. Ids are `<silo>-<UTC time>`: they sort by time."""
    from silo_agent.storage.audit import RESULT, read_kept

    for entry in reversed(cache.entries()):
        if entry.scan_id >= scan_id:
            continue
        try:
            summary = read_kept(entry.path / RESULT)
            if summary is None:
                continue
            return piles_of(summary, "piles", entry.path / RESULT)
        except ScanError as exc:
            import structlog

            structlog.get_logger(__name__).warning(
                "no pile ids carried over", scan_id=entry.scan_id, error=str(exc)
            )
            return []
    return []


def piles_of(data: dict[str, Any], key: str, path: Path) -> list[Pile]:
    """The piles listed under `key` of a JSON object read from `path`; ScanError naming the
    file and the key when one is not a pile."""
    from silo_agent.detect import Pile

    try:
        return [Pile.from_json(p) for p in data.get(key) or []]
    except KeyError as exc:
        raise ScanError(f"{path}: {key}: a pile lacks {exc.args[0]!r}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise ScanError(f"{path}: {key}: not a list of piles ({exc})") from None


def checked_summary(data: dict[str, Any]) -> ScanSummary:
    """A result summary read back as every output reads it: one its payloads accept (built
    once here), so a bad value is refused before anything shows or queues it; ValueError
    naming the key."""
    from silo_agent.analysis.summary import ScanSummary
    from silo_agent.telemetry.payloads import check_summary

    summary = ScanSummary.from_json(data)
    check_summary(summary)
    return summary


def read_result(directory: Path) -> dict[str, Any] | None:
    """The published result kept with a scan (result.json), as kept, once `checked_summary`
    accepts it: the one reader of it for replay, report and `scans`. None when the scan has
    none; ScanError naming the file and the problem when it is damaged."""
    from silo_agent.storage.audit import RESULT, read_kept

    path = directory / RESULT
    data = read_kept(path)
    if data is not None:
        try:
            checked_summary(data)
        except ValueError as exc:
            raise ScanError(f"{path}: {exc}") from None
    return data


def keep_result(
    directory: Path, summary: ScanSummary, result: ScanAnalysis, previous: list[Pile]
) -> None:
    """The summary, height map and processing inputs next to the scan, each written atomically."""
    from silo_agent.storage.audit import AuditCache

    inputs = {"previous_piles": [p.to_json() for p in previous]}
    AuditCache.add_result(directory, summary.to_json(), result.reconstruction.heightmap, inputs)


def process_directory(
    directory: Path,
    config: Config | None = None,
    grid_step_m: float | None = None,
    method: str | None = None,
    release_points: bool = False,
) -> tuple[Scan, ScanAnalysis, ScanSummary]:
    """`silo-agent process` of one scan directory: (scan, result, summary); nothing written.

    With `release_points` the scan's clouds lose their points once the reconstruction has read
    them (`reconstruct.released`): the summary reads none of them, and the raw clouds would
    otherwise live through the reconstruction's peak (a 12 m bin, 8 full-resolution cameras,
    1 cm: 86 MB of 544).

    Raises ScanError for a bad directory, ConfigError for bad settings, ModelError for a bad
    detection model."""
    scan = read_scan(directory)
    analysis = overridden(settings_of(scan, directory / MANIFEST), config, grid_step_m, method)
    result = analyse_with(scan, analysis, [], release_points=release_points)
    return scan, result, summary_of(result, scan, {})


def replay(directory: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """(published, replayed) results of a cached scan, processed again exactly as it was
    processed: its own analysis arguments and the previous piles that gave pile ids. Raises
    ScanError naming the file for a bad scan, a damaged result.json or inputs.json."""
    from silo_agent.storage.audit import INPUTS, RESULT, read_kept

    scan = read_scan(directory)
    published = read_result(directory)
    if published is None:
        raise ScanError(f"{directory / RESULT}: the scan has no published result")
    previous = piles_of(read_kept(directory / INPUTS) or {}, "previous_piles", directory / INPUTS)
    result = analyse_with(scan, settings_of(scan, directory / MANIFEST), previous)
    return published, summary_of(result, scan, {}).to_json()
