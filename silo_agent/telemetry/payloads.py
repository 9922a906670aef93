"""JSON payloads of the MQTT contract (docs/mqtt.md), as pydantic models.

The models are the single source of the JSON Schemas in `config/schemas/` (see
`write_schemas`), so a payload that validates here validates for consumers too. Every
payload carries an `Envelope`: `schema` names the payload and its version, `msg_id` lets
consumers drop re-sends, `seq` orders messages across restarts, `ts` is when it was made.
"""

from __future__ import annotations

import json
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from silo_agent.analysis.alarm_types import AlarmEvent
from silo_agent.analysis.summary import ScanSummary
from silo_agent.base.limits import MAX_REQUEST_ID_CHARS

SAFE_NAME = r"^[A-Za-z0-9_-]+$"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Envelope(_Model):
    """What makes a message identifiable, orderable and de-duplicable."""

    msg_id: str = Field(description="UUID; unique per message, unchanged when re-sent")
    seq: int = Field(ge=1, description="monotonic per agent, survives restarts")
    ts: str = Field(description="RFC 3339 UTC time the message was made")

    @staticmethod
    def new(seq: int, now: datetime | None = None) -> Envelope:
        now = now or datetime.now(UTC)
        return Envelope(msg_id=str(uuid.uuid4()), seq=seq, ts=rfc3339(now))


def rfc3339(moment: datetime) -> str:
    """UTC with millisecond precision and a `Z`, the form every JSON tool parses."""
    return moment.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class Stats(_Model):
    min: float | None
    mean: float | None
    max: float | None


class SurfaceStats(_Model):
    min_z: float | None
    mean_z: float | None
    max_z: float | None


class FailedCamera(_Model):
    serial: str
    error: str


class CamerasUsed(_Model):
    used: list[str]
    failed: list[FailedCamera]


# the states and statuses the payloads allow, named for the code that passes them along
CameraStatus = Literal["ok", "failed", "disabled", "unknown"]
AgentState = Literal["online", "offline", "stopped"]
ReplyStatus = Literal["accepted", "error", "done"]


class CameraState(_Model):
    serial: str
    state: CameraStatus
    error: str | None = None


class OutboxState(_Model):
    pending: int = Field(ge=0, description="messages waiting for a broker acknowledgement")
    dropped: int = Field(ge=0, description="messages dropped by the outbox bounds, ever")
    rejected: int = Field(ge=0, description="messages the broker refused (e.g. ACL), ever")
    dead_lettered: int = Field(
        ge=0,
        description="messages that could never be published (e.g. over the broker's"
        " maximum packet size), set aside in the outbox's dead_letter table, ever",
    )


