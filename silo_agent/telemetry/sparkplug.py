"""Sparkplug B 3.0 edge node: the metrics, and the NBIRTH / NDATA / NDEATH payloads.

Pure payload building; the MQTT session (will, bdSeq, seq, rebirth, STATE) lives in
transport.py, session.py and pump.py.
The node keeps the current value of every metric so that any NBIRTH (first, after a
reconnect, on a rebirth request) declares all of them with their datatypes and values.
NDATA payloads are stored in the outbox without `seq`; `finalize` adds it when sent, leaves out
the metrics the session's NBIRTH did not declare, and marks metrics `is_historical` when they
are replayed after an outage.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from google.protobuf.message import DecodeError

from silo_agent.analysis.alarm_types import ALARM_TYPES, AlarmEvent
from silo_agent.telemetry import sparkplug_b_pb2 as pb

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BD_SEQ = "bdSeq"

INT = {pb.Int8, pb.Int16, pb.Int32, pb.UInt8, pb.UInt16, pb.UInt32}
LONG = {pb.Int64, pb.UInt64, pb.DateTime}

# metric name -> datatype; the result metrics, in the order NBIRTH lists them
RESULT_METRICS: dict[str, int] = {
    "Inventory/Volume m3": pb.Double,
    "Inventory/Mass t": pb.Double,
    "Inventory/Level Min m": pb.Double,
    "Inventory/Level Mean m": pb.Double,
    "Inventory/Level Max m": pb.Double,
    "Inventory/Coverage": pb.Double,
    "Inventory/Valid": pb.Boolean,
    "Inventory/Degraded": pb.Boolean,
    "Inventory/Capacity m3": pb.Double,
    "Inventory/Fill Ratio": pb.Double,
    "Inventory/Headspace m": pb.Double,
    "Inventory/Headspace Mean m": pb.Double,
    "Scan/Last Id": pb.String,
    "Scan/Time": pb.DateTime,
}


def now_ms() -> int:
    return int(time.time() * 1000)


def iso_to_ms(moment: str) -> int:
    return int(datetime.fromisoformat(moment.replace("Z", "+00:00")).timestamp() * 1000)


def alarm_metric(alarm_type: str) -> str:
    return f"Alarms/{alarm_type}"


def camera_metric(serial: str) -> str:
    return f"Cameras/{serial}/State"


@dataclass(frozen=True)
class Topics:
    group_id: str
    edge_node_id: str

    def node(self, message_type: str) -> str:
        return f"{NAMESPACE}/{self.group_id}/{message_type}/{self.edge_node_id}"

    @staticmethod
    def state(host_id: str) -> str:
        return f"{NAMESPACE}/STATE/{host_id}"


def _set_value(metric: Any, datatype: int, value: Any) -> None:
    metric.datatype = datatype
    if value is None:
        metric.is_null = True
    elif datatype in INT:
        metric.int_value = int(value) & 0xFFFFFFFF
    elif datatype in LONG:
        metric.long_value = int(value) & 0xFFFFFFFFFFFFFFFF
    elif datatype == pb.Float:
        metric.float_value = float(value)
    elif datatype == pb.Double:
        metric.double_value = float(value)
    elif datatype == pb.Boolean:
        metric.boolean_value = bool(value)
    elif datatype in (pb.String, pb.Text, pb.UUID):
        metric.string_value = str(value)
    else:
        raise ValueError(f"datatype {datatype} is not used by silo-agent")


class SparkplugNode:
    """Metric definitions, current values and their timestamps (ms) of this edge node."""

    def __init__(self, version: str, camera_serials: Iterable[str]) -> None:
        self.datatypes: dict[str, int] = {"Node Info/Software Version": pb.String}
        self.values: dict[str, Any] = {"Node Info/Software Version": version}
        # when each value was measured (a scan's capture, an event); absent: never set
        self.stamps: dict[str, int] = {}
        self.datatypes.update(RESULT_METRICS)
        for alarm_type in ALARM_TYPES:
            self.datatypes[alarm_metric(alarm_type)] = pb.Boolean
            self.values[alarm_metric(alarm_type)] = False
        for serial in camera_serials:
            self.datatypes[camera_metric(serial)] = pb.String
            self.values[camera_metric(serial)] = "unknown"

    def restore_alarms(self, active: Iterable[str]) -> None:
        """Take the alarm states persisted by the last run, so that the first NBIRTH after a
        restart says raised where the JSON topics, HA and the metrics do."""
        restored = now_ms()  # the persisted state carries no time: that of learning it
        for alarm_type in active:  # the others keep theirs (cleared, or raised at this start)
            self.datatypes[alarm_metric(alarm_type)] = pb.Boolean
            self.values[alarm_metric(alarm_type)] = True
            self.stamps[alarm_metric(alarm_type)] = restored

    def restore_result(self, volume: Mapping[str, Any]) -> None:
        """Take the last result published before this start, so that the first NBIRTH after
        a restart carries it (with its capture time) instead of nulls; the run that published
        it sent its NDATA, or left it in the outbox."""
        self._remember(*_result_values(volume))

    def birth(self, bd_seq: int) -> bytes:
        """NBIRTH: seq 0, bdSeq of this session, the rebirth control and every metric, each
        stamped with when its value was measured (as its NDATA was, so a historian records it
        once); the birth time goes to the session metrics and to values never set."""
        payload = pb.Payload(timestamp=now_ms(), seq=0)
        ts = payload.timestamp
        _set_value(payload.metrics.add(name=BD_SEQ, timestamp=ts), pb.UInt64, bd_seq)
        _set_value(payload.metrics.add(name=REBIRTH, timestamp=ts), pb.Boolean, False)
        for name, datatype in self.datatypes.items():
            metric = payload.metrics.add(name=name, timestamp=self.stamps.get(name, ts))
            _set_value(metric, datatype, self.values.get(name))
        return payload.SerializeToString()

    @staticmethod
    def death(bd_seq: int) -> bytes:
        """NDEATH (the will of the Sparkplug session): only the bdSeq, no seq."""
        payload = pb.Payload(timestamp=now_ms())
        _set_value(payload.metrics.add(name=BD_SEQ), pb.UInt64, bd_seq)
        return payload.SerializeToString()

    def _remember(self, values: dict[str, Any], ts: int) -> bool:
        """Take `values`, measured at `ts`, as the current ones; True if a metric is new (it
        needs a rebirth to be declared)."""
        new_metric = False
        for name, value in values.items():
            if name not in self.datatypes:
                self.datatypes[name] = pb.Boolean if name.startswith("Alarms/") else pb.String
                new_metric = True
            self.values[name] = value
            self.stamps[name] = ts
        return new_metric

    def _data(self, values: dict[str, Any], ts: int) -> tuple[bytes, bool]:
        """NDATA without seq; also returns whether a new metric needs a rebirth first."""
        new_metric = self._remember(values, ts)
        payload = pb.Payload(timestamp=now_ms())
        for name, value in values.items():
            _set_value(payload.metrics.add(name=name, timestamp=ts), self.datatypes[name], value)
        return payload.SerializeToString(), new_metric

    def data_from_result(self, volume: Mapping[str, Any]) -> tuple[bytes, bool]:
        """NDATA of a result: `volume` is its `P/volume` payload's JSON fields."""
        return self._data(*_result_values(volume))

    def data_from_alarm(self, event: AlarmEvent) -> tuple[bytes, bool]:
        return self._data({alarm_metric(event.type): event.state == "raised"}, now_ms())

    def data_from_cameras(self, states: dict[str, str]) -> tuple[bytes, bool]:
        return self._data({camera_metric(s): v for s, v in states.items()}, now_ms())


