"""The schedule against both clocks: interval on the monotonic one, cron on the wall one,
re-planned (and logged) when the wall clock steps. Unit cases step an injected clock; one
end-to-end case steps the daemon's real wall clock with libfaketime."""

from __future__ import annotations

import os
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from zoneinfo import ZoneInfo

import pytest
from structlog.testing import capture_logs

from silo_agent.config import ScheduleConfig
from silo_agent.service.schedule import Schedule
from tests.support.agent import Daemon, write_config

NOON = datetime(2026, 11, 22, 12, 5, tzinfo=UTC)
FAKETIME = next(Path("/usr/lib").glob("*/faketime/libfaketime.so.1"), Path("libfaketime.so.1"))


def schedule(**cfg) -> tuple[Schedule, ScheduleConfig]:
    config = ScheduleConfig.model_validate(cfg)
    return Schedule(config, ZoneInfo("UTC"), NOON, 0.0), config


def test_cron_runs_in_the_site_time_zone():
    config = ScheduleConfig.model_validate({"cron": "0 6 * * *", "interval_s": 3600})
    plan = Schedule(config, ZoneInfo("Australia/Adelaide"), NOON, 0.0)
    runs = plan.next_runs(NOON, 0.0)
    assert str(runs["cron"].tzinfo) == "Australia/Adelaide"
    assert (runs["cron"].hour, runs["cron"].minute) == (6, 0)
    assert runs["interval"] == NOON + timedelta(hours=1)


def test_interval_runs_on_the_monotonic_clock_whatever_the_wall_clock_does():
    plan, _ = schedule(interval_s=60)
    with capture_logs() as logs:
        assert plan.due(NOON - timedelta(hours=1), 30.0) == []  # stepped back an hour
        assert plan.due(NOON - timedelta(hours=1) + timedelta(seconds=30), 60.0) == ["interval"]
        assert plan.due(NOON + timedelta(hours=5), 90.0) == []  # forward five hours
        assert plan.due(NOON + timedelta(hours=5, seconds=30), 120.0) == ["interval"]
    steps = [e["step_s"] for e in logs if e["event"].startswith("wall clock stepped")]
    assert steps == [pytest.approx(-3630), pytest.approx(6 * 3600 - 60)]


def test_cron_follows_the_wall_clock_back_and_forward():
    plan, _ = schedule(cron="*/10 * * * *")  # 12:10, 12:20, ...
    with capture_logs() as logs:
        back = NOON - timedelta(hours=1)  # 11:05: the next run is 11:10, not 12:10
        assert plan.due(back + timedelta(seconds=1), 1.0) == []
        assert plan.next_runs(back, 1.0)["cron"] == datetime(2026, 11, 22, 11, 10, tzinfo=UTC)
        assert plan.due(back + timedelta(minutes=5), 300.0) == ["cron"]
        # forward over 11:20 .. 12:10: one run for all of them, now, then 12:20
        ahead = datetime(2026, 11, 22, 12, 12, tzinfo=UTC)
        assert plan.due(ahead, 310.0) == ["cron"]
        assert plan.next_runs(ahead, 310.0)["cron"] == datetime(2026, 11, 22, 12, 20, tzinfo=UTC)
        assert plan.due(ahead + timedelta(seconds=5), 315.0) == []
    stepped = [e for e in logs if e["event"].startswith("wall clock stepped")]
    assert [e["jumped_over_a_cron_run"] for e in stepped] == [False, True]


def test_a_run_missed_beyond_the_grace_is_skipped_and_several_coalesce():
    plan, _ = schedule(interval_s=10, misfire_grace_s=30)
    assert plan.due(NOON + timedelta(seconds=25), 25.0) == ["interval"]  # 10 and 20: one run
    assert plan.next_runs(NOON + timedelta(seconds=25), 25.0)["interval"] == NOON + timedelta(
        seconds=30
    )
    with capture_logs() as logs:
        assert plan.due(NOON + timedelta(seconds=95), 95.0) == []  # the loop was held 65 s
    assert [e["event"] for e in logs] == ["scheduled scan missed"]
    assert plan.due(NOON + timedelta(seconds=100), 100.0) == ["interval"]


STEPPED = "wall clock stepped: schedule re-planned"


def _wait_step(agent: Daemon, logged: int, step: float, timeout: float = 30) -> None:
    """Until a step of `step` s is logged after the first `logged` steps. A clock call that
    opened libfaketime's file just before it was replaced can read the old offset once more
    (a loaded machine stalls it there: seen in CI), which the daemon rightly logs as a step
    there and back; those may come first."""
    end = time.monotonic() + timeout
    while True:
        new = agent.wait_log(STEPPED, logged + 1, timeout)[logged:]
        if any(e["step_s"] == pytest.approx(step, abs=5) for e in new):
            return
        assert time.monotonic() < end, f"no step of {step} s among {new}"
        logged += len(new)


@pytest.mark.slow
def test_the_daemon_keeps_its_schedule_across_real_clock_steps(tmp_path):
    """libfaketime steps the daemon's wall clock (only its own: the monotonic clock is left
    alone) back an hour and forward again: scheduled scans go on, each step is logged."""
    assert FAKETIME.exists(), "needs Debian's faketime: `make system-deps` installs it"
    offset = tmp_path / "faketime"
    offset.write_text("+0\n")
    config = write_config(
        tmp_path / "agent.toml", 1, tmp_path, schedule={"interval_s": 1.5, "scan_at_start": False}
    )
    env = {
        "LD_PRELOAD": str(FAKETIME),
        "FAKETIME_TIMESTAMP_FILE": str(offset),
        "FAKETIME_NO_CACHE": "1",
        "FAKETIME_DONT_FAKE_MONOTONIC": "1",
    }
    agent = Daemon(config, tmp_path, env=env)
    try:
        agent.wait_log("scan finished", 1, timeout=60)
        for step, shift in ((-3600, "-3600"), (3600, "+0")):
            before = len(agent.wait_log("scan started"))
            logged = len([e for e in agent.log() if e.get("event") == STEPPED])
            # replaced, not rewritten: libfaketime re-reads the file at every clock call and
            # must never see it truncated
            (tmp_path / "faketime.new").write_text(f"{shift}\n")
            os.replace(tmp_path / "faketime.new", offset)
            _wait_step(agent, logged, step)
            agent.wait_log("scan started", before + 2, timeout=30)
    finally:
        agent.kill()
    assert os.environ.get("LD_PRELOAD") != str(FAKETIME)  # the test process was never faked
    assert time.time() > NOON.timestamp()
