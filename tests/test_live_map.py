"""The live map against the moving-robot scene's exact surface: four corner D455s (848x480)
watch a robot rake the first of two heaps, one map every half second (the default 2 Hz)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from scipy import ndimage

from silo_agent.config import LiveConfig
from silo_agent.grid.grid import Grid
from silo_agent.live.map import DepthFrame, LiveMap, LiveUpdate
from silo_agent.sim.grains import grain
from silo_agent.sim.robot import RakingRobot, RobotPose, RobotRig, in_bin
from silo_agent.sim.scenes import Scene, bin_scene
from tests.support.robot import robot_rig

TIMES = np.arange(0.0, 10.5, 0.5)  # the robot climbs the first heap from t ~ 4 s
WARM_UP = 2  # maps before the running values have averaged the noise down
AWAY_M = 0.5  # "away from the robot": this far outside its footprint


@dataclass
class Step:
    t: float
    update: LiveUpdate
    truth: np.ndarray
    pose: RobotPose


def depth_frames(rig: RobotRig, t: float, index: int) -> list[DepthFrame]:
    return [
        DepthFrame.rendered(v.serial, f, v.nominal)
        for v, f in zip(rig.views, rig.frames(t, index), strict=True)
    ]


@pytest.fixture(scope="module")
def run() -> tuple[RobotRig, Grid, LiveMap, list[Step]]:
    rig = robot_rig()
    site = rig.robot.base.site
    grid = Grid.over(site.region, 0.02)
    live = LiveMap(grid, LiveConfig(), site.ceiling_z)
    xs, ys = grid.centres()
    steps = []
    for index, t in enumerate(TIMES):
        update = live.update(depth_frames(rig, t, index), t)
        steps.append(Step(t, update, rig.robot.height(t)(xs, ys), rig.robot.pose(t)))
    return rig, grid, live, steps


@pytest.mark.slow  # the module's 21 maps
def test_the_map_follows_the_raked_surface_within_1cm_rms(run):
    _rig, grid, _live, steps = run
    xs, ys = grid.centres()
    for step in steps[WARM_UP:]:
        away = ~step.pose.footprint(xs, ys, AWAY_M)
        cells = step.update.heightmap.observed & away
        error = step.update.heightmap.heights[cells] - step.truth[cells]
        assert cells.mean() > 0.6, f"t={step.t}: only {cells.mean():.0%} observed"
        rms = float(np.sqrt(np.mean(error**2)))
        assert rms < 0.01, f"t={step.t}: {rms * 100:.2f} cm RMS"


@pytest.mark.slow  # the module's 21 maps
def test_no_robot_shaped_bump(run):
    """Inside the footprint no cell stands more than 2 cm above the grain under the robot."""
    _rig, grid, _live, steps = run
    xs, ys = grid.centres()
    for step in steps:
        under = step.pose.footprint(xs, ys)
        excess = float(np.max(step.update.heightmap.heights[under] - step.truth[under]))
        assert excess <= 0.02, f"t={step.t}: a cell {excess * 100:.1f} cm above the grain"
        assert step.update.held[under].all(), f"t={step.t}: footprint not all held"


@pytest.mark.slow  # the module's 21 maps
def test_the_robot_is_found_where_it_is(run):
    _rig, _grid, _live, steps = run
    for step in steps:
        (robot,) = step.update.robots
        off = np.hypot(robot.x - step.pose.x, robot.y - step.pose.y)
        assert off < 0.3, f"t={step.t}: robot reported {off:.2f} m from its centre"
        assert robot.top_z == pytest.approx(step.pose.z + 0.3, abs=0.05)


@pytest.mark.slow  # the module's 21 maps
def test_changed_mask_covers_the_raked_cells(run):
    rig, grid, _live, steps = run
    xs, ys = grid.centres()
    original = rig.robot.base.height(xs, ys)
    changed = np.zeros(grid.shape, dtype=bool)
    for step in steps[1:]:  # the first map is all new
        changed |= step.update.changed
    last = steps[-1].update
    raked = np.abs(steps[-1].truth - original) > LiveConfig().change_m + 0.01
    measured = raked & last.heightmap.observed  # re-measured since the rake passed
    assert measured.sum() > 1000  # the robot has raked a good part of the first heap
    assert changed[measured].mean() > 0.95
    for step in steps[WARM_UP:]:  # and noise alone rarely moves a running value by change_m
        still = np.abs(step.truth - original) < 1e-9
        still &= ~step.pose.footprint(xs, ys, AWAY_M) & step.update.heightmap.observed
        assert step.update.changed[still].mean() < 0.02, f"t={step.t}"


def test_raking_robot_truth():
    """The scene itself: nothing changes before the rake passes, behind it the heap is cut
    to rake_z, beside it it slumps at the angle of repose."""
    robot = RakingRobot(RobotRig().robot.base)
    x = np.linspace(-3, 3, 301)
    gx, gy = np.meshgrid(x, x)
    before = robot.height(0.0)(gx, gy)
    np.testing.assert_array_equal(before, robot.base.height(gx, gy))
    after = robot.height(100.0)(gx, gy)
    assert np.all(after <= before + 1e-12)
    assert np.max(after) <= np.max(before)
    centre = robot.pose(5.0)
    assert robot.height(100.0)(np.array([centre.x]), np.array([centre.y]))[0] <= robot.rake_z


def looking_down(serial: str, height_m: float, depth_m: float, size: int = 64) -> DepthFrame:
    """A camera `height_m` above a flat floor at z = 0, looking straight down, every pixel
    reading `depth_m` (a D455 focal length of 64 px: a 1 m wide view from 1 m up)."""
    extrinsic = np.diag([1.0, -1.0, -1.0, 1.0])  # camera z (forward) -> silo -z
    extrinsic[2, 3] = height_m
    depth = np.full((size, size), round(depth_m * 1000), dtype=np.uint16)
    return DepthFrame(serial, depth, 0.001, 64.0, 64.0, size / 2, size / 2, extrinsic)


def test_a_far_cameras_points_count_by_their_depth_noise() -> None:
    """A camera 4 m up reads the floor 10 cm high; one 1 m up reads it right. Weighted by the
    D455's depth variance (z^4: 256 times more at 4 m), the far camera's points move the
    cells they share by well under a millimetre, where a plain mean would move them by
    millimetres; each cell's variance is the near camera's single-pixel one (z^2 x 0.08 px /
    (f x 95 mm)), at most, and at least half of it, the share pixels a few apart have in
    common."""
    grid = Grid.over(np.array([[-0.4, -0.4], [0.4, -0.4], [0.4, 0.4], [-0.4, 0.4]]), 0.02)
    live = LiveMap(grid, LiveConfig())
    near, far = looking_down("near", 1.0, 1.0), looking_down("far", 4.0, 3.9)
    alone, _count, _variance = live.frame_heights([far])
    assert np.nanmedian(alone) == pytest.approx(0.1, abs=0.002)
    both, _count, variance = live.frame_heights([near, far])
    shared = np.isfinite(alone) & np.isfinite(both)
    assert shared.sum() > 100
    assert np.max(np.abs(both[shared])) < 0.001
    pixel_rms = 1.0**2 * 0.08 / (64.0 * 0.095)
    inside = np.isfinite(both)
    assert np.all(variance[inside] <= pixel_rms**2 * (1 + 1e-6))
    assert np.all(variance[inside] >= pixel_rms**2 / 2)


def ring_errors(
    scene: Scene, views: tuple[str, ...], times: tuple[float, ...], **size: int
) -> Iterator[tuple[float, np.ndarray]]:
    """Each map's error (map - the exact surface) in the cells within 0.5 m of the bin's
    wall, the map judging the wall with the simulated bins' noise factor (2.5), 5 cm grid."""
    rig = robot_rig(robot=in_bin(scene), views=views, **size)
    site = scene.site
    assert site.bin is not None
    grid = Grid.over(site.region, 0.05)
    xs, ys = grid.centres()
    from_wall = site.bin.radius_m - np.hypot(xs - site.bin.centre[0], ys - site.bin.centre[1])
    ring = (from_wall < 0.5) & (grid.inside > 0)
    live = LiveMap(
        grid, LiveConfig(grid_step_m=0.05), site.ceiling_z, shape=site.bin, noise_factor=2.5
    )
    for index, t in enumerate(times):
        update = live.update(depth_frames(rig, t, index), t)
        yield t, (update.heightmap.heights - rig.robot.height(t)(xs, ys))[ring]


