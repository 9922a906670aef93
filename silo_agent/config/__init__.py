"""Configuration: pydantic models of the TOML file, and the one home of every default.

A bad file is rejected before anything starts, with the file, the key path and what was
expected (`ConfigError`, exit status 78 = EX_CONFIG). Numbers are strict (TOML types already
are): `true` or `"30"` where a number belongs is an error, an integer where a float belongs is
fine. For the service, `load_config` also checks what the file points at (directories it must
write, TLS files) so that `check-config` catches what would otherwise fail only once running.

The models live one module per section; this package's namespace is the config's public API.
A name is imported from its module when first asked for (PEP 562), so a caller pays only for
the sections it uses: `process` validates a scan's reconstruction, detection and calibration
settings and never builds the other sections' models (importing them all after those three:
0.018-0.024 s of CPU, one core under load, 10 fresh processes).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from silo_agent.config.alarms import AlarmsConfig
    from silo_agent.config.base import SAFE_ID, ConfigError, Strict, describe_validation_error
    from silo_agent.config.calibration import SPACING_SIGMA_M, CalibrationConfig, SpacingConfig
    from silo_agent.config.cameras import CameraConfig, SimulationConfig
    from silo_agent.config.detection import DetectionConfig, OnnxDetectionConfig
    from silo_agent.config.live import LiveConfig
    from silo_agent.config.loading import (
        config_warnings,
        environment_problems,
        load_config,
        parse_config,
    )
    from silo_agent.config.mqtt import (
        HomeAssistantConfig,
        MqttConfig,
        MqttTlsConfig,
        SparkplugConfig,
    )
    from silo_agent.config.outputs import AuditConfig, MetricsConfig
    from silo_agent.config.reconstruction import ReconstructionConfig
    from silo_agent.config.root import Config
    from silo_agent.config.schedule import ScheduleConfig, scan_gap_s, stale_after_s
    from silo_agent.config.silo import BinConfig, SiloConfig
    from silo_agent.config.web import WebConfig, read_token

# each public name -> the module of this package that defines it
_HOME = {
    "AlarmsConfig": "alarms",
    "SAFE_ID": "base",
    "ConfigError": "base",
    "Strict": "base",
    "describe_validation_error": "base",
    "SPACING_SIGMA_M": "calibration",
    "CalibrationConfig": "calibration",
    "SpacingConfig": "calibration",
    "CameraConfig": "cameras",
    "SimulationConfig": "cameras",
    "DetectionConfig": "detection",
    "OnnxDetectionConfig": "detection",
    "LiveConfig": "live",
    "config_warnings": "loading",
    "environment_problems": "loading",
    "load_config": "loading",
    "parse_config": "loading",
    "HomeAssistantConfig": "mqtt",
    "MqttConfig": "mqtt",
    "MqttTlsConfig": "mqtt",
    "SparkplugConfig": "mqtt",
    "AuditConfig": "outputs",
    "MetricsConfig": "outputs",
    "ReconstructionConfig": "reconstruction",
    "Config": "root",
    "ScheduleConfig": "schedule",
    "scan_gap_s": "schedule",
    "stale_after_s": "schedule",
    "BinConfig": "silo",
    "SiloConfig": "silo",
    "WebConfig": "web",
    "read_token": "web",
}

__all__ = [
    "SAFE_ID",
    "SPACING_SIGMA_M",
    "AlarmsConfig",
    "AuditConfig",
    "BinConfig",
    "CalibrationConfig",
    "CameraConfig",
    "Config",
    "ConfigError",
    "DetectionConfig",
    "HomeAssistantConfig",
    "LiveConfig",
    "MetricsConfig",
    "MqttConfig",
    "MqttTlsConfig",
    "OnnxDetectionConfig",
    "ReconstructionConfig",
    "ScheduleConfig",
    "SiloConfig",
    "SimulationConfig",
    "SpacingConfig",
    "SparkplugConfig",
    "Strict",
    "WebConfig",
    "config_warnings",
    "describe_validation_error",
    "environment_problems",
    "load_config",
    "parse_config",
    "read_token",
    "scan_gap_s",
    "stale_after_s",
]


def __getattr__(name: str) -> object:
    """A public name, imported from its module on first use and kept in this namespace."""
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{home}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
