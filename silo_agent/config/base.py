"""Shared pieces of the config models: strict base model, the error, common field types."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
)

if TYPE_CHECKING:
    from pydantic import ValidationError

SAFE_ID = r"^[A-Za-z0-9_-]+$"


class ConfigError(Exception):
    """A configuration that cannot be used; the message names file, key and expectation."""


def describe_validation_error(exc: ValidationError, source: str) -> str:
    """One line per problem: `source: key.path: what was expected`."""
    lines = []
    for error in exc.errors():
        path = ".".join(str(p) for p in error["loc"]) or "(top level)"
        if error["type"] == "config_key":  # a cross-check raised at the top, naming its key
            path = error["ctx"]["key"]
        message = error["msg"].removeprefix("Value error, ")
        if error["type"] == "extra_forbidden":
            message = "unknown key"
        elif error["type"] == "missing":
            message = "required key is missing"
        lines.append(f"{source}: {path}: {message}")
    return "\n".join(lines)


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