def test_a_bins_far_wall_is_not_grain() -> None:
    """An 8 m bin (eave 6 m) seen by four eave cameras, each looking across at the far wall
    over most of its image: depth noise throws the wall's points along their rays into the
    bin, and the cells by the wall read them as grain, half a metre high on the median and
    up to 2 m (the map before it knew the wall). Judged by its ray, as the full scan judges
    it, a pixel that saw the wall above the grain is not a point of the grain: the ring by
    the wall reads the grain within centimetres, against the scene's exact surface. From the
    first map: with no height yet to judge the wall by, a first pass of the depths short of
    the wall gives one (taken as the floor, the ring by the wall read 0.22 m low on the
    median and its rims passed for robots)."""
    scene = bin_scene(grain("wheat"), name="bin-8m", diameter_m=8.0, eave_m=6.0)
    views = ("A1", "A3", "A5", "A7")
    for t, error in ring_errors(scene, views, (0.0, 0.5, 1.0), width=424, height=240):
        assert abs(float(np.median(error))) < 0.1, f"t={t}"
    assert float(np.mean(error)) < 0.15
    assert float(np.percentile(error, 95)) < 0.5


def test_a_patch_of_wall_points_does_not_raise_the_grain_the_wall_is_judged_by() -> None:
    """A 12 m bin (eave 8 m) seen by eight eave cameras at 848x480: a few of the far wall's
    pixels read their depth three sigma short (the noise comes in blobs a few pixels wide),
    pass the first pass, and land by the wall at wall heights. Taken as the grain there, they
    let the next pass keep every wall pixel below them: the ring by the wall read up to
    2.5 m high (99th percentile 2.2 m), and kept itself there. The grain the wall is judged by
    is the map opened over WALL_LEVEL_M, which such a patch does not raise."""
    scene = bin_scene(
        grain("wheat"),
        name="bin-12m",
        diameter_m=12.0,
        eave_m=8.0,
        level_m=2.0,
        feature_radius_m=4.0,
    )
    views = tuple(f"A{k}" for k in range(1, 9))
    for t, error in ring_errors(scene, views, (0.0, 0.5)):
        assert float(np.percentile(error, 99)) < 0.4, f"t={t}"
        assert float(np.max(error)) < 1.0, f"t={t}"


