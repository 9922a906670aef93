"""The published summary of one scan: the one type that result.json, `process --json`, `P/scan`,
`P/volume`, Sparkplug, Home Assistant and the Prometheus metrics all read, built by `summarise`.

The fields are declared in the order of the JSON object (docs/scan-format.md), so `to_json` is
a walk over them: a new key is one more field here (and its value in `summarise`). A scan
that produced no result (`NoResult`) has only the fields every consumer reads: those marked
`_engine()` (the engine's details) are left out of its JSON.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, is_dataclass
from typing import TYPE_CHECKING, Any

from silo_agent.detect import Pile, Robot
from silo_agent.reconstruct.residual import PairResidual

if TYPE_CHECKING:
    from silo_agent.analysis.scan_analysis import ScanAnalysis

_ENGINE = "engine"  # field metadata: a key only a summary of a reconstructed scan has


def _engine(default_factory: Any = dict) -> Any:
    return field(default_factory=default_factory, metadata={_ENGINE: True})


@dataclass(frozen=True)
class SurfaceZ:
    """The reconstructed surface's heights, silo frame (metres)."""

    min_z: float
    mean_z: float
    max_z: float


@dataclass(frozen=True)
class Level:
    """The grain level, metres above the floor."""

    min: float
    mean: float
    max: float


@dataclass(frozen=True)
class FailedCamera:
    serial: str
    error: str


@dataclass(frozen=True)
class Cameras:
    """The cameras whose clouds the scan used, and those that failed (`degraded`)."""

    used: tuple[str, ...]
    failed: tuple[FailedCamera, ...] = ()


