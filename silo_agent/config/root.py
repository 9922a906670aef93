"""The whole file: every section, and the checks that span sections."""

from __future__ import annotations

from typing import Annotated

from pydantic import (
    Field,
    model_validator,
)
from pydantic_core import PydanticCustomError

from silo_agent.base.limits import MAX_GRID_CELLS
from silo_agent.config.alarms import AlarmsConfig
from silo_agent.config.base import Strict
from silo_agent.config.calibration import CalibrationConfig
from silo_agent.config.cameras import CameraConfig, SimulationConfig
from silo_agent.config.detection import DetectionConfig
from silo_agent.config.live import LiveConfig
from silo_agent.config.mqtt import MqttConfig
from silo_agent.config.outputs import AuditConfig, MetricsConfig
from silo_agent.config.reconstruction import ReconstructionConfig
from silo_agent.config.schedule import ScheduleConfig
from silo_agent.config.silo import SiloConfig
from silo_agent.config.web import WebConfig
from silo_agent.grid.geometry import (
    grid_shape,
)


class Config(Strict):
    silo: SiloConfig
    reconstruction: ReconstructionConfig = Field(default_factory=ReconstructionConfig)
    detection: DetectionConfig = Field(default_factory=DetectionConfig)
    cameras: Annotated[list[CameraConfig], Field(min_length=1)]
    simulation: SimulationConfig = Field(default_factory=SimulationConfig)
    mqtt: MqttConfig = Field(default_factory=MqttConfig)
    schedule: ScheduleConfig = Field(default_factory=ScheduleConfig)
    audit: AuditConfig = Field(default_factory=AuditConfig)
    alarms: AlarmsConfig = Field(default_factory=AlarmsConfig)
    metrics: MetricsConfig = Field(default_factory=MetricsConfig)
    web: WebConfig = Field(default_factory=WebConfig)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    live: LiveConfig = Field(default_factory=LiveConfig)

    @model_validator(mode="after")
    def _grid_fits(self) -> Config:
        """The scans' grid and the live map's both within the cell limit: a live map past it
        was refused only when a session started, and that stopped the agent."""
        for key, step in (
            ("reconstruction.grid_step_m", self.reconstruction.grid_step_m),
            ("live.grid_step_m", self.live.grid_step_m),
        ):
            rows, cols = grid_shape(self.silo.region_polygon(), step)
            cells = rows * cols
            if cells > MAX_GRID_CELLS:
                raise PydanticCustomError(
                    "config_key",
                    "the region at this step is {cells} cells, more than the limit of {limit}; "
                    "use a coarser grid_step_m",
                    {"key": key, "cells": f"{cells:,}", "limit": f"{MAX_GRID_CELLS:,}"},
                )
        return self

    @model_validator(mode="after")
    def _unique_serials(self) -> Config:
        serials = [c.serial for c in self.cameras]
        dupes = sorted({s for s in serials if serials.count(s) > 1})
        if dupes:
            raise ValueError(f"camera serials must be unique, repeated: {', '.join(dupes)}")
        known = set(serials)
        for k, spacing in enumerate(self.calibration.spacing):
            for key in ("a", "b"):
                serial = getattr(spacing, key)
                if serial not in known:
                    raise PydanticCustomError(
                        "config_key",
                        "unknown camera serial '{serial}', expected the serial of one of the "
                        "[[cameras]] ({known})",
                        {
                            "key": f"calibration.spacing.{k}.{key}",
                            "serial": serial,
                            "known": ", ".join(serials),
                        },
                    )
        for k, serial in enumerate(self.live.cameras or []):
            if serial not in known:
                raise PydanticCustomError(
                    "config_key",
                    "unknown camera serial '{serial}', expected the serial of one of the "
                    "[[cameras]] ({known})",
                    {"key": f"live.cameras.{k}", "serial": serial, "known": ", ".join(serials)},
                )
        return self
