"""Round-bin scenes: truth against closed forms derived here and against integrating the
rendered surface over the wall polygon; what the eave cameras see (grain, the far wall), the
D455 noise at bin range, both resolutions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from silo_agent.sim.camera import NoiseModel, d455_intrinsics, noisy_depth
from silo_agent.sim.grains import GRAINS
from silo_agent.sim.layouts import look_at, view_pose
from silo_agent.sim.scenes import bin_scene, make_scene, numeric_volume
from silo_agent.sim.simulate import SimRig, SimView, simulate

SMALL = (212, 120)  # a quarter of 848x480 each way: enough to see what is where
QUIET = NoiseModel(
    subpixel=0.0, hole_fraction=0.0, speckle_fraction=0.0, max_depth_m=30.0, grazing_end_deg=89.9
)


def cross_check(name: str, step: float = 0.01) -> float:
    """The scene's grain volume by a Cartesian midpoint integration over the wall polygon."""
    scene = make_scene(name)
    shape = scene.site.bin
    assert shape is not None
    return numeric_volume(
        lambda x, y: scene.height(x, y) - shape.bottom(x, y), shape.wall_polygon(), 0.0, step
    )


def test_heap_bin_is_a_cylinder_plus_the_heap_cone() -> None:
    scene = make_scene("bin-heap")
    p, slope = scene.params, GRAINS["wheat"].slope
    cone = np.pi * p["radius"] ** 2 * slope * p["radius"] / 3
    formula = np.pi * 5.0**2 * p["level"] + cone
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-8)
    assert cross_check("bin-heap") == pytest.approx(formula, rel=1e-4)
    truth = scene.truth()
    assert truth["level_max_m"] == pytest.approx(p["level"] + slope * p["radius"], abs=1e-3)
    assert truth["capacity_m3"] == pytest.approx(np.pi * 25 * 7.0)
    assert truth["fill_ratio"] == pytest.approx(formula / (np.pi * 25 * 7.0), rel=1e-8)
    assert truth["headspace_m"] == pytest.approx(7.0 - truth["level_max_m"])


def test_crater_bin_is_a_cylinder_less_the_draw_down_cone() -> None:
    scene = make_scene("bin-crater")
    p, slope = scene.params, GRAINS["wheat"].slope
    depth = slope * p["radius"]
    formula = np.pi * 25 * p["level"] - np.pi * p["radius"] ** 2 * depth / 3
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-8)
    assert cross_check("bin-crater") == pytest.approx(formula, rel=1e-4)
    assert scene.truth()["level_min_m"] == pytest.approx(p["level"] - depth, abs=1e-3)


def test_side_draw_truth_matches_integrating_the_surface() -> None:
    scene = make_scene("bin-side")
    assert cross_check("bin-side") == pytest.approx(scene.volume_m3, rel=1e-4)
    # the outlet is on the wall: the surface there is the level less the full crater depth
    ox, oy = scene.params["outlet"]
    slope = GRAINS["wheat"].slope
    low = scene.params["level"] - slope * scene.params["radius"]
    assert float(scene.height(np.array(ox), np.array(oy))) == pytest.approx(low, abs=1e-9)


def test_hopper_bin_counts_the_cone_under_the_floor() -> None:
    scene = make_scene("hopper-heap")
    shape, p, slope = scene.site.bin, scene.params, GRAINS["wheat"].slope
    assert shape is not None and shape.floor == "hopper"
    big, small, depth = 4.0, 0.2, shape.hopper_depth_m
    assert depth == pytest.approx((big - small) * np.tan(np.radians(45)))
    frustum = np.pi * depth * (big**2 + big * small + small**2) / 3
    formula = frustum + np.pi * big**2 * p["level"] + np.pi * p["radius"] ** 3 * slope / 3
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-8)
    assert cross_check("hopper-heap") == pytest.approx(formula, rel=1e-4)
    assert scene.truth()["capacity_m3"] == pytest.approx(frustum + np.pi * big**2 * 6.0)


def test_low_hopper_bin_has_its_surface_inside_the_hopper() -> None:
    scene = make_scene("hopper-low")
    shape, slope = scene.site.bin, GRAINS["wheat"].slope
    assert shape is not None
    centre_z = scene.params["level"] - slope * scene.params["radius"]

    def column(r: float) -> float:  # grain over the hopper at radius r, computed here
        hopper = -shape.hopper_depth_m + max(r - 0.2, 0.0) * np.tan(np.radians(45))
        return max(centre_z + slope * r - hopper, 0.0) * 2 * np.pi * r

    formula, _ = quad(column, 0.0, 4.0, points=[0.2, 2.7], limit=200)
    assert scene.volume_m3 == pytest.approx(formula, rel=1e-6)
    truth = scene.truth()
    assert truth["level_max_m"] < -1.0  # the grain's edge on the cone, under the floor plane
    assert truth["level_min_m"] == pytest.approx(centre_z, abs=1e-6)
    assert truth["headspace_m"] == pytest.approx(6.0 - truth["level_max_m"])


