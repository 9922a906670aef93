"""`[live]`: camera serials checked against `[[cameras]]`, request limits, bad requests, and
where a session's unseen cells start from."""

from __future__ import annotations

import numpy as np
import pytest

from silo_agent.base.limits import MAX_COMMAND_BYTES
from silo_agent.config import ConfigError, LiveConfig, parse_config
from silo_agent.grid.grid import Grid
from silo_agent.grid.heightmap import HeightMap
from silo_agent.live.map import DepthFrame, LiveMap
from silo_agent.telemetry.live_command import LiveRequest, parse_live_request, session_limits

BASE = {
    "silo": {"id": "s", "region": [[0, 0], [1, 0], [1, 1]]},
    "cameras": [{"serial": "cam-a", "source": "sim", "view": "A1"}],
}


def test_live_cameras_must_be_configured_serials():
    config = parse_config({**BASE, "live": {"cameras": ["cam-a"], "rate_hz": 4}}, "t.toml")
    assert config.live.cameras == ["cam-a"] and config.live.rate_hz == 4
    with pytest.raises(ConfigError, match=r"t.toml: live.cameras.0: unknown camera serial 'cam-b'"):
        parse_config({**BASE, "live": {"cameras": ["cam-b"]}}, "t.toml")
    with pytest.raises(ConfigError, match=r"live.speed: unknown key"):
        parse_config({**BASE, "live": {"speed": 1}}, "t.toml")


def test_requests_within_the_configured_limits():
    settings = LiveConfig(rate_hz=2.0, duration_s=600, max_duration_s=900)
    assert session_limits(settings, LiveRequest(on=True)) == (2.0, 600)
    assert session_limits(settings, LiveRequest(on=True, rate_hz=0.5, duration_s=900)) == (0.5, 900)
    with pytest.raises(ValueError, match=r"rate_hz 3 above live\.rate_hz 2"):
        session_limits(settings, LiveRequest(on=True, rate_hz=3))
    with pytest.raises(ValueError, match=r"duration_s 901 above live\.max_duration_s 900"):
        session_limits(settings, LiveRequest(on=True, duration_s=901))


@pytest.mark.parametrize(
    ("payload", "problem"),
    [
        (b'{"on": "yes"}', "on:"),
        (b'{"rate_hz": 2}', "on: Field required"),
        (b'{"on": true, "rate_hz": 0}', "rate_hz:"),
        (b"[1]", "invalid live request"),
        (b"\xff", "invalid live request"),
        (b'{"on": true, "x": ' + b"1" * MAX_COMMAND_BYTES + b"}", "payload too large"),
    ],
)
def test_bad_requests_name_the_problem(payload: bytes, problem: str):
    with pytest.raises(ValueError, match=problem):
        parse_live_request(payload)


def test_cells_not_seen_live_start_from_the_last_full_scan():
    """A camera looking straight down sees the x < 0 half of a 2 x 2 m region, flat at z = 1;
    the other half keeps the last full scan's (sloped) heights, not the nearest seen cell's."""
    grid = Grid.over(np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]), 0.05)
    xs, _ys = grid.centres()
    scanned = HeightMap(
        grid.origin,
        grid.step,
        (0.5 + 0.1 * xs).astype(np.float32),
        np.ones(grid.shape, bool),
        grid.inside,
    )
    down = np.diag([1.0, -1.0, -1.0, 1.0])  # optical z down, image x along +x
    down[:3, 3] = (-0.5, 0.0, 3.0)  # 2 m above the plane at z = 1
    width, height, f = 100, 200, 100.0  # sees x in [-1.5, 0.5], y in [-2, 2] at 2 m: clip
    depth = np.full((height, width), 2000, dtype=np.uint16)
    u = np.arange(width)
    depth[:, (u - (width - 1) / 2) / f * 2.0 - 0.5 > -0.02] = 0  # nothing at x > -0.02
    frame = DepthFrame("cam", depth, 0.001, f, f, (width - 1) / 2, (height - 1) / 2, down)
    for start, expected_right in ((scanned, 0.5 + 0.1 * xs), (None, np.full(grid.shape, 1.0))):
        live = LiveMap(grid, LiveConfig(), None, start)
        update = live.update([frame], 0.0)
        left, right = xs < -0.1, xs > 0.1
        np.testing.assert_allclose(update.heightmap.heights[left], 1.0, atol=1e-3)
        np.testing.assert_allclose(
            update.heightmap.heights[right], expected_right[right], atol=1e-3
        )
        assert update.heightmap.observed[left].all() and not update.heightmap.observed[right].any()