@pytest.mark.slow  # eight 1280x720 cameras, six maps
def test_the_robot_is_held_out_of_a_bins_map_seen_from_its_eave() -> None:
    """An 8 m bin drawn down at the side (level 1.5 m), eight eave cameras at 1280x720 (a
    setup the session check accepts), the robot on the level grain near the centre, 5-6 m
    from every camera: its rim spreads over three 2 cm cells, and judged over two the map
    found half the steep edge a robot shows, lost it, and let it in 0.3 m high (held
    0-63 % of its footprint). Every map from a cold start holds it out."""
    excess = side_draw_bin_excess(seed=1, times=np.arange(4.5, 7.5, 0.5))
    assert float(np.median(excess)) < 0.05


def side_draw_bin_excess(seed: int, times: np.ndarray) -> list[float]:
    """The robot raking the 8 m side-draw bin under eight eave cameras at 1280x720, the map
    from a cold start at `times[0]`: per map, its highest cell above the grain under the
    robot, once each map is checked to hold the robot's footprint."""
    scene = bin_scene(
        grain("wheat"),
        name="bin-8m-side",
        diameter_m=8.0,
        eave_m=6.0,
        surface="side",
        level_m=1.5,
        feature_radius_m=3.0,
    )
    views = tuple(f"A{k}" for k in range(1, 9))
    rig = robot_rig(robot=in_bin(scene), views=views, width=1280, height=720, seed=seed)
    site = scene.site
    grid = Grid.over(site.region, 0.02)
    xs, ys = grid.centres()
    live = LiveMap(grid, LiveConfig(), site.ceiling_z, shape=site.bin, noise_factor=2.5)
    excess = []
    for index, t in enumerate(times):
        update = live.update(depth_frames(rig, t, index), t)
        under = rig.robot.pose(t).footprint(xs, ys)
        assert update.held[under].mean() > 0.95, f"t={t}"
        truth = rig.robot.height(t)(xs, ys)
        excess.append(float(np.max(update.heightmap.heights[under] - truth[under])))
    return excess


@pytest.mark.slow  # eight 1280x720 cameras, six maps
def test_a_robot_found_stays_found_where_its_rim_blurs() -> None:
    """The same bin (noise seed 0) as the robot crosses its centre, 6 m from every eave
    camera: the rim blurs into a slope, the map found 7-13 of the 20 steep cells a robot
    shows, lost the robot found the map before, and let it in 0.33 m high. A compact raised
    blob where the last map's robot can have driven is that robot."""
    excess = side_draw_bin_excess(seed=0, times=np.arange(7.5, 10.5, 0.5))
    assert max(excess) < 0.05