class _Payload(_Model):
    """Base of the published payloads: the envelope fields, then the subclass's `schema`."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        populate_by_name=True,
        json_schema_serialization_defaults_required=True,
    )
    msg_id: str = Field(json_schema_extra={"format": "uuid"})
    seq: int = Field(ge=1)
    ts: str = Field(json_schema_extra={"format": "date-time"})

    def to_bytes(self) -> bytes:
        return json.dumps(
            self.model_dump(mode="json", by_alias=True), allow_nan=False, separators=(",", ":")
        ).encode()


def _schema_field(name: str) -> Any:
    return Field(default=name, description="payload name/version", alias="schema")


class StatusPayload(_Payload):
    """`P/status` (retained): availability of the agent; `offline` is the Last Will."""

    schema_: Literal["silo-status/1"] = _schema_field("silo-status/1")
    state: AgentState
    version: str
    client_id: str
    cameras: list[CameraState]
    last_scan_id: str | None
    outbox: OutboxState


class VolumePayload(_Payload):
    """`P/volume` (retained): the latest result, what dashboards show."""

    schema_: Literal["silo-volume/1"] = _schema_field("silo-volume/1")
    scan_id: str
    captured_at: str
    volume_m3: float | None
    mass_t: float | None
    coverage: float = Field(ge=0, le=1)
    level: Stats = Field(description="grain level, metres above the floor")
    valid: bool
    degraded: bool
    capacity_m3: float | None = Field(
        default=None, description="bin: volume from the bottom (hopper included) to the eave"
    )
    fill_ratio: float | None = Field(default=None, description="bin: volume_m3 / capacity_m3")
    headspace_m: float | None = Field(
        default=None, description="bin: eave (or roof peak) down to the highest grain"
    )
    headspace_mean_m: float | None = Field(
        default=None, description="bin: eave (or roof peak) down to the mean grain surface"
    )


class ScanPayload(_Payload):
    """`P/scan`: one per finished scan, the whole result summary."""

    schema_: Literal["silo-scan-result/1"] = _schema_field("silo-scan-result/1")
    scan_id: str
    captured_at: str
    volume_m3: float | None
    mass_t: float | None
    coverage: float = Field(ge=0, le=1)
    grid_step_m: float = Field(gt=0)
    surface: SurfaceStats
    level: Stats
    valid: bool
    invalid_reason: str | None
    degraded: bool
    capacity_m3: float | None = None
    fill_ratio: float | None = None
    headspace_m: float | None = None
    headspace_mean_m: float | None = None
    cameras: CamerasUsed
    piles: list[dict[str, Any]]
    timings: dict[str, float]


class AlarmPayload(_Payload):
    """`P/alarm` (event) and `P/alarm/<type>` (retained current state)."""

    schema_: Literal["silo-alarm/1"] = _schema_field("silo-alarm/1")
    type: str = Field(pattern=r"^[a-z0-9_]+$")
    state: Literal["raised", "cleared"]
    severity: Literal["info", "warning", "critical"]
    scan_id: str | None
    message: str = ""
    position: tuple[float, float] | None = Field(
        default=None, description="collapse: silo-frame (x, y) of the centre, metres"
    )
    area_m2: float | None = Field(default=None, ge=0, description="collapse: affected area")
    depth_m: float | None = Field(default=None, description="collapse: deepest drop")
    volume_m3: float | None = Field(default=None, ge=0, description="collapse: volume lost")
    value: float | None = Field(default=None, description="measured value that triggered it")
    threshold: float | None = None


class CommandReplyPayload(_Payload):
    """Reply to `P/cmd/scan`: `accepted`, or an `error` naming the problem, later `scan_id`."""

    schema_: Literal["silo-cmd-reply/1"] = _schema_field("silo-cmd-reply/1")
    request_id: str | None
    status: ReplyStatus
    accepted: bool
    error: str | None = None
    scan_id: str | None = None


class ScanRequest(_Model):
    """`P/cmd/scan` request body; unknown keys are rejected so typos get an answer."""

    model_config = ConfigDict(extra="forbid", strict=True)
    request_id: Annotated[str, Field(min_length=1, max_length=MAX_REQUEST_ID_CHARS)]


PAYLOADS: dict[str, type[_Payload]] = {
    "status": StatusPayload,
    "volume": VolumePayload,
    "scan": ScanPayload,
    "alarm": AlarmPayload,
    "cmd-reply": CommandReplyPayload,
}


# ---------------------------------------------------------------- builders


def _level(summary: ScanSummary) -> Stats:
    level = summary.level
    if level is None:
        return Stats(min=None, mean=None, max=None)
    return Stats(min=level.min, mean=level.mean, max=level.max)


def volume_payload(env: Envelope, summary: ScanSummary) -> VolumePayload:
    """`P/volume` from a result summary."""
    return VolumePayload(
        **env.model_dump(),
        scan_id=summary.scan_id,
        captured_at=summary.captured_at,
        volume_m3=summary.volume_m3,
        mass_t=summary.mass_t,
        coverage=summary.coverage,
        level=_level(summary),
        valid=summary.valid,
        degraded=summary.degraded,
        capacity_m3=summary.capacity_m3,
        fill_ratio=summary.fill_ratio,
        headspace_m=summary.headspace_m,
        headspace_mean_m=summary.headspace_mean_m,
    )


def scan_payload(env: Envelope, summary: ScanSummary) -> ScanPayload:
    """`P/scan`: the summary's published part, validated."""
    surface = summary.surface
    return ScanPayload(
        **env.model_dump(),
        scan_id=summary.scan_id,
        captured_at=summary.captured_at,
        volume_m3=summary.volume_m3,
        mass_t=summary.mass_t,
        coverage=summary.coverage,
        grid_step_m=summary.grid_step_m,
        surface=SurfaceStats(min_z=None, mean_z=None, max_z=None)
        if surface is None
        else SurfaceStats(min_z=surface.min_z, mean_z=surface.mean_z, max_z=surface.max_z),
        level=_level(summary),
        valid=summary.valid,
        invalid_reason=summary.invalid_reason,
        degraded=summary.degraded,
        capacity_m3=summary.capacity_m3,
        fill_ratio=summary.fill_ratio,
        headspace_m=summary.headspace_m,
        headspace_mean_m=summary.headspace_mean_m,
        cameras=CamerasUsed(
            used=list(summary.cameras.used),
            failed=[FailedCamera(serial=f.serial, error=f.error) for f in summary.cameras.failed],
        ),
        piles=[p.to_json() for p in summary.piles],
        timings={k: float(v) for k, v in summary.timings.items()},
    )


def alarm_payload(env: Envelope, event: AlarmEvent) -> AlarmPayload:
    """An alarm event with the envelope added."""
    return AlarmPayload(**env.model_dump(), **event.to_json())


def check_summary(summary: ScanSummary) -> None:
    """Raise ValueError naming the problem if a summary cannot become the payloads."""
    env = Envelope.new(1)
    try:
        volume_payload(env, summary)
        scan_payload(env, summary)
    except ValidationError as exc:
        raise ValueError(f"result summary: {describe_errors(exc)}") from None


def describe_errors(exc: ValidationError) -> str:
    """`key: problem; key: problem`, short enough for a reply payload."""
    parts = []
    for error in exc.errors():
        path = ".".join(str(p) for p in error["loc"]) or "(payload)"
        message = "unknown field" if error["type"] == "extra_forbidden" else error["msg"]
        parts.append(f"{path}: {message}")
    return "; ".join(parts)


# ---------------------------------------------------------------- schemas


def json_schemas() -> dict[str, dict]:
    """File name -> JSON Schema of every payload, as committed in config/schemas/."""
    out = {}
    for name, model in PAYLOADS.items():
        schema = model.model_json_schema(by_alias=True, mode="serialization")
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"urn:silo-agent:schema:{model.model_fields['schema_'].default}"
        out[f"{name}.json"] = schema
    request = ScanRequest.model_json_schema()
    request["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    request["$id"] = "urn:silo-agent:schema:silo-cmd-scan/1"
    out["cmd-scan.json"] = request
    return out


def render_schema(schema: dict) -> str:
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def write_schemas(directory: Path) -> list[Path]:
    """(Re)write config/schemas/*.json from the models."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, schema in json_schemas().items():
        path = directory / name
        path.write_text(render_schema(schema), encoding="utf-8")
        written.append(path)
    return written
