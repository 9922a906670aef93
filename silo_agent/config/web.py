"""`[web]`: the operator's read-only page (silo_agent/web, docs/web.md) and its access token."""

from __future__ import annotations

import ipaddress
from pathlib import Path

from pydantic import Field, model_validator
from pydantic_core import PydanticCustomError

from silo_agent.config.base import HostName, Strict


def is_loopback(host: str) -> bool:
    """`localhost` or an address in 127.0.0.0/8 or ::1: reachable from this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class WebConfig(Strict):
    """The operator's page; off by default."""

    enabled: bool = False
    host: HostName = Field(default="127.0.0.1", description="listen address")
    port: int = Field(default=8464, ge=1, le=65535)
    token_file: Path | None = Field(
        default=None,
        description="file holding the access token every request must carry; required when "
        "host is not a loopback address",
    )

    @model_validator(mode="after")
    def _token_beyond_loopback(self) -> WebConfig:
        if self.enabled and self.token_file is None and not is_loopback(self.host):
            raise PydanticCustomError(
                "config_key",
                "listening on {host} (beyond this machine) needs a token_file: without one "
                "anyone on the network could read the silo's data",
                {"key": "web.token_file", "host": self.host},
            )
        return self


def read_token(path: Path) -> str:
    """The web access token: the file's text without surrounding whitespace. ValueError if it
    is not UTF-8 or not one word; OSError if it cannot be read."""
    try:
        token = path.read_bytes().decode("utf-8").strip()
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not UTF-8 text") from None
    if any(c.isspace() for c in token):
        raise ValueError(f"{path}: the token must be one word (no spaces or line breaks)")
    return token


def token_problem(path: Path) -> str | None:
    """Why the web token in `path` cannot be used (unreadable, empty, not one word), or None."""
    try:
        token = read_token(path)
    except ValueError as exc:
        return str(exc)
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    return None if token else f"{path} is empty"
