"""The repose fill against surfaces whose heights are known exactly: a cone at the angle of
repose with an unseen flank, the floor in a pile's shadow, a level surface with a hole, and
grain beside a wall that depth noise carried into the region."""

from __future__ import annotations

import numpy as np

from silo_agent.config import ReconstructionConfig
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.fill import LEVEL_SLOPE, membrane_fill, repose_fill
from silo_agent.sim.scenes import make_scene
from silo_agent.sim.simulate import simulate

SLOPE = np.tan(np.radians(26.0))  # wheat


def _grid(step: float, half: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    centres = np.arange(-half + step / 2, half, step)
    return np.meshgrid(centres, centres)


def _points(known: np.ndarray, step: float) -> np.ndarray:
    """Points per cell of a surface seen at 40,000 points per m² where it is known."""
    return np.where(known, max(1, round(40_000 * step**2)), 0)


def _cone(x: np.ndarray, y: np.ndarray, radius: float = 1.4) -> np.ndarray:
    return SLOPE * np.maximum(radius - np.hypot(x, y), 0.0)


def test_an_unseen_flank_continues_the_crest_at_the_repose_slope() -> None:
    step = 0.02
    x, y = _grid(step)
    truth = _cone(x, y)
    r = np.hypot(x, y)
    unseen = (np.abs(np.arctan2(y, x)) < np.radians(35)) & (r > 0.3) & (r < 1.2)  # a flank
    domain = np.ones_like(unseen)
    known = ~unseen

    repose = repose_fill(truth, known, domain, _points(known, step), SLOPE, step)
    membrane = membrane_fill(truth, known, domain)

    repose_error = np.sum(repose[unseen] - truth[unseen]) * step**2
    membrane_error = np.sum(membrane[unseen] - truth[unseen]) * step**2
    assert membrane_error < -0.01  # the soap film sags under the cone: 10 litres and more
    assert abs(repose_error) < 0.15 * abs(membrane_error)
    assert np.all(repose[known] == truth[known])


def test_the_floor_in_a_piles_shadow_stays_floor() -> None:
    step = 0.02
    x, y = _grid(step)
    truth = _cone(x, y)
    shadow = (y < -1.1) & (np.abs(x) < 1.0)  # behind the pile, out to the region's edge
    domain = np.ones_like(shadow)

    repose = repose_fill(truth, ~shadow, domain, _points(~shadow, step), SLOPE, step)
    membrane = membrane_fill(truth, ~shadow, domain)

    membrane_bulge = np.mean(membrane[shadow] - truth[shadow])
    assert membrane_bulge > 0.04  # the film borrows the pile's height
    # level surfaces rise from the floor seen on either side at LEVEL_SLOPE, no more
    assert abs(np.mean(repose[shadow] - truth[shadow])) < 0.2 * membrane_bulge
    assert np.max(np.abs(repose[shadow] - truth[shadow])) < LEVEL_SLOPE * 1.0 + 0.002


def test_a_hole_in_level_grain_is_filled_level() -> None:
    step = 0.02
    x, y = _grid(step)
    truth = 1.6 + 0.01 * x  # levelled, a 1 % tilt
    hole = np.hypot(x - 0.3, y) < 0.8
    domain = np.ones_like(hole)

    filled = repose_fill(truth, ~hole, domain, _points(~hole, step), SLOPE, step)

    assert np.max(np.abs(filled[hole] - truth[hole])) < 1e-3


def test_wall_points_in_the_region_lift_no_fill() -> None:
    step = 0.02
    x, y = _grid(step)
    truth = np.full(x.shape, 1.2)
    measured = truth.copy()
    measured[:, -3:] = 3.0  # the wall, read into the last cells of the region
    hole = (np.abs(x - 1.2) < 0.5) & (np.abs(y) < 0.5)
    domain = np.ones_like(hole)

    filled = repose_fill(measured, ~hole, domain, _points(~hole, step), SLOPE, step)

    assert np.max(filled[hole]) < 1.2 + 0.02


def test_the_fill_does_not_depend_on_the_grid_step() -> None:
    volumes = []
    for step in (0.1, 0.05, 0.02, 0.01):
        x, y = _grid(step)
        truth = _cone(x, y)
        unseen = ((np.abs(np.arctan2(y, x)) < np.radians(35)) & (np.hypot(x, y) > 0.3)) | (
            (y < -1.1) & (np.abs(x) < 1.0)
        )
        known = ~unseen
        filled = repose_fill(truth, known, np.ones_like(known), _points(known, step), SLOPE, step)
        volumes.append(np.sum(filled - truth) * step**2)
    assert np.ptp(volumes) < 0.002  # m³, over the 8 m² hidden: 0.25 mm


def test_the_empty_cells_of_a_fine_grid_are_no_hole() -> None:
    step = 0.005
    x, _ = _grid(step, half=1.0)
    truth = 1.6 + 0.0 * x
    rng = np.random.default_rng(3)
    known = rng.random(x.shape) < 0.3  # 1.2 points per cell: most cells empty, none unseen
    measured = np.where(known, truth + rng.normal(0, 0.01, x.shape), np.nan)

    filled = repose_fill(measured, known, np.ones_like(known), known.astype(int), SLOPE, step)

    assert abs(np.mean(filled[~known]) - 1.6) < 0.002


def test_the_fill_moves_with_the_crest_not_a_block_at_a_time() -> None:
    """The shadow behind a crest, its corner at the crest, moved across the grid a centimetre
    at a time: the fill's error moves by no more than the cells the shadow gains or loses do
    (holes and sources picked a block at a time moved it by 1.8 % of the pile)."""
    step = 0.02
    x, y = _grid(step)
    errors, membrane_errors = [], []
    for shift in np.arange(0.0, 0.101, 0.01):
        truth = _cone(x - shift, y - 0.7 * shift)
        unseen = (x > shift) & (y > 0.7 * shift) & (np.hypot(x - shift, y - 0.7 * shift) < 1.6)
        known = ~unseen
        filled = repose_fill(truth, known, np.ones_like(known), _points(known, step), SLOPE, step)
        errors.append(np.sum(filled - truth) * step**2)
        membrane = membrane_fill(truth, known, np.ones_like(known))
        membrane_errors.append(np.sum(membrane - truth) * step**2)
    volume = np.pi * 1.4**2 * SLOPE * 1.4 / 3
    assert np.ptp(errors) / volume < 0.006, np.round(errors, 4)
    assert np.ptp(errors) < 3 * np.ptp(membrane_errors)


def test_the_default_fill_is_repose_outside_a_bin_and_the_membrane_in_one() -> None:
    default = ReconstructionConfig()
    assert default.fill == "auto"
    open_site, bin_site = make_scene("cone").site, make_scene("bin-heap").site
    assert bin_site.bin is not None and open_site.bin is None
    assert default.fill_for(open_site.bin is not None) == "repose"
    assert default.fill_for(bin_site.bin is not None) == "membrane"
    assert ReconstructionConfig(fill="membrane").fill_for(open_site.bin is not None) == "membrane"
    assert ReconstructionConfig(fill="repose").fill_for(bin_site.bin is not None) == "repose"
    result = reconstruct(simulate("cone", ["A1", "A5"], seed=0), default)
    assert result.parameters["fill"] == "repose" and "repose_deg" in result.parameters
