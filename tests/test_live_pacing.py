"""Live maps are paced by capture time and sent as soon as they are built: one slow map (a
model run, a loaded gateway) does not leave every later map waiting as old as it was, and no
two maps go out closer than a period, neither from the session nor on the wire.

Timing is real (monotonic clocks at the events); the bounds leave a loaded 2-core machine
room: the failures they catch are a period apart from the behaviour they want."""

from __future__ import annotations

import itertools
import threading
from dataclasses import dataclass, field

import numpy as np
import pytest

from silo_agent.config import Config, parse_config
from silo_agent.live.map import DepthFrame
from silo_agent.live.session import LiveSession
from silo_agent.sim.robot import RobotRig
from tests.support.mqtt import BASE

RATE_HZ = 2.0
PERIOD_S = 1.0 / RATE_HZ
SLOW_S = 0.8  # the first map's capture: longer than a period
MAPS = 14


@dataclass
class SlowFirstSource:
    """The robot rig's frames, rendered once; the first capture takes SLOW_S (a model's first
    run, a busy gateway). Records when each capture began."""

    frames_once: list[DepthFrame]
    captures: list[float] = field(default_factory=list)

    def frames(self, elapsed_s: float, color: bool = False) -> list[DepthFrame]:
        import time

        self.captures.append(time.monotonic())
        if len(self.captures) == 1:
            threading.Event().wait(SLOW_S)  # the slow capture itself, not a synchronisation
        return self.frames_once

    def close(self) -> None:
        """Nothing to release."""


@pytest.fixture(scope="module")
def rig_frames() -> tuple[RobotRig, list[DepthFrame]]:
    rig = RobotRig(width=212, height=120, mesh_step=0.03)
    frames = [
        DepthFrame.rendered(v.serial, f, v.nominal)
        for v, f in zip(rig.views, rig.frames(0.0), strict=True)
    ]
    return rig, frames


def config_for(rig: RobotRig) -> Config:
    site = rig.robot.base.site
    cameras = [
        {"serial": v.serial, "source": "sim", "view": v.key, "width": 212, "height": 120}
        for v in rig.views
    ]
    data = {
        "silo": {"id": "pace", "region": site.region.tolist(), "ceiling_z": site.ceiling_z},
        "cameras": cameras,
        "live": {"grid_step_m": 0.05},
    }
    return parse_config(data, "test")


def test_maps_go_out_as_soon_as_built_after_a_slow_one_and_never_closer_than_a_period(
    rig_frames,
) -> None:
    import time

    rig, frames = rig_frames
    source = SlowFirstSource(frames)
    sent: list[float] = []
    done = threading.Event()

    def publish(_payload: bytes, period: float) -> None:
        assert period == PERIOD_S
        sent.append(time.monotonic())
        if len(sent) >= MAPS:
            done.set()

    session = LiveSession(
        config_for(rig),
        "pace-1",
        RATE_HZ,
        120.0,
        publish,
        lambda _reason: done.set(),
        open_frames=lambda _config: source,
    )
    session.start()
    try:
        assert done.wait(60), f"{len(sent)} maps in 60 s"
    finally:
        session.stop("test over")
    captures = source.captures[: len(sent)]
    ages = np.subtract(sent, captures)
    # never two maps, nor two captures, closer than a period (the session's own clock)
    assert min(b - a for a, b in itertools.pairwise(sent)) >= PERIOD_S - 1e-3
    assert min(b - a for a, b in itertools.pairwise(captures)) >= PERIOD_S - 1e-3
    # after the slow one, maps go out at their build time, not at the slow map's age (before
    # the fix every later map was held about SLOW_S - PERIOD_S... PERIOD_S old)
    later = ages[3:]
    assert np.mean(later >= PERIOD_S / 2) <= 0.1, np.round(ages, 3).tolist()
    assert float(np.median(later)) < PERIOD_S / 4, np.round(ages, 3).tolist()


def test_the_network_thread_keeps_live_maps_a_period_apart_on_the_wire(
    broker, telemetry_factory, collector_factory
) -> None:
    """Two maps handed over back to back: the second goes out a period after the first, not
    at the network thread's next turn."""
    live = f"{BASE}/heightmap/live"
    got = collector_factory(broker, [live])
    tel = telemetry_factory(broker)
    period = 1.0
    tel.publish_live(b"map-1", period)
    (first,) = got.wait_topic(live)
    tel.publish_live(b"map-2", period)
    second = got.wait_topic(live, 2)[1]
    assert second.payload == b"map-2"
    assert second.at - first.at >= period / 2  # ~ 1 s; without the pacing ~ 0.01 s
