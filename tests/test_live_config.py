"""`[live]`: defaults in config.py, camera serials checked against `[[cameras]]`, request limits."""

from __future__ import annotations

import pytest

from silo_agent.config import ConfigError, LiveConfig, parse_config
from silo_agent.live.command import LiveRequest, parse_live_request, session_limits

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


@pytest.mark.parametrize(("payload", "problem"), [
    (b'{"on": "yes"}', "on:"),
    (b'{"rate_hz": 2}', "on: Field required"),
    (b'{"on": true, "rate_hz": 0}', "rate_hz:"),
    (b"[1]", "invalid live request"),
    (b"\xff", "invalid live request"),
    (b'{"on": true, "x": ' + b"1" * 5000 + b"}", "payload too large"),
])
def test_bad_requests_name_the_problem(payload: bytes, problem: str):
    with pytest.raises(ValueError, match=problem):
        parse_live_request(payload)
