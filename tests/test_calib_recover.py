"""Calibration recovers known placement errors on simulated scans, and refuses large ones."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from silo_agent.calibrate import (
    CalibrationError,
    calibrate,
    fit_plane,
    floor_points,
    level_scan,
    refine,
    with_extrinsics,
)
from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.reconstruct import reconstruct
from silo_agent.sim.grains import grain
from silo_agent.sim.layouts import perturb, view_pose
from silo_agent.sim.scenes import bin_scene, make_scene
from silo_agent.sim.simulate import SimRig, simulate
from tests.support.calib import knocked, render, rig

VIEWS = ["A1", "A3"]


@pytest.fixture(scope="module")
def perturbed():
    """A scan whose cameras really sit 0.5 deg / 1 cm off their (nominal) extrinsics."""
    true = {}
    for k, view in enumerate(VIEWS):
        nominal = view_pose(rig().scene, view)
        true[view] = perturb(nominal, 0.5, 0.01, np.random.default_rng(100 + k))
    scan = render(VIEWS, seed=5, true_poses=true)
    return scan, {f"sim-{v}": t for v, t in true.items()}


def _vertical_error(scan, poses, truth) -> dict[str, float]:
    """RMS height error (m) of each camera's points placed by `poses` instead of the truth."""
    out = {}
    for camera in scan.cameras:
        p = camera.points[::20].astype(float)
        z_est = p @ poses[camera.serial][2, :3] + poses[camera.serial][2, 3]
        z_true = p @ truth[camera.serial][2, :3] + truth[camera.serial][2, 3]
        out[camera.serial] = float(np.sqrt(np.mean((z_est - z_true) ** 2)))
    return out


def _tilt_error_deg(pose: np.ndarray, truth: np.ndarray) -> float:
    up_est, up_true = pose[:3, :3].T @ [0, 0, 1], truth[:3, :3].T @ [0, 0, 1]
    return float(np.degrees(np.arccos(np.clip(np.dot(up_est, up_true), -1, 1))))


def test_floor_calibration_recovers_height_and_tilt(perturbed) -> None:
    scan, truth = perturbed
    result = calibrate(scan, CalibrationConfig(), floor=True)
    before = _vertical_error(scan, {c.serial: c.extrinsic for c in scan.cameras}, truth)
    after = _vertical_error(scan, result.extrinsics(), truth)
    for serial in truth:
        assert before[serial] > 0.005
        assert after[serial] < 0.002, (serial, after)
        assert _tilt_error_deg(result.extrinsics()[serial], truth[serial]) < 0.06
        degrees, metres = next(c for c in result.cameras if c.serial == serial).correction
        # yaw about the pile's axis is unobservable on a cone: only bounded, not recovered
        assert 0.1 < degrees < 3.0 and metres < 0.1
    key = "sim-A1|sim-A3"
    assert abs(result.residual_before[key].median_m) > 0.003
    assert abs(result.residual_after[key].median_m) < 0.002
    assert all(c.leveled_by == "floor" for c in result.cameras)
    assert result.pairs[0].used

    # the residual yaw (unobservable) moves where each camera puts the crest by a centimetre or
    # so: the repose fill (the default here), which hangs the unseen flank from the crest, must
    # move no more than the membrane for it (its block-wise holes and crest moved 1.1 %)
    truth_m3 = rig().scene.volume_m3
    for fill in ("membrane", "repose"):
        settings = ReconstructionConfig(fill=fill)
        reference = reconstruct(
            replace(scan, cameras=with_extrinsics(scan.cameras, truth)), settings
        )
        fixed = reconstruct(
            replace(scan, cameras=with_extrinsics(scan.cameras, result.extrinsics())), settings
        )
        raw = reconstruct(scan, settings)
        assert abs(raw.volume_m3 - reference.volume_m3) / truth_m3 > 0.01, fill
        assert abs(fixed.volume_m3 - reference.volume_m3) / truth_m3 < 0.003, fill


