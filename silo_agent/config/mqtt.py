"""`[mqtt]`: broker, TLS, Sparkplug B and Home Assistant."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    Field,
    model_validator,
)

from silo_agent.base.limits import MAX_DURATION_S, MAX_TOPIC_PREFIX_BYTES
from silo_agent.config.base import ConfigError, HostName, Strict


class MqttTlsConfig(Strict):
    """TLS to the broker; without `ca_file` the system trust store verifies the broker."""

    ca_file: Path | None = None
    cert_file: Path | None = Field(default=None, description="client certificate (PEM)")
    key_file: Path | None = Field(default=None, description="client private key (PEM)")
    key_password_file: Path | None = None
    key_password_env: str | None = None

    @model_validator(mode="after")
    def _pairs(self) -> MqttTlsConfig:
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("cert_file and key_file go together")
        if self.key_password_file is not None and self.key_password_env is not None:
            raise ValueError("give key_password_file or key_password_env, not both")
        return self


def _topic_prefix(prefix: str) -> str:
    """A prefix the agent's topics start with, as a broker takes it (MQTT 5, 4.7): a bad one
    passed every check and then nothing was ever published."""
    if not prefix:
        raise ValueError("must not be empty")
    if "\x00" in prefix:
        raise ValueError("must not contain a NUL character")
    if "+" in prefix or "#" in prefix:
        raise ValueError("must not contain a wildcard (+ or #)")
    if prefix.startswith("$"):
        raise ValueError("must not start with $ (the broker's topics, e.g. $SYS)")
    size = len(prefix.encode("utf-8"))
    if size > MAX_TOPIC_PREFIX_BYTES:
        raise ValueError(f"is {size:,} bytes long, at most {MAX_TOPIC_PREFIX_BYTES:,} are allowed")
    return prefix


TopicPrefix = Annotated[str, AfterValidator(_topic_prefix)]


class SparkplugConfig(Strict):
    """Eclipse Sparkplug B 3.0 dialect, published next to the JSON topics."""

    enabled: bool = False
    group_id: str = Field(default="silos", pattern=r"^[^#+/]+$")
    edge_node_id: str | None = Field(
        default=None, pattern=r"^[^#+/]+$", description="default: silo.id"
    )
    primary_host_id: str | None = Field(
        default=None, pattern=r"^[^#+/]+$", description="wait for this host's STATE online"
    )


class HomeAssistantConfig(Strict):
    """Home Assistant MQTT discovery (device-based)."""

    enabled: bool = False
    discovery_prefix: TopicPrefix = "homeassistant"


class MqttConfig(Strict):
    host: HostName = Field(default="127.0.0.1", description="broker name or address")
    port: int = Field(default=1883, ge=1, le=65535)
    topic_prefix: TopicPrefix = "silo"
    protocol: Literal["5", "3.1.1"] = "5"
    client_id: str | None = Field(
        default=None, min_length=1, max_length=64, description="default: silo-agent-<silo.id>"
    )
    keepalive_s: int = Field(default=30, ge=5, le=65535)
    username: str | None = None
    password_file: Path | None = None
    password_env: str | None = None
    tls: MqttTlsConfig | None = None
    reconnect_min_s: float = Field(default=1.0, gt=0, le=MAX_DURATION_S)
    reconnect_max_s: float = Field(default=60.0, gt=0, le=MAX_DURATION_S)
    max_inflight: int = Field(default=20, ge=1, le=65535)
    outbox_path: Path = Path("/var/lib/silo-agent/outbox.sqlite")
    outbox_max_messages: int = Field(default=100_000, ge=10)
    outbox_max_bytes: int = Field(default=500_000_000, ge=100_000)
    outbox_max_age_days: float = Field(default=30.0, gt=0)
    shutdown_timeout_s: float = Field(default=5.0, ge=0, le=MAX_DURATION_S)
    sparkplug: SparkplugConfig = Field(default_factory=SparkplugConfig)
    homeassistant: HomeAssistantConfig = Field(default_factory=HomeAssistantConfig)

    @model_validator(mode="after")
    def _consistent(self) -> MqttConfig:
        if self.password_file is not None and self.password_env is not None:
            raise ValueError("give password_file or password_env, not both")
        if (self.password_file is not None or self.password_env is not None) and not self.username:
            raise ValueError("a password needs a username")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("reconnect_max_s must be >= reconnect_min_s")
        return self


def read_secret(file: Path | None, env: str | None, key: str) -> str | None:
    """A password from a file (first line) or an environment variable, never from the TOML;
    ConfigError naming `key`_file or `key`_env when it cannot be read."""
    if file is not None:
        try:
            return file.read_text(encoding="utf-8").splitlines()[0].strip()
        except (OSError, IndexError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{key}_file: cannot read a password from {file}: {exc}") from None
    if env is not None:
        value = os.environ.get(env)
        if value is None:
            raise ConfigError(f"{key}_env: environment variable {env} is not set")
        return value
    return None
