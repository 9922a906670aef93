"""`P/cmd/live`: the request body, its limits, and the accepted command the agent answers."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from silo_agent.base.limits import (
    MAX_COMMAND_BYTES,
    MAX_DURATION_S,
    MAX_REQUEST_ID_CHARS,
    MIN_LIVE_RATE_HZ,
)
from silo_agent.config import LiveConfig


class LiveRequest(BaseModel):
    """`P/cmd/live` body: `{"on": true, "rate_hz": 2, "duration_s": 600}` or `{"on": false}`."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)
    on: bool
    rate_hz: Annotated[float, Field(ge=MIN_LIVE_RATE_HZ)] | None = None
    duration_s: Annotated[float, Field(gt=0, le=MAX_DURATION_S)] | None = None
    request_id: Annotated[str, Field(min_length=1, max_length=MAX_REQUEST_ID_CHARS)] | None = None


def parse_live_request(payload: bytes | bytearray) -> LiveRequest:
    """The request, or a ValueError whose message says what is wrong with it in one line."""
    if len(payload) > MAX_COMMAND_BYTES:
        raise ValueError(f"payload too large: {len(payload)} bytes, limit {MAX_COMMAND_BYTES}")
    try:
        return LiveRequest.model_validate_json(payload)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'body'}: {e['msg']}" for e in exc.errors()
        )
        raise ValueError(f"invalid live request: {problems}") from None


def session_limits(settings: LiveConfig, request: LiveRequest) -> tuple[float, float]:
    """(rate_hz, duration_s) of a request within `[live]`: a ValueError names a limit passed."""
    rate = request.rate_hz if request.rate_hz is not None else settings.rate_hz
    duration = request.duration_s if request.duration_s is not None else settings.duration_s
    if rate > settings.rate_hz:
        raise ValueError(f"rate_hz {rate:g} above live.rate_hz {settings.rate_hz:g}")
    if duration > settings.max_duration_s:
        raise ValueError(
            f"duration_s {duration:g} above live.max_duration_s {settings.max_duration_s:g}"
        )
    return rate, duration


@dataclass(frozen=True)
class LiveCommand:
    """An accepted `P/cmd/live` request, kept to send the session's final reply."""

    request: LiveRequest
    reply_topic: str
    correlation: bytes | None
