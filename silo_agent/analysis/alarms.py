"""Alarms: (previous alarm state, new scan) -> alarm events. Pure numpy/scipy: no I/O, no clock.

Every alarm type is a `Detector`: a function that looks at the scan (`Inputs`) and says whether
the condition holds, given whether the alarm is active now (so it can apply the hysteresis of
the clear threshold). `evaluate` turns conditions into `raised` / `cleared` events and carries
the state (active alarms, collapse baseline, last volume) from scan to scan. A new alarm type
is one more entry in `DETECTORS` (or the `detectors` argument of `evaluate`).

Collapse compares the new height map with a baseline map over the cells observed in both: the
previous valid scan's, kept pinned while a collapse is active (so a hole stays an alarm until
it is filled again), or the one `alarms.baseline_scan_id` names.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from silo_agent.analysis.alarm_types import ALARM_TYPES, AlarmEvent, AlarmStateName, Severity
from silo_agent.config import AlarmsConfig, CalibrationConfig, SiloConfig
from silo_agent.detect.geometric import grid_of
from silo_agent.grid.heightmap import HeightMap
from silo_agent.grid.volume import smooth_sigma

SIGMA_PER_MAD = 1.4826  # standard deviation of a normal distribution per median absolute dev.
NOISE_SHAPE_M = 0.1  # the cameras' noise model, read over this scale, says where maps are noisy


# ---------------------------------------------------------------- inputs and findings


@dataclass(frozen=True)
class Inputs:
    """What the alarms see of one scan (built by the agent from the result and the capture)."""

    scan_id: str
    heightmap: HeightMap | None
    volume_m3: float | None
    coverage: float
    valid: bool
    floor_z: float = SiloConfig.model_fields["floor_z"].default
    ceiling_z: float | None = None
    max_z: float | None = None  # highest point of the reconstructed surface (silo frame)
    failed_cameras: tuple[tuple[str, str], ...] = ()  # (serial, error)
    cache_full: bool = False
    reconstructed: bool = True  # False: the scan failed before reconstruction (no coverage)
    baseline: HeightMap | None = None  # collapse baseline's map, if there is one
    # the new map's information density (Reconstruction.information): where its noise is
    information: np.ndarray | None = None
    baseline_scan_id: str | None = None
    previous_volume_m3: float | None = None  # default: the state's last valid volume
    registration_residual_m: Mapping[str, float] = field(default_factory=dict)  # pair -> median
    gravity_deg: Mapping[str, float] = field(default_factory=dict)  # camera -> IMU vs extrinsic
    gravity_tolerance_deg: Mapping[str, float] = field(default_factory=dict)  # camera -> limit


@dataclass(frozen=True)
class Finding:
    """A detector's verdict: the condition holds (`active`) and what to say about it."""

    active: bool
    severity: Severity = "warning"
    message: str = ""
    details: Mapping[str, Any] = field(default_factory=dict)  # AlarmEvent's detail fields


Detector = Callable[[Inputs, AlarmsConfig, bool], Finding | None]  # None: cannot judge now


@dataclass(frozen=True)
class AlarmState:
    """Carried from scan to scan (the agent persists it as JSON)."""

    active: Mapping[str, AlarmEvent] = field(default_factory=dict)  # type -> its raised event
    baseline_scan_id: str | None = None
    last_volume_m3: float | None = None
    drift: Mapping[str, Any] = field(default_factory=dict)  # drift.DriftState.to_json()

    def to_json(self) -> dict[str, Any]:
        return {
            "active": {k: v.to_json() for k, v in self.active.items()},
            "baseline_scan_id": self.baseline_scan_id,
            "last_volume_m3": self.last_volume_m3,
            "drift": dict(self.drift),
        }

    @staticmethod
    def from_json(data: Mapping[str, Any]) -> AlarmState:
        return AlarmState(
            active={str(k): AlarmEvent.from_json(v) for k, v in (data.get("active") or {}).items()},
            baseline_scan_id=data.get("baseline_scan_id"),
            last_volume_m3=data.get("last_volume_m3"),
            drift=dict(data.get("drift") or {}),
        )


# ---------------------------------------------------------------- collapse


