"""Calibration drift, watched at run time: every scan's camera-pair height disagreements
(reconstruct/residual.py) and the cameras' IMU gravity against their extrinsics become
raise/clear events (`drift_step`: pure, previous state in, new state and events out) for the
alarm publisher to forward. Recalibrating is the offline tool's job (`silo_agent.calibrate`),
which the daemon does not import. The gravity readings come from the scan
(`scan.gravity_angles`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from silo_agent.config import CalibrationConfig, CameraConfig, Config
from silo_agent.reconstruct.residual import PairResidual
from silo_agent.scan import CameraCloud, gravity_angles

# a camera without its own `gravity_tolerance_deg` gets the config's default
DEFAULT_GRAVITY_TOLERANCE_DEG: float = CameraConfig.model_fields["gravity_tolerance_deg"].default


@dataclass(frozen=True)
class DriftEvent:
    """An alarm transition. `key` is stable per alarm: `"residual:<a>|<b>"` for a camera pair,
    `"gravity:<serial>"` for a camera whose IMU disagrees with its extrinsic."""

    kind: Literal["raised", "cleared"]
    key: str
    cameras: tuple[str, ...]
    value: float  # |median residual| (m) or gravity angle (deg) of the scan that decided
    threshold: float
    message: str

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "key": self.key,
            "cameras": list(self.cameras),
            "value": self.value,
            "threshold": self.threshold,
            "message": self.message,
        }


@dataclass(frozen=True)
class DriftState:
    """What the detector remembers between scans: run lengths over / under the threshold per
    key (positive: scans in a row over, negative: in a row under) and the raised alarms."""

    runs: Mapping[str, int] = field(default_factory=dict)
    raised: frozenset[str] = frozenset()

    def to_json(self) -> dict[str, Any]:
        return {"runs": dict(self.runs), "raised": sorted(self.raised)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> DriftState:
        return cls(
            {str(k): int(v) for k, v in data.get("runs", {}).items()},
            frozenset(data.get("raised", ())),
        )


def drift_step(
    state: DriftState,
    residuals: Mapping[str, PairResidual | float],
    gravity_deg: Mapping[str, float],
    settings: CalibrationConfig,
    gravity_tolerance_deg: Mapping[str, float] | float = DEFAULT_GRAVITY_TOLERANCE_DEG,
) -> tuple[DriftState, list[DriftEvent]]:
    """One scan of the `calibration_drift` detector. Pure.

    - `residuals`: the scan's `registration_residual_m` (pair key -> median metres, or the
      `PairResidual`s of `Reconstruction.registration`);
    - `gravity_deg`: per camera, the angle between its IMU gravity and its extrinsic's vertical
      (`gravity_angles(scan.cameras)`, or `gravity_angle_deg` in scan.json);
    - `gravity_tolerance_deg`: per camera (its `[[cameras]] gravity_tolerance_deg`) or one value.

    An alarm is raised when its value is over the threshold (`drift_threshold_m` for |median|,
    the tolerance for gravity) in `drift_consecutive` scans in a row, and cleared after as
    many scans in a row under it. A key absent from a scan (pair without overlap, camera without
    IMU, failed camera) keeps its run and alarm unchanged: no news is not good news.
    """
    n = settings.drift_consecutive
    values: dict[str, tuple[float, float, tuple[str, ...], str]] = {}
    for key, r in residuals.items():
        median = r.median_m if isinstance(r, PairResidual) else float(r)
        a, _, b = key.partition("|")
        values[f"residual:{key}"] = (
            abs(median),
            settings.drift_threshold_m,
            (a, b),
            f"cameras {a} and {b} disagree by {median * 1000:+.1f} mm on the height of the "
            "cells both see",
        )
    for serial, angle in gravity_deg.items():
        if isinstance(gravity_tolerance_deg, (int, float)):
            tolerance = float(gravity_tolerance_deg)
        else:
            tolerance = gravity_tolerance_deg.get(serial, DEFAULT_GRAVITY_TOLERANCE_DEG)
        values[f"gravity:{serial}"] = (
            float(angle),
            float(tolerance),
            (serial,),
            f"camera {serial}'s accelerometer is {angle:.2f} deg off the tilt its extrinsic claims",
        )
    runs = dict(state.runs)
    raised = set(state.raised)
    events: list[DriftEvent] = []
    for key, (value, threshold, cameras, text) in sorted(values.items()):
        over = value > threshold
        previous = runs.get(key, 0)
        run = (max(previous, 0) + 1) if over else (min(previous, 0) - 1)
        runs[key] = run
        if over and run >= n and key not in raised:
            raised.add(key)
            events.append(
                DriftEvent(
                    "raised",
                    key,
                    cameras,
                    value,
                    threshold,
                    f"{text} ({n} scans in a row): recalibrate (silo-agent calibrate)",
                )
            )
        elif not over and -run >= n and key in raised:
            raised.discard(key)
            events.append(
                DriftEvent(
                    "cleared", key, cameras, value, threshold, f"{text}: back within {threshold:g}"
                )
            )
    return DriftState(runs, frozenset(raised)), events


class DriftMonitor:
    """A stateful wrapper of `drift_step` for the daemon: `update(result, scan)` per scan."""

    def __init__(
        self,
        settings: CalibrationConfig,
        gravity_tolerance_deg: Mapping[str, float] | float = DEFAULT_GRAVITY_TOLERANCE_DEG,
        state: DriftState | None = None,
    ) -> None:
        self.settings = settings
        self.gravity_tolerance_deg = gravity_tolerance_deg
        self.state = state or DriftState()

    @classmethod
    def for_config(cls, config: Config, state: DriftState | None = None) -> DriftMonitor:
        tolerances = {c.serial: c.gravity_tolerance_deg for c in config.cameras}
        return cls(config.calibration, tolerances, state)

    def update(
        self, residuals: Mapping[str, PairResidual | float], cameras: Sequence[CameraCloud] = ()
    ) -> list[DriftEvent]:
        """Feed one scan (`Reconstruction.registration` and the scan's cameras): its events."""
        self.state, events = drift_step(
            self.state,
            residuals,
            gravity_angles(cameras),
            self.settings,
            self.gravity_tolerance_deg,
        )
        return events

    @property
    def active(self) -> frozenset[str]:
        return self.state.raised
