"""`[silo]`: the site: region, floor, ceiling, density, time zone; `[silo.bin]`: the bin's
known wall, eave and bottom (grid/bin_shape.py)."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import (
    Field,
    field_validator,
    model_validator,
)

from silo_agent.base.limits import MAX_COORDINATE_M
from silo_agent.config.base import SAFE_ID, Point2, Strict
from silo_agent.grid.bin_shape import BinShape
from silo_agent.grid.geometry import (
    check_polygon,
)


class BinConfig(Strict):
    """A storage bin's geometry: a round wall (centre, diameter) or a wall polygon; the eave;
    a flat floor, a conical hopper or a sloped floor. Heights are above `silo.floor_z`."""

    diameter_m: float | None = Field(default=None, gt=0, description="round bin: wall diameter")
    centre: Point2 = Field(default=(0.0, 0.0), description="round bin: wall centre, silo frame")
    wall: list[Point2] | None = Field(
        default=None, min_length=3, description="a polygon bin's wall instead of diameter_m"
    )
    eave_height_m: float = Field(gt=0, description="eave (top of the wall) above floor_z")
    floor: Literal["flat", "hopper", "sloped"] = "flat"
    hopper_depth_m: float | None = Field(
        default=None, gt=0, description="hopper: floor plane down to the outlet"
    )
    hopper_angle_deg: float | None = Field(
        default=None, gt=0, lt=90, description="hopper: cone slope from the horizontal, or depth"
    )
    outlet_diameter_m: float = Field(default=0.3, gt=0, description="hopper: outlet diameter")
    floor_slope_deg: float = Field(default=0.0, ge=0, lt=60, description="sloped floor: tilt")
    floor_downhill_deg: float = Field(
        default=0.0, description="sloped floor: direction it falls to (0 = +x, ccw)"
    )
    roof_pitch_deg: float = Field(default=30.0, ge=0, lt=80)
    headspace_from: Literal["eave", "roof"] = Field(
        default="eave", description="headspace is measured from the eave or the roof peak"
    )

    def shape(self, floor_z: float) -> BinShape:
        depth = self.hopper_depth_m or 0.0
        if self.floor == "hopper" and self.hopper_angle_deg is not None and self.diameter_m:
            run = (self.diameter_m - self.outlet_diameter_m) / 2
            depth = run * float(np.tan(np.radians(self.hopper_angle_deg)))
        return BinShape(
            floor_z=floor_z,
            eave_z=floor_z + self.eave_height_m,
            centre=self.centre,
            diameter_m=self.diameter_m,
            wall=tuple(self.wall) if self.wall is not None else None,
            floor=self.floor,
            hopper_depth_m=depth if self.floor == "hopper" else 0.0,
            outlet_diameter_m=self.outlet_diameter_m if self.floor == "hopper" else 0.0,
            floor_slope_deg=self.floor_slope_deg,
            floor_downhill_deg=self.floor_downhill_deg,
            roof_pitch_deg=self.roof_pitch_deg,
            headspace_from=self.headspace_from,
        )

    @model_validator(mode="after")
    def _consistent(self) -> BinConfig:
        if self.floor == "hopper" and (self.hopper_depth_m is None) == (
            self.hopper_angle_deg is None
        ):
            raise ValueError("a hopper floor needs one of hopper_depth_m or hopper_angle_deg")
        for key, problem in self.shape(0.0).problems():
            raise ValueError(f"{key}: {problem}")
        return self


class SiloConfig(Strict):
    id: str = Field(pattern=SAFE_ID, description="used in topics and scan ids")
    region: list[Point2] | None = Field(
        default=None,
        min_length=3,
        description="integration polygon, silo frame; default: the bin's wall",
    )
    bin: BinConfig | None = Field(default=None, description="the bin's wall, eave and bottom")
    # the bound a scan's manifest holds them to: a scan written from the config must read back
    floor_z: float = Field(default=0.0, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)
    ceiling_z: float | None = Field(default=None, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)
    base: Literal["floor", "boundary"] = "floor"
    bulk_density_t_m3: float | None = Field(default=None, gt=0)
    timezone: str = Field(default="UTC", description="IANA zone of schedule.cron")

    @field_validator("timezone")
    @classmethod
    def _known_zone(cls, zone: str) -> str:
        from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

        try:
            ZoneInfo(zone)
        except (ZoneInfoNotFoundError, ValueError, OSError):  # OSError: a name too long for a file
            raise ValueError(f"unknown time zone {zone!r} (want an IANA name)") from None
        return zone

    @field_validator("region")
    @classmethod
    def _region_is_simple(cls, region: list[Point2] | None) -> list[Point2] | None:
        problem = check_polygon(np.asarray(region, dtype=float)) if region is not None else None
        if problem:
            raise ValueError(problem)
        return region

    @model_validator(mode="after")
    def _ceiling_above_floor(self) -> SiloConfig:
        if self.ceiling_z is not None and self.ceiling_z <= self.floor_z:
            raise ValueError(f"ceiling_z ({self.ceiling_z}) must be above floor_z ({self.floor_z})")
        if self.region is None and self.bin is None:
            raise ValueError(
                "region: give the integration polygon, or a [silo.bin] to use its wall"
            )
        shape = self.bin_shape()
        if shape is not None and self.region is not None:
            problem = shape.region_problem(np.asarray(self.region, dtype=float))
            if problem:
                raise ValueError(f"region: {problem}")
        return self

    def bin_shape(self) -> BinShape | None:
        """The bin's geometry in the silo frame, if the config has one."""
        return self.bin.shape(self.floor_z) if self.bin is not None else None

    def region_polygon(self) -> np.ndarray:
        """The integration polygon: `region`, or the bin's wall."""
        if self.region is not None:
            return np.asarray(self.region, dtype=float)
        shape = self.bin_shape()
        assert shape is not None  # checked above: one of them is given
        return shape.wall_polygon()