@dataclass(frozen=True)
class Collapse:
    """One connected region where the surface dropped."""

    centroid: tuple[float, float]  # silo frame, weighted by the drop
    area_m2: float
    depth_m: float  # the deepest drop
    volume_m3: float  # grain volume lost over the region
    # the drop that counted (max of the configured depth and the noise floor; its mean over
    # the region where the noise differs over the map)
    threshold_m: float


def _roughness(hm: HeightMap, mask: np.ndarray, shape: np.ndarray | float = 1.0) -> float:
    """Sensor noise of one map: robust sigma of the heights minus their 3x3 median (each
    residual over the map's `noise_shape` there)."""
    filled = np.where(np.isfinite(hm.heights), hm.heights, np.nanmedian(hm.heights))
    residual = ((filled - ndimage.median_filter(filled, size=3)) / shape)[mask]
    if residual.size == 0:
        return 0.0
    return float(SIGMA_PER_MAD * np.median(np.abs(residual - np.median(residual))))


def noise_shape(new: HeightMap, information: np.ndarray | None) -> np.ndarray | float:
    """Per cell, how noisy the maps are there against their median cell: the cameras' noise
    model (`volume.smooth_sigma` of `information` over NOISE_SHAPE_M) over its median, the
    largest where nothing was measured; 1 (the same everywhere) without `information`.

    Across a big bin the noise differs threefold between the heap under the cameras and the
    ring 15-19 m from them: one sigma for the whole map, set by the ring's many cells, asked
    an 18 m bin's heap for a drop of 0.6-1.2 m before it was a collapse."""
    if information is None:
        return 1.0
    if information.shape != new.heights.shape:
        raise ValueError(f"information on {information.shape} cells, the map {new.shape}")
    region = np.isfinite(new.heights) & (new.inside > 0)
    sigma = smooth_sigma(grid_of(new), information, region, NOISE_SHAPE_M)
    modelled = sigma > 0
    if not np.any(modelled):
        return 1.0
    sigma = np.where(modelled, sigma, float(sigma[modelled].max()))
    return sigma / float(np.median(sigma[modelled]))


def noise_floor(
    baseline: HeightMap, new: HeightMap, both: np.ndarray, shape: np.ndarray | float = 1.0
) -> float:
    """Sigma of the height difference that sensor noise alone explains, over `shape`
    (`noise_shape`; a cell's sigma is this times its shape): the larger of the robust spread
    of the difference itself and the two maps' own roughness combined."""
    diff = ((new.heights - baseline.heights) / shape)[both]
    if diff.size == 0:
        return 0.0
    spread = SIGMA_PER_MAD * float(np.median(np.abs(diff - np.median(diff))))
    rough = float(np.hypot(_roughness(baseline, both, shape), _roughness(new, both, shape)))
    return max(spread, rough)


