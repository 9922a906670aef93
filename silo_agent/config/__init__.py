"""Configuration: pydantic models of the TOML file, and the one home of every default.

A bad file is rejected before anything starts, with the file, the key path and what was
expected (`ConfigError`, exit status 78 = EX_CONFIG). Numbers are strict (TOML types already
are): `true` or `"30"` where a number belongs is an error, an integer where a float belongs is
fine. For the service, `load_config` also checks what the file points at (directories it must
write, TLS files) so that `check-config` catches what would otherwise fail only once running.

The models live one module per section; this package's namespace is the config's public API.
"""

from silo_agent.config.alarms import AlarmsConfig
from silo_agent.config.base import SAFE_ID, ConfigError, Strict
from silo_agent.config.calibration import SPACING_SIGMA_M, CalibrationConfig, SpacingConfig
from silo_agent.config.cameras import CameraConfig, SimulationConfig
from silo_agent.config.detection import DetectionConfig, OnnxDetectionConfig
from silo_agent.config.live import LiveConfig
from silo_agent.config.loading import (
    config_warnings,
    describe_validation_error,
    environment_problems,
    load_config,
    parse_config,
)
from silo_agent.config.mqtt import HomeAssistantConfig, MqttConfig, MqttTlsConfig, SparkplugConfig
from silo_agent.config.outputs import AuditConfig, MetricsConfig
from silo_agent.config.reconstruction import ReconstructionConfig
from silo_agent.config.root import Config
from silo_agent.config.schedule import ScheduleConfig, scan_gap_s, stale_after_s
from silo_agent.config.silo import BinConfig, SiloConfig
from silo_agent.config.web import WebConfig, read_token

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
