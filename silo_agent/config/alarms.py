"""`[alarms]`: alarm thresholds."""

from __future__ import annotations

from pydantic import (
    Field,
)

from silo_agent.config.base import Strict


class AlarmsConfig(Strict):
    """Alarm thresholds (silo_agent/analysis/alarms.py); each raises and clears with hysteresis."""

    enabled: bool = True
    collapse_depth_m: float = Field(default=0.10, gt=0, description="drop vs the baseline")
    collapse_min_area_m2: float = Field(default=0.25, gt=0, description="smallest collapse")
    collapse_noise_k: float = Field(
        default=5.0, gt=0, description="a drop must also exceed k x the maps' noise sigma"
    )
    baseline_scan_id: str | None = Field(
        default=None,
        pattern=r"^[A-Za-z0-9_.-]+$",
        description="pin the collapse baseline to this cached scan; default the last valid scan",
    )
    high_level_margin_m: float | None = Field(
        default=0.30, gt=0, description="level_high when the surface is this close to ceiling_z"
    )
    low_volume_m3: float | None = Field(default=None, ge=0, description="level_low below this")
    change_fraction: float | None = Field(
        default=0.20, gt=0, description="change: volume moved by more than this share in a scan"
    )
    min_coverage: float = Field(default=0.30, ge=0, le=1, description="coverage fault below")
    hysteresis: float = Field(
        default=0.5,
        gt=0,
        lt=1,
        description="an active alarm clears only when its measure falls below this share "
        "of the raise threshold (level: this share of the margin further away)",
    )