def find_collapses(
    baseline: HeightMap,
    new: HeightMap,
    depth_m: float,
    min_area_m2: float,
    noise_k: float,
    information: np.ndarray | None = None,
) -> list[Collapse]:
    """Regions (8-connected) where the new surface is lower than the baseline by more than
    max(depth_m, noise_k x the noise sigma there), largest first. The sigma is the maps'
    (`noise_floor`); with the new map's `information` (the cameras are the same in both
    scans), where the noise is less than that, shaped over the map by the cameras' noise
    model (`noise_shape`), the less: a collapse under the cameras is judged by the noise
    there, not by the far wall's, and nowhere by more than the whole map's. The
    decision rests on the cells observed in both maps: a region needs `min_area_m2` of them;
    its footprint, depth and lost volume then include the filled cells within it (a hole in
    one view is still the funnel). The difference is median-filtered (3x3) first so single
    noisy cells neither make nor break a region."""
    if baseline.heights.shape != new.heights.shape or baseline.step != new.step:
        raise ValueError("baseline and new height maps are on different grids")
    known = np.isfinite(baseline.heights) & np.isfinite(new.heights) & (new.inside > 0)
    both = known & baseline.observed & new.observed
    if not np.any(both):
        return []
    sigma: float | np.ndarray = noise_floor(baseline, new, both)
    shape = noise_shape(new, information)
    if not isinstance(shape, float):  # where the noise is less than the map's, that noise
        sigma = np.minimum(sigma, noise_floor(baseline, new, both, shape) * shape)
    threshold = np.maximum(depth_m, noise_k * sigma)
    drop = np.where(known, baseline.heights.astype(float) - new.heights, 0.0)
    drop = ndimage.median_filter(drop, size=3)
    labels, count = ndimage.label(known & (drop > threshold), structure=np.ones((3, 3)))
    if count == 0:
        return []
    index = np.arange(1, count + 1)
    cell_area = new.step**2 * new.inside
    observed_areas = ndimage.sum(cell_area * both, labels, index)
    areas = ndimage.sum(cell_area, labels, index)
    depths = ndimage.maximum(drop, labels, index)
    counted = ndimage.mean(np.broadcast_to(threshold, drop.shape), labels, index)
    lost = ndimage.sum(drop * cell_area, labels, index)
    xs, ys = new.cell_centres()
    cx = ndimage.sum(xs * drop * cell_area, labels, index) / lost
    cy = ndimage.sum(ys * drop * cell_area, labels, index) / lost
    found = [
        Collapse(
            (float(cx[i]), float(cy[i])),
            float(areas[i]),
            float(depths[i]),
            float(lost[i]),
            float(counted[i]),
        )
        for i in range(count)
        if observed_areas[i] >= min_area_m2
    ]
    return sorted(found, key=lambda c: -c.area_m2)


def detect_collapse(inputs: Inputs, cfg: AlarmsConfig, active: bool) -> Finding | None:
    if inputs.baseline is None or inputs.heightmap is None or not inputs.valid:
        return None
    scale = cfg.hysteresis if active else 1.0  # an active collapse clears only well below
    found = find_collapses(
        inputs.baseline,
        inputs.heightmap,
        cfg.collapse_depth_m * scale,
        cfg.collapse_min_area_m2 * scale,
        cfg.collapse_noise_k,
        inputs.information,
    )
    if not found:
        return Finding(False, "critical", f"no collapse against {inputs.baseline_scan_id}")
    c = found[0]
    return Finding(
        True,
        "critical",
        f"surface dropped {c.depth_m:.2f} m over {c.area_m2:.2f} m² at "
        f"({c.centroid[0]:.2f}, {c.centroid[1]:.2f}) against {inputs.baseline_scan_id}",
        {
            "position": (round(c.centroid[0], 4), round(c.centroid[1], 4)),
            "area_m2": round(c.area_m2, 4),
            "depth_m": round(c.depth_m, 4),
            "volume_m3": round(c.volume_m3, 4),
            "threshold": round(c.threshold_m, 4),
        },
    )


# ---------------------------------------------------------------- level, volume, faults


def detect_level_high(inputs: Inputs, cfg: AlarmsConfig, active: bool) -> Finding | None:
    if cfg.high_level_margin_m is None or inputs.ceiling_z is None or inputs.max_z is None:
        return None
    margin = cfg.high_level_margin_m * ((1 + cfg.hysteresis) if active else 1.0)
    limit = inputs.ceiling_z - margin
    distance = inputs.ceiling_z - inputs.max_z
    return Finding(
        inputs.max_z >= limit,
        "warning",
        f"surface {distance:.2f} m below the ceiling (alarm within {cfg.high_level_margin_m} m)",
        {
            "value": round(inputs.max_z - inputs.floor_z, 4),
            "threshold": round(inputs.ceiling_z - cfg.high_level_margin_m - inputs.floor_z, 4),
        },
    )


def detect_level_low(inputs: Inputs, cfg: AlarmsConfig, active: bool) -> Finding | None:
    if cfg.low_volume_m3 is None or inputs.volume_m3 is None or not inputs.valid:
        return None
    limit = cfg.low_volume_m3 * ((1 + cfg.hysteresis) if active else 1.0)
    return Finding(
        inputs.volume_m3 < limit,
        "warning",
        f"volume {inputs.volume_m3:.3f} m³ (alarm below {cfg.low_volume_m3} m³)",
        {"value": round(inputs.volume_m3, 4), "threshold": cfg.low_volume_m3},
    )


