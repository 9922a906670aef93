"""The alarm types the domain evaluates (the one list every output declares: Sparkplug, Home
Assistant, Prometheus, MQTT topics) and the one event type every output publishes."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal

# Alarm types every consumer can count on: Prometheus' alarm_active, the Sparkplug NBIRTH's
# Alarms/*, Home Assistant discovery and the retained P/alarm/<type> states declare them up
# front (the scan's detectors, calibration, and the outbox's own alarm); others may appear and
# are added as they are seen.
ALARM_TYPES = (
    "collapse",
    "level_high",
    "level_low",
    "change",
    "camera",
    "coverage",
    "cache",
    "calibration",
    "outbox",
)

AlarmStateName = Literal["raised", "cleared"]
Severity = Literal["info", "warning", "critical"]


@dataclass(frozen=True, kw_only=True)
class AlarmEvent:
    """A `silo-alarm/1` event body (telemetry adds the envelope): an alarm type was raised or
    cleared. The details after `message` are what the detector measured; a detail left None
    is not part of the JSON."""

    type: str
    state: AlarmStateName
    severity: Severity
    scan_id: str | None
    message: str = ""
    position: tuple[float, float] | None = None  # collapse: silo-frame (x, y) of the centre
    area_m2: float | None = None  # collapse: affected area
    depth_m: float | None = None  # collapse: deepest drop
    volume_m3: float | None = None  # collapse: volume lost
    value: float | None = None  # the measured value that triggered it
    threshold: float | None = None

    def to_json(self) -> dict[str, Any]:
        """The event's JSON object: the five keys every event has, then the details set."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None or f.name == "scan_id":
                out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> AlarmEvent:
        """An event read back (the persisted alarm state, an `EVENT.json` to publish by
        hand); ValueError naming the problem."""
        if not isinstance(data, Mapping):
            raise ValueError(f"alarm event: must be a JSON object, got {data!r:.40}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"alarm event: unknown key(s) {', '.join(unknown)}")
        position = data.get("position")
        if position is not None and not isinstance(position, list | tuple):
            raise ValueError(f"alarm event: position: must be [x, y], got {position!r:.40}")
        try:
            return cls(**{**data, "position": None if position is None else tuple(position)})
        except TypeError as exc:
            raise ValueError(f"alarm event: {exc}") from None


def idle_alarm(alarm_type: str) -> AlarmEvent:
    """The state of an alarm type that is not raised (nothing raised it yet)."""
    return AlarmEvent(
        type=alarm_type, state="cleared", severity="info", scan_id=None, message="not raised"
    )
