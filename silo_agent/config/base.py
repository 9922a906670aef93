"""Shared pieces of the config models: strict base model, the error, common field types."""

from __future__ import annotations

from typing import Annotated

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
)

SAFE_ID = r"^[A-Za-z0-9_-]+$"


class ConfigError(Exception):
    """A configuration that cannot be used; the message names file, key and expectation."""


class Strict(BaseModel):
    # defer_build: a model's validator is built when first used, so `process` (which validates
    # a scan's reconstruction, detection and calibration settings) does not build the rest;
    # sections default through default_factory for the same reason
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, defer_build=True)


def _host_name(host: str) -> str:
    if not host or any(c.isspace() for c in host):
        raise ValueError(f"want a host name or IP address, got {host!r}")
    return host


HostName = Annotated[str, AfterValidator(_host_name)]
Point2 = tuple[float, float]
Matrix4 = tuple[
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
]