def _result_values(summary: Mapping[str, Any]) -> tuple[dict[str, Any], int]:
    """The metrics of a scan result (a `P/volume` payload's fields) and its capture time, ms."""
    level = summary.get("level") or {}
    captured = iso_to_ms(summary["captured_at"])
    values = {
        "Inventory/Volume m3": summary.get("volume_m3"),
        "Inventory/Mass t": summary.get("mass_t"),
        "Inventory/Level Min m": level.get("min"),
        "Inventory/Level Mean m": level.get("mean"),
        "Inventory/Level Max m": level.get("max"),
        "Inventory/Coverage": summary.get("coverage"),
        "Inventory/Valid": summary.get("valid"),
        "Inventory/Degraded": summary.get("degraded", False),
        "Inventory/Capacity m3": summary.get("capacity_m3"),
        "Inventory/Fill Ratio": summary.get("fill_ratio"),
        "Inventory/Headspace m": summary.get("headspace_m"),
        "Inventory/Headspace Mean m": summary.get("headspace_mean_m"),
        "Scan/Last Id": summary["scan_id"],
        "Scan/Time": captured,
    }
    return values, captured


def finalize(
    raw: bytes, seq: int, historical: bool, declared: Collection[str]
) -> tuple[bytes | None, list[str]]:
    """Give a stored NDATA its session seq, keeping only the metrics this session's NBIRTH
    `declared` (a host rejects others; a replay can hold metrics of an earlier run's config);
    replayed data is flagged `is_historical`. Returns the payload (None: no metric left) and
    the names left out."""
    payload = pb.Payload.FromString(raw)
    kept = [m for m in payload.metrics if m.name in declared]
    left_out = [m.name for m in payload.metrics if m.name not in declared]
    if not kept:
        return None, left_out
    del payload.metrics[:]
    payload.metrics.extend(kept)
    payload.seq = seq
    if historical:
        for metric in payload.metrics:
            metric.is_historical = True
    return payload.SerializeToString(), left_out


def is_rebirth_request(raw: bytes | bytearray) -> bool:
    """An NCMD asking for `Node Control/Rebirth` = true (raw as paho hands it over)."""
    try:
        payload = pb.Payload.FromString(bytes(raw))
    except DecodeError:
        return False
    return any(m.name == REBIRTH and m.boolean_value for m in payload.metrics)