def test_a_far_floor_is_fitted_without_bias() -> None:
    """Wall cameras 2.6 m up see the empty bay's floor from 2.8-6 m, where the noise makes
    10 cm cells stand off the floor on both sides. Dropping only the high ones (meant for a
    pile's foot) left the floor 1.5 mm low on average, about 2.5 pp of a pile's volume there."""
    scene = make_scene("empty")
    simulated = SimRig(scene)
    heights = []
    for seed in range(3):  # 12 camera views, placed exactly where their extrinsic says
        scan = simulate(scene, ["A1", "A3", "A5", "A7"], seed, (0.0, 0.0), rig=simulated)
        for camera in scan.cameras:
            found, sigma = floor_points(camera, camera.extrinsic, 0.0, CalibrationConfig())
            normal, centroid = fit_plane(found, 1 / sigma**2)
            heights.append(centroid[2] + normal[:2] @ centroid[:2] / normal[2])  # at x=y=0
    # one view's fit scatters by ~2 mm (correlated noise at range): the mean of 12 is the test
    assert abs(np.mean(heights)) < 0.0008, np.round(np.array(heights) * 1000, 2)


def test_gravity_levels_the_rig_without_a_floor(perturbed) -> None:
    scan, truth = perturbed
    result = calibrate(scan, CalibrationConfig(), floor=False)
    for camera in result.cameras:
        assert camera.leveled_by == "gravity"
        assert camera.gravity_angle_before_deg > 0.1
        assert camera.gravity_angle_after_deg < 0.1
        assert _tilt_error_deg(camera.after, truth[camera.serial]) < 0.1
    mean_z = np.mean([c.after[2, 3] for c in result.cameras])
    assert mean_z == pytest.approx(np.mean([c.before[2, 3] for c in result.cameras]), abs=1e-9)


def test_a_correction_beyond_the_bound_is_refused(perturbed) -> None:
    scan, _ = perturbed
    with pytest.raises(CalibrationError, match=r"refused: sim-A\d would turn .* and move \d+ mm"):
        calibrate(scan, CalibrationConfig(max_correction_m=0.004), floor=True)
    with pytest.raises(CalibrationError, match=r"max_correction_deg = 0\.1"):
        calibrate(scan, CalibrationConfig(max_correction_deg=0.1), floor=True)


def test_a_bins_calibration_says_its_poses_need_checking() -> None:
    """In a bin the eave cameras see the floor 6-10 m away: `calibrate` says so with every
    result and with its refusal (bench/results/calibration-bins.md: it left a simulated 8 m
    bin's cameras further off than they were); outside bins it says nothing of the kind."""
    scene = bin_scene(grain("wheat"), name="bin-8m", diameter_m=8.0, eave_m=6.0)
    scan = simulate(scene, ["A1", "A5"], 0, (0.5, 0.01), resolution=(424, 240))
    alone = CalibrationConfig(min_overlap=1.0)  # each camera by itself: no pair registered
    warning = "in a bin the cameras see the floor and the grain from the eave"
    result = calibrate(scan, alone, floor=False)
    assert any(warning in note for note in result.notes)
    assert warning in result.describe()
    with pytest.raises(CalibrationError, match=warning):
        calibrate(scan, alone.model_copy(update={"max_correction_deg": 0.01}), floor=False)
    bay = render(VIEWS, seed=5)
    assert not any(warning in note for note in calibrate(bay, alone, floor=False).notes)


@pytest.mark.slow
def test_per_scan_refinement_is_bounded() -> None:
    nominal = view_pose(rig().scene, "A3")
    settings = CalibrationConfig(refine=True)
    small = render(VIEWS, seed=7, true_poses={"A3": knocked(nominal, 0.2, (1.0, 0.0, 0.0))})
    refined, notes = refine(small, settings)
    assert notes == []
    before = reconstruct(small, ReconstructionConfig()).registration["sim-A1|sim-A3"]
    after = reconstruct(refined, ReconstructionConfig()).registration["sim-A1|sim-A3"]
    assert abs(before.median_m) > 0.003 and abs(after.median_m) < 0.0015

    large = render(VIEWS, seed=7, true_poses={"A3": knocked(nominal, 1.0, (1.0, 0.0, 0.0))})
    kept, notes = refine(large, settings)
    assert kept is large and len(notes) == 1 and "beyond refine_max" in notes[0]


