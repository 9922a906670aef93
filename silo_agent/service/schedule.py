"""When scheduled scans are due, judged each turn of the main loop against both clocks.

`interval_s` runs on the monotonic clock: a step of the wall clock (NTP correcting a gateway
without a real-time clock, an operator's `date -s`) never moves it. `cron` is wall time in the
silo's zone (06:00 means 06:00): a step re-plans it from the new time, so a clock stepped back
an hour does not wait an hour past a fire time, and one stepped forward over fire times runs
one scan for them instead of none. Each step is logged. The caller passes both clocks' times
(tests step them at will).

This replaced APScheduler's BackgroundScheduler, which waited on a wall-clock deadline with a
monotonic timer: after a step back of an hour no scheduled scan ran for the rest of the run.
APScheduler's CronTrigger still computes the fire times.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from zoneinfo import ZoneInfo

import structlog

from silo_agent.config import ScheduleConfig

log = structlog.get_logger(__name__)

CLOCK_STEP_S = 2.0  # the wall clock moved this much more (or less) than the monotonic one
TICK = timedelta(microseconds=1)


class Schedule:
    """The scheduled jobs ("interval", "cron") of a `[schedule]` from the given moment on."""

    def __init__(self, cfg: ScheduleConfig, zone: ZoneInfo, wall: datetime, mono: float) -> None:
        from apscheduler.triggers.cron import CronTrigger

        self.cfg = cfg
        self._interval_at = mono + cfg.interval_s if cfg.interval_s is not None else None
        self._cron = CronTrigger.from_crontab(cfg.cron, timezone=zone) if cfg.cron else None
        self._cron_at = self._cron.get_next_fire_time(None, wall) if self._cron else None
        self._offset = wall.timestamp() - mono  # wall minus monotonic: constant but for steps

    def next_runs(self, wall: datetime, mono: float) -> dict[str, datetime]:
        """Job -> its next fire time, as wall time (for the log)."""
        runs = {}
        if self._interval_at is not None:
            runs["interval"] = wall + timedelta(seconds=self._interval_at - mono)
        if self._cron_at is not None:
            runs["cron"] = self._cron_at
        return runs

    def seconds_to_next(self, wall: datetime, mono: float) -> float | None:
        """How long the loop may sleep before a job falls due (None: no job)."""
        waits = [(at - wall).total_seconds() for at in self.next_runs(wall, mono).values()]
        return max(0.0, min(waits)) if waits else None

    def due(self, wall: datetime, mono: float) -> list[str]:
        """The jobs that fire now. A fire time missed by more than `misfire_grace_s` (the
        loop was held up) is skipped, several missed make one."""
        fired = []
        step = (wall.timestamp() - mono) - self._offset
        self._offset += step
        if abs(step) > CLOCK_STEP_S:
            fired += self._stepped(step, wall)
        grace = self.cfg.misfire_grace_s
        if self._interval_at is not None and mono >= self._interval_at:
            late = mono - self._interval_at
            interval = float(self.cfg.interval_s or 0)
            self._interval_at += (late // interval + 1) * interval
            fired += self._fire_or_skip("interval", late, grace)
        if self._cron is not None and self._cron_at is not None and wall >= self._cron_at:
            late = (wall - self._cron_at).total_seconds()
            self._cron_at = self._cron.get_next_fire_time(None, wall + TICK)
            fired += self._fire_or_skip("cron", late, grace)
        return sorted(set(fired))

    def _stepped(self, step: float, wall: datetime) -> list[str]:
        """The wall clock jumped by `step` seconds: re-plan the cron job from the new time;
        fire times a forward step jumped over run once, now."""
        jumped = self._cron_at is not None and step > 0 and self._cron_at <= wall
        if self._cron is not None:
            self._cron_at = self._cron.get_next_fire_time(None, wall)
        log.warning(
            "wall clock stepped: schedule re-planned",
            step_s=round(step, 3),
            now=wall.isoformat(),
            next_cron=self._cron_at.isoformat() if self._cron_at else None,
            jumped_over_a_cron_run=jumped,
        )
        return ["cron"] if jumped else []

    @staticmethod
    def _fire_or_skip(job: str, late: float, grace: float) -> list[str]:
        if late <= grace:
            return [job]
        log.warning("scheduled scan missed", job=job, late_s=round(late, 3), grace_s=grace)
        return []
