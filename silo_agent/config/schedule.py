"""`[schedule]`: when scans run, and the schedule arithmetic (longest gap, staleness)."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from pydantic import (
    Field,
    field_validator,
)

from silo_agent.base.limits import MAX_DURATION_S
from silo_agent.config.base import Strict


class ScheduleConfig(Strict):
    interval_s: float | None = Field(default=None, gt=0, le=MAX_DURATION_S)
    cron: str | None = Field(default=None, description="crontab line, in silo.timezone")
    scan_at_start: bool = True
    misfire_grace_s: float = Field(
        default=300,
        gt=0,
        le=MAX_DURATION_S,
        description="a scan due this long ago (machine asleep) still runs",
    )
    scan_timeout_s: float = Field(
        default=600, gt=0, le=MAX_DURATION_S, description="overall deadline of one scan"
    )
    stop_timeout_s: float = Field(
        default=30,
        ge=0,
        le=MAX_DURATION_S,
        description="on SIGTERM, how long a running scan may finish",
    )

    @field_validator("cron")
    @classmethod
    def _valid_cron(cls, cron: str | None) -> str | None:
        if cron is None:
            return None
        from apscheduler.triggers.cron import CronTrigger

        try:
            CronTrigger.from_crontab(cron)
        except ValueError as exc:
            raise ValueError(f"not a crontab expression ({exc})") from None
        return cron


STALE_AFTER_GAPS = 2  # a reading goes stale when this many scheduled scans brought none
CRON_LOOKAHEAD_FIRES = 2000  # a week of a cron's fire times, at most, to find its longest gap


def scan_gap_s(schedule: ScheduleConfig, timezone: str) -> float | None:
    """Longest time between two scheduled scans (None: scans only at start or on request)."""
    from datetime import UTC, datetime, timedelta

    gaps = [schedule.interval_s] if schedule.interval_s is not None else []
    if schedule.cron is not None:
        from apscheduler.triggers.cron import CronTrigger

        trigger = CronTrigger.from_crontab(schedule.cron, timezone=timezone)
        fires: list[datetime] = []
        fire = trigger.get_next_fire_time(None, datetime.now(UTC))
        while fire is not None and len(fires) < CRON_LOOKAHEAD_FIRES:
            fires.append(fire)
            if fire - fires[0] > timedelta(days=8):
                break
            fire = trigger.get_next_fire_time(fire, fire)
        if len(fires) > 1:
            gaps.append(max((b - a).total_seconds() for a, b in pairwise(fires)))
    return min(gaps) if gaps else None


def stale_after_s(schedule: ScheduleConfig, timezone: str) -> int | None:
    """Seconds after which a published reading is stale (HA's `expire_after`): one scheduled
    scan may fail or be skipped, the next one, up to its deadline, must bring a new one."""
    gap = scan_gap_s(schedule, timezone)
    if gap is None:
        return None
    return int(np.ceil(STALE_AFTER_GAPS * gap + schedule.scan_timeout_s))
