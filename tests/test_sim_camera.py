"""The virtual D455 against its noise model: RMS at 1, 2 and 4 m measured on a flat wall, the
correlated part, quantisation, the left invalid band, range limits and grazing drop-outs."""

from __future__ import annotations

import numpy as np
import pytest

from silo_agent.sim.camera import NoiseModel, d455_intrinsics, render
from silo_agent.sim.layouts import look_at
from silo_agent.sim.mesh import GRAIN, Mesh, World
from silo_agent.sim.raycast import Raycaster

FOCAL = 440.0
INTRINSICS = d455_intrinsics(FOCAL)


def wall(distance: float, tilt_deg: float = 0.0) -> Raycaster:
    """A plane crossing the optical axis (+y of the silo) at `distance`, turned by `tilt_deg`
    about the silo z axis (0: facing the camera)."""
    t = np.radians(tilt_deg)
    along = np.array([np.cos(t), np.sin(t), 0.0]) * 100
    up = np.array([0.0, 0.0, 100.0])
    centre = np.array([0.0, distance, 0.0])
    vertices = np.array(
        [centre - along - up, centre + along - up, centre + along + up, centre - along + up],
        dtype=np.float32,
    )
    triangles = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
    return Raycaster(World((Mesh(vertices, triangles, GRAIN),)))


POSE = look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]))  # looking along +y


def errors(distance: float, frames: int, noise: NoiseModel) -> np.ndarray:
    """Depth error (m) per pixel per frame, NaN where invalid: (frames, H, W)."""
    caster = wall(distance)
    out = []
    for i in range(frames):
        frame = render(caster, POSE, INTRINSICS, noise, np.random.default_rng(i))
        depth = frame.depth.astype(float) * frame.depth_unit_m
        out.append(np.where(frame.depth > 0, depth - distance, np.nan))
    return np.array(out)


@pytest.mark.parametrize(("distance", "expected_mm"), [(1.0, 1.9), (2.0, 7.7), (4.0, 30.6)])
def test_depth_rms_follows_z2_subpixel_over_f_baseline(distance: float, expected_mm: float) -> None:
    noise = NoiseModel()
    formula = distance**2 * 0.08 / (FOCAL * 0.095)
    assert formula * 1000 == pytest.approx(expected_mm, abs=0.1)  # design.md's numbers
    err = errors(distance, 6, noise)
    measured = np.sqrt(np.nanmean(err**2) - noise.depth_unit_m**2 / 12)  # minus quantisation
    assert measured == pytest.approx(formula, rel=0.03)
    assert abs(np.nanmean(err)) < 0.05 * formula  # unbiased


def lag_correlation(err: np.ndarray, lag: int) -> float:
    """Correlation of errors `lag` columns apart (clear of the left band)."""
    a, b = err[:, :, 100 : err.shape[2] - lag], err[:, :, 100 + lag :]
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def test_noise_is_partly_spatially_correlated() -> None:
    err = errors(2.0, 3, NoiseModel())
    assert 0.35 < lag_correlation(err, 1) < 0.6  # half the variance, correlated over ~4 px
    assert abs(lag_correlation(err, 40)) < 0.05


def test_depth_is_quantised_to_the_depth_unit_and_exact_without_noise() -> None:
    quiet = NoiseModel(subpixel=0.0)
    err = errors(1.2345, 1, quiet)
    assert np.nanmax(np.abs(err)) <= 0.0005 + 1e-9  # 1 mm steps, nothing else
    frame = render(wall(1.2345), POSE, INTRINSICS, quiet, np.random.default_rng(0))
    assert set(np.unique(frame.depth)) <= {0, 1234, 1235}


@pytest.mark.parametrize("distance", [1.0, 2.0, 4.0])
def test_left_band_is_invalid_with_width_f_baseline_over_z(distance: float) -> None:
    frame = render(
        wall(distance), POSE, INTRINSICS, NoiseModel(subpixel=0.0), np.random.default_rng(0)
    )
    valid = (frame.depth > 0).mean(axis=0)  # per column
    width = FOCAL * 0.095 / distance
    assert valid[: int(width) - 1].max() == 0.0
    assert valid[int(width) + 2 :].mean() > 0.95  # holes and speckle take a little


@pytest.mark.parametrize("distance", [0.3, 6.5])
def test_outside_the_depth_range_nothing_is_returned(distance: float) -> None:
    frame = render(wall(distance), POSE, INTRINSICS, NoiseModel(), np.random.default_rng(0))
    assert not frame.depth.any()
    assert len(frame.points()[0]) == 0


def test_grazing_surfaces_drop_out() -> None:
    facing = render(wall(2.0), POSE, INTRINSICS, NoiseModel(), np.random.default_rng(0))
    grazing = render(
        wall(2.0, tilt_deg=86.0), POSE, INTRINSICS, NoiseModel(), np.random.default_rng(0)
    )
    hit_columns = slice(200, 650)  # where the tilted wall is within range
    assert (facing.depth[:, hit_columns] > 0).mean() > 0.95
    assert (grazing.depth[:, hit_columns] > 0).mean() < 0.3


def test_points_deproject_onto_the_wall_in_the_optical_frame() -> None:
    frame = render(
        wall(2.0),
        POSE,
        INTRINSICS,
        NoiseModel(subpixel=0.0),
        np.random.default_rng(0),
        grain_rgb=(200, 150, 100),
    )
    points, colors = frame.points()
    assert points.dtype == np.float32 and len(points) > 0.9 * 848 * 480
    assert np.abs(points[:, 2] - 2.0).max() <= 0.0005 + 1e-6  # +z forward
    assert points[:, 0].min() < -1.5 and points[:, 0].max() > 1.5  # +x spans the image width
    assert colors is not None and colors.shape == points.shape and colors.dtype == np.uint8
    assert frame.color is not None and frame.color.shape == (480, 848, 3)
    assert np.all(colors[:, 0] > colors[:, 2])  # the grain colour, shaded
