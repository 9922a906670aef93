"""`[silo]`: the site: region, floor, ceiling, density, time zone."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import (
    Field,
    field_validator,
    model_validator,
)

from silo_agent.config.base import SAFE_ID, Point2, Strict
from silo_agent.grid.geometry import (
    check_polygon,
)


class SiloConfig(Strict):
    id: str = Field(pattern=SAFE_ID, description="used in topics and scan ids")
    region: list[Point2] = Field(min_length=3, description="integration polygon, silo frame")
    floor_z: float = 0.0
    ceiling_z: float | None = None
    base: Literal["floor", "boundary"] = "floor"
    bulk_density_t_m3: float | None = Field(default=None, gt=0)
    timezone: str = Field(default="UTC", description="IANA zone of schedule.cron")

    @field_validator("timezone")
    @classmethod
    def _known_zone(cls, zone: str) -> str:
        from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

        try:
            ZoneInfo(zone)
        except (ZoneInfoNotFoundError, ValueError):
            raise ValueError(f"unknown time zone {zone!r} (want an IANA name)") from None
        return zone

    @field_validator("region")
    @classmethod
    def _region_is_simple(cls, region: list[Point2]) -> list[Point2]:
        problem = check_polygon(np.asarray(region, dtype=float))
        if problem:
            raise ValueError(problem)
        return region

    @model_validator(mode="after")
    def _ceiling_above_floor(self) -> SiloConfig:
        if self.ceiling_z is not None and self.ceiling_z <= self.floor_z:
            raise ValueError(f"ceiling_z ({self.ceiling_z}) must be above floor_z ({self.floor_z})")
        return self