def detect_change(inputs: Inputs, cfg: AlarmsConfig, active: bool) -> Finding | None:
    before, now = inputs.previous_volume_m3, inputs.volume_m3
    if cfg.change_fraction is None or before is None or now is None or not inputs.valid:
        return None
    share = abs(now - before) / max(abs(before), 1e-9)
    limit = cfg.change_fraction * (cfg.hysteresis if active else 1.0)
    return Finding(
        share > limit,
        "warning",
        f"volume {before:.3f} -> {now:.3f} m³ ({share * 100:.1f} % in one scan)",
        {"value": round(now - before, 4), "threshold": round(cfg.change_fraction * before, 4)},
    )


def detect_camera(inputs: Inputs, cfg: AlarmsConfig, active: bool) -> Finding:
    failed = inputs.failed_cameras
    return Finding(
        bool(failed),
        "warning",
        "; ".join(f"{serial}: {error}" for serial, error in failed) or "all cameras delivered",
        {"value": float(len(failed))},
    )


def detect_coverage(inputs: Inputs, cfg: AlarmsConfig, active: bool) -> Finding | None:
    if not inputs.reconstructed:  # the camera alarm tells why there is nothing to cover
        return None
    limit = cfg.min_coverage * ((1 + cfg.hysteresis) if active else 1.0)
    return Finding(
        inputs.coverage < limit,
        "warning",
        f"{inputs.coverage * 100:.1f} % of the region observed (alarm below "
        f"{cfg.min_coverage * 100:.0f} %)",
        {"value": round(inputs.coverage, 4), "threshold": cfg.min_coverage},
    )


def detect_cache(inputs: Inputs, cfg: AlarmsConfig, active: bool) -> Finding:
    return Finding(
        inputs.cache_full,
        "critical",
        "audit cache full or unwritable: scan published without its raw clouds, result or "
        "height map kept"
        if inputs.cache_full
        else "audit cache writable",
    )


DETECTORS: dict[str, Detector] = {
    "collapse": detect_collapse,
    "level_high": detect_level_high,
    "level_low": detect_level_low,
    "change": detect_change,
    "camera": detect_camera,
    "coverage": detect_coverage,
    "cache": detect_cache,
}


# ---------------------------------------------------------------- lifecycle

# alarm type -> the AlarmsConfig key whose absence (None) switches its detector off
SWITCHES = {
    "level_high": "high_level_margin_m",
    "level_low": "low_volume_m3",
    "change": "change_fraction",
}


def switched_off(cfg: AlarmsConfig) -> dict[str, str]:
    """Alarm type -> why its detector is off under this config. Such a detector never judges
    again, so an alarm it raised would otherwise stay raised for good."""
    if not cfg.enabled:
        return {kind: "alarms switched off (alarms.enabled = false)" for kind in ALARM_TYPES}
    return {
        kind: f"detector switched off (alarms.{key} not set)"
        for kind, key in SWITCHES.items()
        if getattr(cfg, key) is None
    }


def clear_switched_off(
    state: AlarmState, cfg: AlarmsConfig, scan_id: str | None
) -> tuple[list[AlarmEvent], AlarmState]:
    """`cleared` events for the active alarms whose detector the config switched off (the
    agent calls it at start and on reload too, so a clear does not wait for the next scan)."""
    off = switched_off(cfg)
    events = [
        AlarmEvent(
            type=kind,
            state="cleared",
            severity=raised.severity,
            scan_id=scan_id,
            message=off[kind],
        )
        for kind, raised in state.active.items()
        if kind in off
    ]
    if not events:
        return [], state
    active = {k: v for k, v in state.active.items() if k not in off}
    return events, replace(state, active=active)


def _event(kind: str, state: AlarmStateName, finding: Finding, scan_id: str) -> AlarmEvent:
    """The event of a detector's finding."""
    return AlarmEvent(
        type=kind,
        state=state,
        severity=finding.severity,
        scan_id=scan_id,
        message=finding.message,
        **finding.details,
    )


