"""Scene truth against closed forms derived here, and against integrating the rendered height
field: the truth must be the volume of what the cameras see, computed without the engine."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from silo_agent.sim.grains import GRAINS
from silo_agent.sim.layouts import VIEWS, view_pose
from silo_agent.sim.scenes import cone_height, make_scene, numeric_volume, square
from silo_agent.sim.simulate import simulate

STEP = 0.003  # midpoint integration step for the cross-checks (the scenes use 2 mm)


def test_cone_matches_pi_r2_h_over_3_and_the_papers_pile() -> None:
    scene = make_scene("cone", "wheat")
    r, h = scene.params["radius"], scene.params["height"]
    assert h == pytest.approx(r * np.tan(np.radians(26.0)))  # wheat's angle of repose
    formula = np.pi * r**2 * h / 3
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-12)
    assert formula == pytest.approx(1.68, rel=1e-9)
    region = scene.site.region
    assert numeric_volume(scene.height, region, 0.0, STEP) == pytest.approx(formula, rel=1e-6)


@pytest.mark.parametrize("name", ["wheat", "corn", "soybeans", "rice"])
def test_grain_sets_slope_and_density(name: str) -> None:
    scene = make_scene("cone", name)
    g = GRAINS[name]
    slope = scene.params["height"] / scene.params["radius"]
    assert np.degrees(np.arctan(slope)) == pytest.approx(g.repose_deg)
    assert scene.site.bulk_density_t_m3 == g.density_t_m3
    assert scene.truth()["mass_t"] == pytest.approx(scene.volume_m3 * g.density_t_m3)


def test_ridge_is_a_prism_plus_a_cone() -> None:
    scene = make_scene("ridge", "corn")
    p = scene.params
    r, h, length = p["half_width"], p["height"], p["length"]
    formula = length * (2 * r * h / 2) + np.pi * r**2 * h / 3  # triangle x L, 2 half-cones
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-12)
    got = numeric_volume(scene.height, scene.site.region, 0.0, STEP)
    assert got == pytest.approx(formula, rel=1e-6)


def test_crater_is_a_slab_minus_an_inverted_cone() -> None:
    scene = make_scene("crater", "rice")
    p = scene.params
    r, d = p["radius"], p["depth"]
    assert d == pytest.approx(r * np.tan(np.radians(GRAINS["rice"].repose_deg)))
    formula = p["level"] * 36.0 - np.pi * r**2 * d / 3
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-12)
    got = numeric_volume(scene.height, scene.site.region, 0.0, STEP)
    assert got == pytest.approx(formula, rel=1e-6)


def test_flat_is_the_crater_bay_before_the_funnel_opened() -> None:
    flat, crater = make_scene("flat", "wheat"), make_scene("crater", "wheat")
    assert flat.volume_m3 == pytest.approx(1.2 * 36.0, rel=1e-12)
    assert numeric_volume(flat.height, flat.site.region, 0.0, STEP) == pytest.approx(
        flat.volume_m3, rel=1e-6
    )
    x, y = np.meshgrid(np.linspace(-2.9, 2.9, 30), np.linspace(-2.9, 2.9, 30))
    far = np.hypot(x - 0.4, y + 0.3) > crater.params["radius"]  # outside the funnel: the same
    assert np.array_equal(flat.height(x, y)[far], crater.height(x, y)[far])
    assert np.array_equal(flat.site.region, crater.site.region)
    assert (flat.layout, flat.wall_half_m, flat.wall_camera_z) == (
        crater.layout,
        crater.wall_half_m,
        crater.wall_camera_z,
    )


def test_full_bay_is_a_slab_plus_the_filling_cone_with_clutter_above_the_crop() -> None:
    scene = make_scene("full", "wheat")
    p = scene.params
    formula = p["level"] * 36.0 + np.pi * p["radius"] ** 2 * (p["peak"] - p["level"]) / 3
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-12)
    got = numeric_volume(scene.height, scene.site.region, 0.0, STEP)
    assert got == pytest.approx(formula, rel=1e-6)
    ceiling = scene.site.ceiling_z
    assert ceiling is not None and p["peak"] < ceiling
    assert scene.clutter and all(box.lo[2] > ceiling for box in scene.clutter)


def _cap(radius: float, slope: float, a: float) -> float:
    """Volume of a cone (apex height slope*radius) beyond a vertical plane at distance a from
    its axis: integrate the exact chord integral of slope*(R - sqrt(x² + y²)) over x."""

    def chord(x: float) -> float:
        w = np.sqrt(max(radius**2 - x**2, 0.0))
        if w == 0.0:
            return 0.0
        log = np.log((radius + w) / (radius - w)) if x > 0 else 0.0
        return slope * (radius * w - 0.5 * x**2 * log)

    return quad(chord, a, radius, limit=200)[0]


def test_max_of_two_overlapping_cones_matches_the_semi_analytic_union() -> None:
    radius, slope, distance = 1.0, 0.5, 1.2
    cone = np.pi * radius**2 * slope * radius / 3
    assert _cap(radius, slope, 0.0) == pytest.approx(cone / 2, rel=1e-8)  # the cap formula

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.maximum(
            cone_height(x, y, (-distance / 2, 0.0), radius, slope),
            cone_height(x, y, (distance / 2, 0.0), radius, slope),
        )

    union = 2 * cone - 2 * _cap(radius, slope, distance / 2)
    assert numeric_volume(height, square(1.7), 0.0, 0.002) == pytest.approx(union, rel=1e-6)


def test_piles_truth_splits_the_total_between_the_piles() -> None:
    scene = make_scene("piles", "wheat")
    cones = scene.params["cones"]
    assert len(scene.piles) == len(cones) >= 3
    assert scene.volume_m3 == pytest.approx(
        numeric_volume(scene.height, scene.site.region, 0.0, STEP), rel=1e-6
    )
    assert sum(p.volume_m3 for p in scene.piles) == pytest.approx(scene.volume_m3, rel=1e-9)
    slope = GRAINS["wheat"].slope
    alone = [np.pi * r**2 * slope * r / 3 for _, r in cones]
    assert scene.volume_m3 < sum(alone)  # they overlap
    for pile, own, ((cx, cy), r) in zip(scene.piles, alone, cones, strict=True):
        assert 0.5 * own < pile.volume_m3 <= own
        assert np.hypot(pile.centroid[0] - cx, pile.centroid[1] - cy) < 0.2 * r
        assert pile.apex == pytest.approx((cx, cy, slope * r))
    truth = scene.truth()
    assert [p["volume_m3"] for p in truth["piles"]] == [p.volume_m3 for p in scene.piles]


@pytest.mark.parametrize("grain_name", ["wheat", "soybeans"])
def test_bay_cone_is_the_papers_pile_in_the_empty_bay(grain_name: str) -> None:
    empty, scene = make_scene("empty", grain_name), make_scene("bay-cone", grain_name)
    p = scene.params
    assert p["height"] == pytest.approx(p["radius"] * GRAINS[grain_name].slope)
    formula = np.pi * p["radius"] ** 2 * p["height"] / 3
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-12) and formula == pytest.approx(1.68)
    region = scene.site.region
    assert np.array_equal(region, empty.site.region)
    assert numeric_volume(scene.height, region, 0.0, 0.002) == pytest.approx(formula, rel=1e-6)
    assert empty.volume_m3 == 0.0 and numeric_volume(empty.height, region, 0.0, 0.002) == 0.0
    # floor around the pile inside the region, walls (up to above the cameras) outside it
    half = p["region_half"]
    assert p["radius"] < half - 1.0 and np.abs(region).max() == half < 3.0
    wall = np.array([3.05, 0.0, -3.05]), np.array([0.0, 3.05, 1.0])
    assert np.all(scene.height(*wall) == p["wall_top"]) and p["wall_top"] > scene.wall_camera_z
    # one rig for both: same cameras, same site
    for view in VIEWS:
        assert np.array_equal(view_pose(empty, view), view_pose(scene, view))
    assert (empty.site.floor_z, empty.site.ceiling_z) == (scene.site.floor_z, scene.site.ceiling_z)


def test_every_wall_camera_sees_the_bays_floor_walls_and_pile() -> None:
    scene = make_scene("bay-cone")
    scan = simulate(scene, list(VIEWS), seed=0)
    radius = scene.params["radius"]
    for camera in scan.cameras:
        p = camera.points_in_silo()
        r = np.hypot(p[:, 0], p[:, 1])
        floor = (np.abs(p[:, 2]) < 0.05) & (r > radius + 0.1) & (np.abs(p[:, :2]).max(axis=1) < 2.9)
        pile = (p[:, 2] > 0.1) & (r < radius - 0.1)
        walls = [(p[:, axis] * sign > 3.0) & (p[:, 2] > 0.3) for axis in (0, 1) for sign in (1, -1)]
        assert floor.sum() > 50_000 and pile.sum() > 20_000, camera.serial
        assert sum(w.sum() > 5_000 for w in walls) >= 2, camera.serial


def test_unknown_scene_and_grain_are_named() -> None:
    with pytest.raises(ValueError, match="known: cone, piles, ridge, crater, full"):
        make_scene("dome")
    with pytest.raises(ValueError, match="unknown grain 'barley'"):
        make_scene("cone", "barley")