@dataclass(frozen=True, kw_only=True)
class ScanSummary:
    """One scan's result, as every output publishes it (docs/scan-format.md, docs/mqtt.md)."""

    scan_id: str
    method: str
    volume_m3: float | None
    mass_t: float | None
    coverage: float
    grid_step_m: float
    surface: SurfaceZ | None
    level: Level | None
    valid: bool
    invalid_reason: str | None
    capacity_m3: float | None = None  # a bin's ([silo.bin]); None without one
    fill_ratio: float | None = None
    headspace_m: float | None = None
    headspace_mean_m: float | None = None
    cameras: Cameras
    points: Mapping[str, int] = _engine()
    parameters: Mapping[str, Any] = _engine()
    timings_s: Mapping[str, float] = _engine()  # the engine's stages
    piles: tuple[Pile, ...] = ()
    robots: tuple[Robot, ...] | None = _engine(lambda: None)  # None: no YOLO model configured
    registration_residual_m: Mapping[str, float] = _engine()  # camera pair -> median
    registration_residual: Mapping[str, PairResidual] = _engine()
    captured_at: str
    degraded: bool
    timings: Mapping[str, float]  # the scan's stages (capture, audit, reconstruct, ...)
    reconstructed: bool = field(default=True, metadata={"json": False})

    def to_json(self) -> dict[str, Any]:
        """The JSON object, keys in field order (result.json's bytes depend on it)."""
        return {
            f.name: _jsonable(getattr(self, f.name))
            for f in fields(self)
            if f.metadata.get("json", True) and (self.reconstructed or not f.metadata.get(_ENGINE))
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ScanSummary:
        """A summary read back (result.json, a hand-written one for `telemetry publish`);
        ValueError naming the key that is missing or malformed."""
        try:
            return _from_json(cls, data)
        except KeyError as exc:
            raise ValueError(f"result summary lacks {exc.args[0]!r}") from None
        except (TypeError, AttributeError, ValueError) as exc:
            raise ValueError(f"result summary: {exc}") from None


@dataclass(frozen=True)
class NoResult:
    """A scan that produced no result (no cloud, processing failed, abandoned): `reason`."""

    scan_id: str
    method: str
    grid_step_m: float
    reason: str


def summarise(
    outcome: ScanAnalysis | NoResult,
    captured_at: str,
    failed: Sequence[FailedCamera],
    timings: Mapping[str, float],
) -> ScanSummary:
    """The summary of a scan's analysis, or of a scan without a result.

    Parameters
    ----------
    outcome : ScanAnalysis or NoResult
        What the scan's analysis found, or why there is none.
    captured_at : str
        The scan's capture time, RFC 3339 UTC.
    failed : sequence of FailedCamera
        The cameras that failed during the capture (the summary is then `degraded`).
    timings : mapping of str to float
        The scan's stage durations, seconds (`capture_s`, ...); rounded to 0.1 ms.

    Returns
    -------
    ScanSummary
        What every output publishes.
    """
    rounded = {k: round(v, 4) for k, v in timings.items()}
    if isinstance(outcome, NoResult):
        return ScanSummary(
            scan_id=outcome.scan_id,
            method=outcome.method,
            volume_m3=None,
            mass_t=None,
            coverage=0.0,
            grid_step_m=outcome.grid_step_m,
            surface=None,
            level=None,
            valid=False,
            invalid_reason=outcome.reason,
            cameras=Cameras((), tuple(failed)),
            captured_at=captured_at,
            degraded=bool(failed),
            timings=rounded,
            reconstructed=False,
        )
    result = outcome.reconstruction
    bin_figures = result.bin_figures()
    surface = level = None
    if result.surface is not None:
        s, floor = result.surface, result.floor_z
        surface = SurfaceZ(s.min, s.mean, s.max)
        level = Level(s.min - floor, s.mean - floor, s.max - floor)
    return ScanSummary(
        scan_id=result.scan_id,
        method=result.method,
        volume_m3=result.volume_m3,
        mass_t=result.mass_t,
        coverage=result.coverage,
        grid_step_m=result.grid_step_m,
        surface=surface,
        level=level,
        valid=result.valid,
        invalid_reason=result.invalid_reason,
        capacity_m3=result.capacity_m3,
        fill_ratio=bin_figures["fill_ratio"],
        headspace_m=bin_figures["headspace_m"],
        headspace_mean_m=bin_figures["headspace_mean_m"],
        cameras=Cameras(tuple(result.cameras), tuple(failed)),
        points=result.points,
        parameters=result.parameters,
        timings_s=result.timings_s,
        piles=tuple(outcome.piles),
        robots=None if outcome.robots is None else tuple(outcome.robots),
        registration_residual_m={k: r.median_m for k, r in result.registration.items()},
        registration_residual=result.registration,
        captured_at=captured_at,
        degraded=bool(failed),
        timings=rounded,
    )


def _jsonable(value: Any) -> Any:
    """A field's JSON value: `to_json()` where a type has one, dataclasses as objects."""
    if hasattr(value, "to_json"):
        return value.to_json()
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: _jsonable(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, Mapping):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def _from_json(cls: type[ScanSummary], data: Mapping[str, Any]) -> ScanSummary:
    if not isinstance(data, Mapping):
        raise TypeError("not a JSON object")
    return cls(
        scan_id=data["scan_id"],
        method=data.get("method", ""),
        volume_m3=data.get("volume_m3"),
        mass_t=data.get("mass_t"),
        coverage=data["coverage"],
        grid_step_m=data["grid_step_m"],
        surface=_part(data, "surface", lambda v: SurfaceZ(**v)),
        level=_part(data, "level", lambda v: Level(**v)),
        valid=data["valid"],
        invalid_reason=data.get("invalid_reason"),
        capacity_m3=data.get("capacity_m3"),
        fill_ratio=data.get("fill_ratio"),
        headspace_m=data.get("headspace_m"),
        headspace_mean_m=data.get("headspace_mean_m"),
        cameras=_part(
            data,
            "cameras",
            lambda v: Cameras(
                tuple(v.get("used", ())), tuple(FailedCamera(**f) for f in v.get("failed", ()))
            ),
        )
        or Cameras(()),
        points=_object(data, "points"),
        parameters=_object(data, "parameters"),
        timings_s=_durations(data, "timings_s"),
        piles=_part(data, "piles", lambda v: tuple(Pile.from_json(p) for p in v)) or (),
        robots=_part(data, "robots", lambda v: tuple(Robot.from_json(r) for r in v)),
        registration_residual_m=_object(data, "registration_residual_m"),
        registration_residual=_part(
            data,
            "registration_residual",
            lambda v: {k: PairResidual.from_json(k, r) for k, r in v.items()},
        )
        or {},
        captured_at=data["captured_at"],
        degraded=data.get("degraded", False),
        timings=_durations(data, "timings"),
        reconstructed="points" in data,
    )


def _part(data: Mapping[str, Any], key: str, build: Callable[[Any], Any]) -> Any:
    """`build(data[key])`, None where the key is missing or null; ValueError naming the key."""
    value = data.get(key)
    if value is None:
        return None
    try:
        return build(value)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f"{key}: {exc}") from None


def _object(data: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    """`data[key]`, a JSON object ({} where the key is missing or null); ValueError naming
    the key, not an AttributeError where a consumer walks it."""
    value = data.get(key)
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ValueError(f"{key}: must be a JSON object, got {value!r:.40}")
    return value


def _durations(data: Mapping[str, Any], key: str) -> Mapping[str, float]:
    """`data[key]`, stage names to seconds; ValueError naming the key and the stage."""
    value = _object(data, key)
    for stage, seconds in value.items():
        if isinstance(seconds, bool) or not isinstance(seconds, int | float):
            raise ValueError(f"{key}.{stage}: must be a number of seconds, got {seconds!r:.40}")
    return value