def evaluate(
    state: AlarmState,
    inputs: Inputs,
    cfg: AlarmsConfig,
    detectors: Mapping[str, Detector] | None = None,
    calibration: CalibrationConfig | None = None,
) -> tuple[list[AlarmEvent], AlarmState]:
    """Events (`raised` / `cleared`, only on a change) and the state for the next scan.

    With `calibration`, the `calibration` alarm follows the calibration_drift detector
    (silo_agent.analysis.drift.drift_step, whose run lengths the state carries): raised while any
    camera pair's height disagreement or camera's IMU tilt is drifted, cleared when none is.

    Parameters
    ----------
    state : AlarmState
        The active alarms, the collapse baseline and the last volume, from the last scan.
    inputs : Inputs
        What the alarms see of this scan.
    cfg : AlarmsConfig
        Thresholds, hysteresis and which detectors are on.
    detectors : mapping of str to Detector, optional
        Alarm type -> detector; default `DETECTORS`.
    calibration : CalibrationConfig, optional
        Drift thresholds; None leaves the `calibration` alarm as it is.

    Returns
    -------
    events : list of AlarmEvent
        The changes, in order: clears of switched-off detectors first.
    state : AlarmState
        The state to pass to the next scan's evaluation.
    """
    detectors = DETECTORS if detectors is None else detectors
    if inputs.previous_volume_m3 is None:
        inputs = replace(inputs, previous_volume_m3=state.last_volume_m3)
    events, state = clear_switched_off(state, cfg, inputs.scan_id)
    active = dict(state.active)
    if cfg.enabled:
        for kind, detect in detectors.items():
            was = kind in active
            finding = detect(inputs, cfg, was)
            if finding is None:
                continue
            if finding.active and not was:
                event = _event(kind, "raised", finding, inputs.scan_id)
                active[kind] = event
                events.append(event)
            elif was and not finding.active:
                del active[kind]
                events.append(_event(kind, "cleared", finding, inputs.scan_id))
    drift = state.drift
    if cfg.enabled and calibration is not None and inputs.reconstructed:
        drift = _calibration_drift(inputs, calibration, state.drift, active, events)
    baseline = state.baseline_scan_id
    if cfg.baseline_scan_id is not None:
        baseline = cfg.baseline_scan_id
    elif "collapse" not in active and inputs.valid and inputs.heightmap is not None:
        baseline = inputs.scan_id  # the next scan is compared with this one
    volume = state.last_volume_m3
    if inputs.valid and inputs.volume_m3 is not None:
        volume = inputs.volume_m3
    return events, replace(
        state, active=active, baseline_scan_id=baseline, last_volume_m3=volume, drift=drift
    )


def _calibration_drift(
    inputs: Inputs,
    calibration: CalibrationConfig,
    previous: Mapping[str, Any],
    active: dict[str, AlarmEvent],
    events: list[AlarmEvent],
) -> dict[str, Any]:
    """One drift_step; raise or clear the `calibration` alarm in `active` / `events`."""
    from silo_agent.analysis.drift import DEFAULT_GRAVITY_TOLERANCE_DEG, DriftState, drift_step

    tolerances = inputs.gravity_tolerance_deg or DEFAULT_GRAVITY_TOLERANCE_DEG
    state, changes = drift_step(
        DriftState.from_json(previous),
        inputs.registration_residual_m,
        inputs.gravity_deg,
        calibration,
        tolerances,
    )
    was = "calibration" in active
    drifted = sorted(state.raised)
    if drifted and not was:
        raised = [c for c in changes if c.kind == "raised"]
        message = "; ".join(c.message for c in raised) + f" [drifted: {', '.join(drifted)}]"
        details = {}
        if raised:  # AlarmPayload's value / threshold: the worst of them
            worst = max(raised, key=lambda c: c.value / c.threshold)
            details = {"value": worst.value, "threshold": worst.threshold}
        event = _event(
            "calibration", "raised", Finding(True, "warning", message, details), inputs.scan_id
        )
        active["calibration"] = event
        events.append(event)
    elif was and not drifted:
        del active["calibration"]
        finding = Finding(False, "warning", "camera poses agree again")
        events.append(_event("calibration", "cleared", finding, inputs.scan_id))
    return state.to_json()