def test_per_scan_leveling_puts_each_camera_back_on_the_floor(perturbed) -> None:
    """`calibration.level`: every scan, each camera leveled on the floor it sees. Its height
    and tilt come back; its yaw and plan position, which a floor cannot show, do not, so the
    volume comes back to within what they leave (against the scan placed by the true poses)."""
    scan, truth = perturbed
    leveled, corrections, notes = level_scan(scan, CalibrationConfig(level=True))
    assert notes == [] and set(corrections) == set(truth)
    before = _vertical_error(scan, {c.serial: c.extrinsic for c in scan.cameras}, truth)
    poses = {c.serial: c.extrinsic for c in leveled.cameras}
    after = _vertical_error(leveled, poses, truth)
    for serial in truth:
        assert before[serial] > 0.005 and after[serial] < 0.001, (before, after)
        assert _tilt_error_deg(poses[serial], truth[serial]) < 0.06
        assert 0.1 < corrections[serial][0] < 0.5 and 0.005 < corrections[serial][1] < 0.02

    settings = ReconstructionConfig()
    reference = reconstruct(replace(scan, cameras=with_extrinsics(scan.cameras, truth)), settings)
    raw = reconstruct(scan, settings).volume_m3 - reference.volume_m3
    fixed = reconstruct(leveled, settings).volume_m3 - reference.volume_m3
    assert abs(fixed) < 0.2 * abs(raw), (raw, fixed)


def test_per_scan_leveling_is_bounded_and_wants_bare_flat_floor(perturbed) -> None:
    scan, _ = perturbed
    bounded = CalibrationConfig(level=True, refine_max_m=0.005)  # each camera moves ~1 cm
    kept, corrections, notes = level_scan(scan, bounded)
    assert kept is scan and corrections == {} and len(notes) == 2
    assert all("beyond refine_max_*; extrinsic unchanged" in note for note in notes)

    sloping = replace(scan.site, base="boundary")
    kept, corrections, notes = level_scan(scan, CalibrationConfig(level=True), sloping)
    assert kept is scan and notes == [
        "level: the floor is not a flat plane at floor_z; extrinsics unchanged"
    ]

    covered = simulate(make_scene("crater"), VIEWS, seed=1)  # grain wall to wall: no floor
    kept, corrections, notes = level_scan(covered, CalibrationConfig(level=True))
    assert kept is covered and corrections == {}
    assert notes == [f"level: sim-{v} sees no bare floor; extrinsic unchanged" for v in VIEWS]


def test_every_scan_is_leveled_by_default_outside_bins_only(perturbed) -> None:
    from silo_agent.analysis.scan_analysis import analyse
    from silo_agent.config import DetectionConfig

    scan, truth = perturbed
    default = CalibrationConfig()
    assert scan.site.bin is None and scan.site.base == "floor"
    assert default.level == "auto" and default.levels(False, "floor")
    assert not CalibrationConfig(level=False).levels(False, "floor")
    # in a bin (grain covers the floor) or on sloping ground: only when asked
    assert not default.levels(True, "floor") and CalibrationConfig(level=True).levels(True, "floor")
    assert not default.levels(False, "boundary")

    # the analysis every path runs levels the knocked cameras by default
    analysed = analyse(scan, ReconstructionConfig(), DetectionConfig(), calibration=default)
    leveled = analysed.reconstruction.parameters["leveled"]
    assert sorted(leveled) == sorted(truth)
    assert all(
        0.1 < degrees < 0.5 and metres > 0.005
        for degrees, metres in map(lambda c: (c["turned_deg"], c["moved_m"]), leveled.values())
    )
    off = analyse(
        scan, ReconstructionConfig(), DetectionConfig(), calibration=CalibrationConfig(level=False)
    )
    assert "leveled" not in off.reconstruction.parameters