def box_on_floor(cx: float, blur_m: float = 0.0) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The robot's 0.6 x 0.4 x 0.3 m box centred at (cx, 0) on a flat floor, sampled every
    5 mm, its rim blurred by a gaussian of `blur_m` (as far cameras' noise smears it)."""
    step = 0.005
    xs, ys = np.meshgrid(np.arange(-2.0, 2.0, step), np.arange(-1.5, 1.5, step))
    height = np.where((np.abs(xs - cx) <= 0.3) & (np.abs(ys) <= 0.2), 0.3, 0.0)
    if blur_m:
        height = ndimage.gaussian_filter(height, blur_m / step)

    def at(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        col = np.clip(np.rint((x + 2.0) / step).astype(int), 0, height.shape[1] - 1)
        row = np.clip(np.rint((y + 1.5) / step).astype(int), 0, height.shape[0] - 1)
        return height[row, col]

    return at


def plan_view(surface: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> DepthFrame:
    """A noiseless camera 8 m above the floor looking straight down, 400 x 300 px of 1 cm on
    the floor: each pixel's depth where its ray meets `surface` (a few fixed-point steps)."""
    camera_m, f, width, height = 8.0, 800.0, 400, 300
    extrinsic = np.diag([1.0, -1.0, -1.0, 1.0])  # camera z (forward) -> silo -z
    extrinsic[2, 3] = camera_m
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    depth = np.full(u.shape, camera_m)
    for _ in range(4):
        depth = camera_m - surface(u / f * depth, -v / f * depth)
    return DepthFrame(
        "top",
        np.rint(depth * 1000).astype(np.uint16),
        0.001,
        f,
        f,
        width / 2,
        height / 2,
        extrinsic,
    )


def test_a_blurred_robot_is_a_robot_only_where_the_last_maps_robot_can_be() -> None:
    """A robot box whose rim a 6 cm blur has turned into a slope is not found on its own (a
    mound of grain could look so), but it is where the robot the map found half a second
    before can have driven to, and not 2.6 m from it (beyond 1.5 m/s)."""
    grid = Grid.over(np.array([[-1.9, -1.4], [1.9, -1.4], [1.9, 1.4], [-1.9, 1.4]]), 0.02)
    alone = LiveMap(grid, LiveConfig()).update([plan_view(box_on_floor(0.0, 0.06))], 0.0)
    assert alone.robots == []
    live = LiveMap(grid, LiveConfig())
    assert len(live.update([plan_view(box_on_floor(-0.3))], 0.0).robots) == 1
    near = live.update([plan_view(box_on_floor(-0.15, 0.06))], 0.5).robots
    assert len(near) == 1
    assert near[0].x == pytest.approx(-0.15, abs=0.02)
    assert abs(near[0].y) < 0.02
    live = LiveMap(grid, LiveConfig())
    assert len(live.update([plan_view(box_on_floor(-1.4))], 0.0).robots) == 1
    assert live.update([plan_view(box_on_floor(1.2, 0.06))], 0.5).robots == []


def test_a_robot_found_by_its_edge_vouches_for_no_other_blob() -> None:
    """The robot found again by its steep edge, a blurred box 0.9 m from where it was (within
    its reach) is not taken up as a second robot; of two blurred boxes in its reach, only the
    one nearer to where it was heading is."""
    grid = Grid.over(np.array([[-1.9, -1.4], [1.9, -1.4], [1.9, 1.4], [-1.9, 1.4]]), 0.02)

    def both(
        first: Callable[[np.ndarray, np.ndarray], np.ndarray],
        second: Callable[[np.ndarray, np.ndarray], np.ndarray],
    ) -> DepthFrame:
        return plan_view(lambda x, y: np.maximum(first(x, y), second(x, y)))

    live = LiveMap(grid, LiveConfig())
    assert len(live.update([plan_view(box_on_floor(-0.3))], 0.0).robots) == 1
    robots = live.update([both(box_on_floor(-0.15), box_on_floor(0.6, 0.06))], 0.5).robots
    assert len(robots) == 1
    assert robots[0].x == pytest.approx(-0.15, abs=0.05)
    live = LiveMap(grid, LiveConfig())
    live.update([plan_view(box_on_floor(-0.6))], 0.0)
    live.update([plan_view(box_on_floor(-0.45))], 0.5)  # heading +x at 0.3 m/s
    robots = live.update([both(box_on_floor(-1.1, 0.06), box_on_floor(-0.3, 0.06))], 1.0).robots
    assert len(robots) == 1
    assert robots[0].x == pytest.approx(-0.3, abs=0.05)
