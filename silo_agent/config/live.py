"""`[live]`: the live height map a leveling robot follows."""

from __future__ import annotations

from typing import Literal

from pydantic import (
    Field,
)

from silo_agent.base.choices import DEFAULT_GRID_STEP_M
from silo_agent.base.limits import MAX_DURATION_S, MIN_LIVE_RATE_HZ
from silo_agent.config.base import Strict


class LiveConfig(Strict):
    """`[live]`: the live height map a leveling robot follows (`P/cmd/live`, `P/heightmap/live`)."""

    rate_hz: float = Field(
        default=2.0, ge=MIN_LIVE_RATE_HZ, le=10, description="maps per second, at most"
    )
    grid_step_m: float = Field(default=DEFAULT_GRID_STEP_M, gt=0.005, le=0.5)
    cameras: list[str] | None = Field(
        default=None, description="serials of the cameras used; default all [[cameras]]"
    )
    duration_s: float = Field(
        default=600.0, gt=0, le=MAX_DURATION_S, description="a session without duration_s"
    )
    max_duration_s: float = Field(
        default=3600.0, gt=0, le=MAX_DURATION_S, description="longest session allowed"
    )
    decimation: int = Field(default=1, ge=1, le=8, description="depth pixels step per axis")
    smoothing: float = Field(
        default=0.3, gt=0, le=1, description="weight of the newest frame in a cell's running value"
    )
    reset_m: float = Field(
        default=0.07, gt=0, description="a confirmed frame this far from a cell's value replaces it"
    )
    change_m: float = Field(
        default=0.02, gt=0, description="a cell this far from its last reported value is changed"
    )
    stale_s: float = Field(
        default=3.0, gt=0, description="a cell not measured for this long is not `observed`"
    )
    robot_min_height_m: float = Field(
        default=0.15, gt=0, description="a robot stands at least this far above the local grain"
    )
    robot_radius_m: float = Field(
        default=0.4, gt=0, description="the robot's half diagonal: held around its centre"
    )
    robot_margin_m: float = Field(
        default=0.15, ge=0, description="kept out of the map around the robot's footprint"
    )
    hold_ahead_s: float = Field(
        default=1.0,
        ge=0,
        description="cells the robot will reach within this time, at its tracked speed, are held",
    )
    coverage_check: bool = Field(
        default=True,
        description="refuse a session whose cameras cannot keep the robot out (docs/mqtt.md)",
    )
    edge_disparity_px: float = Field(
        default=0.5,
        gt=0,
        description="depth edge: 3 x 3 disparity range above this; its mixed pixels are dropped",
    )
    model_rate_hz: float = Field(
        default=1.0,
        ge=MIN_LIVE_RATE_HZ,
        le=10,
        description="runs per second, at most, of [detection.onnx]'s model on the colour frames",
    )
    qos: Literal[0, 1] = 0
