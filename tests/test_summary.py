"""The one published summary: what every output serialises, and how it reads back."""

from __future__ import annotations

import json

import pytest

from silo_agent.analysis.alarm_types import AlarmEvent
from silo_agent.analysis.scan_analysis import analyse
from silo_agent.analysis.summary import FailedCamera, NoResult, ScanSummary, summarise
from silo_agent.config import DetectionConfig, ReconstructionConfig
from silo_agent.sim import make_scene, simulate


@pytest.fixture(scope="module")
def analysed():
    scan = simulate(make_scene("piles"), ["A1", "A5"], seed=3)
    return analyse(scan, ReconstructionConfig(), DetectionConfig())


def test_a_summary_reads_back_as_it_was_written(analysed) -> None:
    """result.json read back (replay, the Sparkplug restore, `telemetry publish`) is the same
    summary: every key, piles and camera pairs included."""
    failed = [FailedCamera("sim-A3", "timeout")]
    summary = summarise(analysed, "2026-11-22T02:00:00Z", failed, {"capture_s": 1.23456})
    text = json.dumps(summary.to_json(), allow_nan=False)
    again = ScanSummary.from_json(json.loads(text))
    assert json.dumps(again.to_json(), allow_nan=False) == text
    assert summary.timings == {"capture_s": 1.2346}
    assert summary.degraded and summary.cameras.failed == (FailedCamera("sim-A3", "timeout"),)
    assert again.piles == summary.piles and len(summary.piles) > 0


def test_a_scan_without_a_result_has_the_published_keys_only() -> None:
    """No cloud, a crash, a deadline: `P/scan` still gets every key it validates, and no
    engine details that were never computed."""
    summary = summarise(
        NoResult("silo-1-20261122T020000Z", "bicm", 0.02, "capture: no camera delivered a cloud"),
        "2026-11-22T02:00:00Z",
        [FailedCamera("cam-a", "timeout")],
        {"capture_s": 2.5},
    )
    out = summary.to_json()
    assert not {"points", "parameters", "timings_s", "robots", "registration_residual"} & set(out)
    assert out["valid"] is False and out["invalid_reason"].startswith("capture:")
    assert out["cameras"] == {"used": [], "failed": [{"serial": "cam-a", "error": "timeout"}]}
    assert out["degraded"] is True and out["piles"] == [] and out["coverage"] == 0.0
    assert ScanSummary.from_json(out) == summary


def test_an_alarm_event_is_its_json_and_back() -> None:
    """The persisted alarm state and `telemetry publish --alarm` read events back as they were
    written; details nobody set are not in the JSON (as the retained states always were)."""
    event = AlarmEvent(
        type="collapse",
        state="raised",
        severity="critical",
        scan_id="silo-1-20261122T020000Z",
        message="surface dropped",
        position=(0.4, -1.2),
        area_m2=0.35,
        threshold=0.1,
    )
    out = event.to_json()
    assert list(out) == [
        "type",
        "state",
        "severity",
        "scan_id",
        "message",
        "position",
        "area_m2",
        "threshold",
    ]
    assert out["position"] == [0.4, -1.2]
    assert AlarmEvent.from_json(json.loads(json.dumps(out))) == event
    with pytest.raises(ValueError, match=r"unknown key.*colour"):
        AlarmEvent.from_json({**out, "colour": "red"})
    with pytest.raises(ValueError, match="severity"):
        AlarmEvent.from_json({"type": "x", "state": "raised", "scan_id": None})