def test_eave_cameras_hang_under_the_eave_and_look_down_past_the_centre() -> None:
    scene = make_scene("bin-crater")
    for view in ("A1", "A3", "A5", "A7"):
        pose = view_pose(scene, view)
        position, forward = pose[:3, 3], pose[:3, 2]
        assert np.hypot(*position[:2]) == pytest.approx(4.7)
        assert position[2] == pytest.approx(6.7)
        assert forward[2] < -0.5  # looking down ...
        assert np.dot(forward[:2], position[:2]) < 0  # ... and inward


def test_eave_cameras_see_grain_and_the_far_wall_and_a_level_camera_sees_the_roof() -> None:
    scene = make_scene("bin-heap")
    rig = SimRig(scene, noise=QUIET)
    scan = simulate(scene, ["A1", "A5"], seed=0, rig=rig, resolution=SMALL)
    for camera in scan.cameras:
        p = camera.points_in_silo()
        r = np.hypot(p[:, 0], p[:, 1])
        wall = (r > 4.98) & (p[:, 2] > scene.height(p[:, 0], p[:, 1]) + 0.05)
        assert 0.1 < wall.mean() < 0.6, camera.serial  # the far wall fills much of the view
        assert (r < 4.9).mean() > 0.4, camera.serial
    level = look_at(np.array([0.0, -4.7, 6.7]), np.array([0.0, 0.0, 8.0]))
    k = d455_intrinsics(440.0, *SMALL)
    view = SimView("up", "up", level, level, k)
    points = rig.cloud(view, 0).points_in_silo()
    roof = points[:, 2] > 7.0 + 0.01
    assert roof.mean() > 0.3


@pytest.mark.parametrize("resolution", [(848, 480), (1280, 720)])
def test_both_d455_resolutions_render(resolution: tuple[int, int]) -> None:
    scene = make_scene("bin-crater")
    scan = simulate(scene, ["A3"], seed=1, resolution=resolution)
    camera = scan.cameras[0]
    assert camera.intrinsics is not None
    assert (camera.intrinsics["width"], camera.intrinsics["height"]) == resolution
    assert 0.7 * resolution[0] * resolution[1] < len(camera.points) <= resolution[0] * resolution[1]


def test_bin_noise_is_about_two_percent_at_four_metres_and_grows_with_range_squared() -> None:
    noise = SimRig(make_scene("bin-heap")).noise
    at_4 = float(noise.rms_m(4.0, 440.0))
    assert 0.015 < at_4 / 4.0 < 0.025
    assert float(noise.rms_m(8.0, 440.0)) == pytest.approx(4 * at_4)
    assert noise.max_depth_m >= 12.0  # the far wall of a 10 m bin is ~10 m away


def test_stereo_noise_is_in_disparity_so_far_depths_read_far_on_average() -> None:
    """A block matcher errs in disparity: the mean inverse depth is right and the mean depth
    reads sigma^2 / z far (2 cm at 9 m here); the RMS is the datasheet's z^2 model."""
    noise = SimRig(make_scene("bin-heap")).noise
    depth = np.full((2000, 2000), 9.0)
    measured = noisy_depth(depth, 440.0, noise, np.random.default_rng(5))
    sigma = float(noise.rms_m(9.0, 440.0))
    assert float(np.std(measured)) == pytest.approx(sigma, rel=0.05)
    assert float(np.mean(1.0 / measured)) == pytest.approx(1.0 / 9.0, rel=1e-3)
    assert float(np.mean(measured)) - 9.0 == pytest.approx(sigma**2 / 9.0, abs=0.006)


def test_measured_wall_scatter_follows_the_noise_model() -> None:
    """Wall points at 9-10 m land 0.1-0.5 m off the wall along the ray: the issue's problem."""
    scene = make_scene("bin-heap")
    scan = simulate(scene, ["A1"], seed=2)  # the noise is in pixels of disparity: 848 wide
    p = scan.cameras[0].points_in_silo()
    high = p[:, 2] > 3.5  # nothing but wall up there
    inward = 5.0 - np.hypot(p[high, 0], p[high, 1])
    assert 0.1 < float(np.std(inward)) < 0.6


def test_bin_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="unknown bin surface"):
        bin_scene(GRAINS["wheat"], surface="dome")
    with pytest.raises(ValueError, match="flat floor"):
        bin_scene(GRAINS["wheat"], surface="side", hopper_angle_deg=45.0)
    with pytest.raises(ValueError, match="round bin"):
        view_pose(make_scene("cone"), "A1", "eave")
