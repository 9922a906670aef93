"""What the scan pipeline publishes through, as Frigate's `Communicator` is for its dispatcher:
a small protocol apart from the MQTT machinery.

`telemetry.client.Telemetry` is the real one (the outbox, the broker, Sparkplug, Home
Assistant); `MemoryPublisher` keeps what it is given, in order, after the same validation, so
the pipeline's paths (a full disk, a failed or abandoned scan) are tested in milliseconds
without a broker.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Protocol

from silo_agent.analysis.alarm_types import AlarmEvent
from silo_agent.analysis.summary import ScanSummary
from silo_agent.grid.heightmap import HeightMap
from silo_agent.telemetry.payloads import Envelope, alarm_payload, check_summary

CameraStates = dict[str, tuple[str, str | None]]  # serial -> (ok | failed | ..., error)


class Publisher(Protocol):
    """The pipeline's outputs. Each call only queues (it never waits on a network) and
    raises ValueError, naming the problem, for what no consumer could accept."""

    def publish_result(self, summary: ScanSummary, heightmap: HeightMap | None = None) -> object:
        """A scan's result: `P/scan`, `P/volume`, `P/heightmap` (and what follows them)."""
        ...

    def publish_scan_failure(self, summary: ScanSummary) -> object:
        """A scan without a result: `P/scan` alone, its `invalid_reason` says why."""
        ...

    def publish_alarm(self, event: AlarmEvent) -> object:
        """An alarm raised or cleared."""
        ...

    def set_status(
        self, cameras: CameraStates | None = None, last_scan_id: str | None = None
    ) -> None:
        """What `P/status` reports: the cameras' states, the last scan."""
        ...

    def raised_alarms(self) -> set[str]:
        """The alarm types raised now, whoever raised them (the metrics show them)."""
        ...


@dataclass
class Published:
    """One call on a `MemoryPublisher`: `kind` is result, failure or alarm."""

    kind: str
    summary: ScanSummary | None = None
    heightmap: HeightMap | None = None
    event: AlarmEvent | None = None


@dataclass
class MemoryPublisher:
    """A `Publisher` that keeps everything in memory: `published` in call order, `cameras`
    and `last_scan_id` as the status would say them."""

    published: list[Published] = field(default_factory=list)
    cameras: CameraStates = field(default_factory=dict)
    last_scan_id: str | None = None
    alarm_states: dict[str, AlarmEvent] = field(default_factory=dict)  # type -> latest event
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def publish_result(self, summary: ScanSummary, heightmap: HeightMap | None = None) -> None:
        check_summary(summary)
        with self._lock:
            self.published.append(Published("result", summary, heightmap))
            self.last_scan_id = summary.scan_id

    def publish_scan_failure(self, summary: ScanSummary) -> None:
        check_summary(summary)
        with self._lock:
            self.published.append(Published("failure", summary))
            self.last_scan_id = summary.scan_id

    def publish_alarm(self, event: AlarmEvent) -> None:
        alarm_payload(Envelope.new(1), event)  # as Telemetry validates it
        with self._lock:
            self.published.append(Published("alarm", event=event))
            self.alarm_states[event.type] = event

    def set_status(
        self, cameras: CameraStates | None = None, last_scan_id: str | None = None
    ) -> None:
        with self._lock:
            self.cameras.update(cameras or {})
            if last_scan_id is not None:
                self.last_scan_id = last_scan_id

    def raised_alarms(self) -> set[str]:
        with self._lock:
            return {t for t, e in self.alarm_states.items() if e.state == "raised"}

    def of(self, kind: str) -> list[Published]:
        """What was published of one kind, in order."""
        with self._lock:
            return [p for p in self.published if p.kind == kind]

    def alarms(self) -> list[AlarmEvent]:
        """The alarm events, in order."""
        return [p.event for p in self.of("alarm") if p.event is not None]
