"""The calibration_drift detector: residuals over N scans in a row, IMU gravity vs extrinsic."""

from __future__ import annotations

import numpy as np
import pytest

from silo_agent.analysis.drift import DriftMonitor, DriftState, drift_step
from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.reconstruct import reconstruct
from silo_agent.scan import CameraCloud, gravity_angles
from silo_agent.sim.layouts import look_at, view_pose
from tests.support.calib import knocked, render, rig

SETTINGS = CalibrationConfig(drift_threshold_m=0.005, drift_consecutive=3)


def test_raised_after_n_scans_in_a_row_and_cleared_after_n_under() -> None:
    state = DriftState()
    kinds = []
    for value in [0.009, 0.002, 0.009, 0.009, 0.009, 0.009, 0.001, 0.009, 0.001, 0.001, 0.001]:
        state, events = drift_step(state, {"a|b": value}, {}, SETTINGS)
        kinds.append([e.kind for e in events])
    assert kinds == [[], [], [], [], ["raised"], [], [], [], [], [], ["cleared"]]
    assert state.raised == frozenset()


def test_a_missing_pair_keeps_its_alarm_and_state_round_trips() -> None:
    state = DriftState()
    for _ in range(3):
        state, events = drift_step(state, {"a|b": -0.02}, {}, SETTINGS)
    assert [e.key for e in events] == ["residual:a|b"] and events[0].cameras == ("a", "b")
    state, events = drift_step(state, {}, {}, SETTINGS)  # pair not seen this scan
    assert events == [] and state.raised == {"residual:a|b"}
    assert DriftState.from_json(state.to_json()) == state


@pytest.mark.parametrize("axis", ["pitch", "yaw"])
def test_fires_for_a_camera_turned_by_one_degree(axis: str) -> None:
    nominal = view_pose(rig().scene, "A3")
    camera_axis = (1.0, 0.0, 0.0) if axis == "pitch" else tuple(nominal[:3, :3].T @ [0, 0, 1])
    true = {"A3": knocked(nominal, 1.0, camera_axis)}
    monitor = DriftMonitor(SETTINGS, gravity_tolerance_deg=3.0)
    raised_at = []
    for seed in range(3):
        scan = render(["A1", "A3"], seed, true)
        result = reconstruct(scan, ReconstructionConfig())
        events = monitor.update(result.registration, scan.cameras)
        raised_at += [(seed, e.key) for e in events if e.kind == "raised"]
    assert raised_at == [(2, "residual:sim-A1|sim-A3")]


@pytest.mark.slow
def test_quiet_on_repeated_scans_of_an_unchanged_scene() -> None:
    monitor = DriftMonitor(SETTINGS, gravity_tolerance_deg=0.5)
    for seed in range(5):
        scan = render(["A1", "A3", "A5", "A7"], seed)
        result = reconstruct(scan, ReconstructionConfig())
        assert monitor.update(result.registration, scan.cameras) == []
    assert monitor.active == frozenset()
    assert len([k for k in monitor.state.runs if k.startswith("residual:")]) == 6


def _camera_with_gravity(extrinsic: np.ndarray, true_rotation: np.ndarray) -> CameraCloud:
    """A camera whose IMU (gravity, down, camera axes) reads its true rotation's gravity."""
    gravity = true_rotation.T @ np.array([0.0, 0.0, -9.80665])
    return CameraCloud(
        "cam", np.zeros((1, 3), np.float32), extrinsic, extra={"gravity": gravity.tolist()}
    )


def test_gravity_vector_disagreeing_with_the_extrinsic() -> None:
    extrinsic = look_at(np.array([0.0, -2.5, 2.0]), np.array([0.0, 0.0, 0.0]))
    # turned 2 degrees about its own x axis (horizontal for a camera without roll)
    c, s = np.cos(np.radians(2.0)), np.sin(np.radians(2.0))
    pitch = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    knocked_camera = _camera_with_gravity(extrinsic, extrinsic[:3, :3] @ pitch)
    level_camera = _camera_with_gravity(extrinsic, extrinsic[:3, :3])
    assert gravity_angles([knocked_camera])["cam"] == pytest.approx(2.0, abs=1e-6)
    assert gravity_angles([level_camera])["cam"] == pytest.approx(0.0, abs=1e-4)

    state, raised = DriftState(), []
    for _ in range(3):
        state, events = drift_step(
            state, {}, gravity_angles([knocked_camera]), SETTINGS, {"cam": 1.5}
        )
        raised += events
    assert [(e.kind, e.key) for e in raised] == [("raised", "gravity:cam")]
    assert raised[0].value == pytest.approx(2.0, abs=1e-6)
    quiet = DriftState()
    for _ in range(5):
        quiet, events = drift_step(quiet, {}, gravity_angles([knocked_camera]), SETTINGS, 3.0)
        assert events == []


def test_simulated_imu_sees_a_knocked_camera() -> None:
    nominal = view_pose(rig().scene, "A3")
    scan = render(["A3"], 0, {"A3": knocked(nominal, 1.0, (1.0, 0.0, 0.0))})
    assert gravity_angles(scan.cameras)["sim-A3"] == pytest.approx(1.0, abs=1e-6)


def test_the_calibration_alarm_follows_the_drift_detector() -> None:
    from silo_agent.analysis.alarms import AlarmState, Inputs, evaluate
    from silo_agent.config import AlarmsConfig
    from silo_agent.telemetry.payloads import Envelope, alarm_payload

    state, seen, published = AlarmState(), [], []
    for k, residual in enumerate([0.02, 0.02, 0.02, 0.02, 0.001, 0.001, 0.001]):
        inputs = Inputs(
            scan_id=f"s{k}",
            heightmap=None,
            volume_m3=None,
            coverage=1.0,
            valid=True,
            registration_residual_m={"a|b": residual},
            gravity_deg={"a": 0.1},
            gravity_tolerance_deg={"a": 3.0},
        )
        events, state = evaluate(state, inputs, AlarmsConfig(), detectors={}, calibration=SETTINGS)
        seen += [(k, e.type, e.state) for e in events]
        published += [alarm_payload(Envelope.new(k + 1), e) for e in events]  # as MQTT does
        state = AlarmState.from_json(state.to_json())  # as the agent persists it
    assert seen == [(2, "calibration", "raised"), (6, "calibration", "cleared")]
    assert published[0].value == pytest.approx(0.02) and "a|b" in published[0].message
    events, _ = evaluate(AlarmState(), inputs, AlarmsConfig(), detectors={})
    assert events == []  # without calibration settings the detector does not run
