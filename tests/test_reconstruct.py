"""The BICM engine against analytic truth (tests/support/synthetic.py), never its own output."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from silo_agent.config import CalibrationConfig, ReconstructionConfig
from silo_agent.grid.geometry import cell_fractions, polygon_area, transform_from_euler
from silo_agent.reconstruct import reconstruct
from silo_agent.reconstruct.fill import bspline_fill, membrane_fill
from silo_agent.reconstruct.level import level_scan
from silo_agent.scan import CameraCloud, Scan, Site, write_scan
from tests.support.cli import run_cli
from tests.support.synthetic import Scene, cone, frustum_on_slab, look_at, observe, ring_views


def _error(scan: Scan, truth: float, **settings) -> float:
    result = reconstruct(scan, ReconstructionConfig(**settings))
    return (result.volume_m3 - truth) / truth


def test_four_views_within_one_percent(cone_scan_4: Scan, cone_scene: Scene) -> None:
    assert abs(_error(cone_scan_4, cone_scene.volume, grid_step_m=0.02)) < 0.01


def test_two_opposite_views_within_three_percent(cone_scan_2: Scan, cone_scene: Scene) -> None:
    assert abs(_error(cone_scan_2, cone_scene.volume, grid_step_m=0.02)) < 0.03


def test_grid_step_barely_matters(cone_scan_4: Scan, cone_scene: Scene) -> None:
    errors = [
        _error(cone_scan_4, cone_scene.volume, grid_step_m=s) for s in (0.1, 0.05, 0.02, 0.01)
    ]
    assert max(errors) - min(errors) < 0.01, errors


def test_two_views_give_the_same_volume_at_a_coarse_and_a_fine_step(
    cone_scan_2: Scan, cone_scene: Scene
) -> None:
    """Issue 24: the trust rule judged density on the grid's own cells, so at 1 cm (a point or
    two a cell) it dropped cells by chance and at 10 cm whole partly seen ones: +1.77 % at
    0.1 m, +2.55 % at 0.01 m. Judged on 5 cm blocks at every step: +2.04 and +1.85 %."""
    errors = [_error(cone_scan_2, cone_scene.volume, grid_step_m=s) for s in (0.1, 0.01)]
    assert all(abs(e) < 0.03 for e in errors), errors
    assert abs(errors[0] - errors[1]) < 0.005, errors


def test_bicm_beats_the_rectangle_method(cone_scan_2: Scan, cone_scene: Scene) -> None:
    for step in (0.05, 0.01):
        bicm = abs(_error(cone_scan_2, cone_scene.volume, grid_step_m=step))
        rectangle = abs(
            _error(cone_scan_2, cone_scene.volume, grid_step_m=step, method="rectangle")
        )
        assert bicm < rectangle


def test_full_floor_with_pile() -> None:
    scene = frustum_on_slab()
    scan = observe(scene, ring_views(4, distance=2.0), np.random.default_rng(3), spacing=0.01)
    assert abs(_error(scan, scene.volume, grid_step_m=0.02)) < 0.005


def test_rigid_motion_of_the_whole_site_changes_nothing(cone_scan_4: Scan) -> None:
    """Moving silo frame and cameras together (rotation about z, shift) keeps the volume."""
    motion = transform_from_euler([0, 0, 33.0], [5.0, -3.0, 2.0])
    site = cone_scan_4.site
    region = site.region @ motion[:2, :2].T + motion[:2, 3]
    moved = replace(
        cone_scan_4,
        site=Site(region, site.floor_z + 2.0, site.ceiling_z + 2.0),
        cameras=[replace(c, extrinsic=motion @ c.extrinsic) for c in cone_scan_4.cameras],
    )
    settings = ReconstructionConfig(grid_step_m=0.02)
    before = reconstruct(cone_scan_4, settings)
    after = reconstruct(moved, settings)
    assert after.volume_m3 == pytest.approx(before.volume_m3, rel=0.005)
    assert after.surface.max - 2.0 == pytest.approx(before.surface.max, abs=0.02)


# ---------------------------------------------------------------- clustered means


def _plane_camera(
    serial: str, z: float, count: int, rng: np.random.Generator, noise: float = 0.003
) -> CameraCloud:
    """A camera 2 m above a flat patch, reporting it at height z (its own misalignment)."""
    pose = look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.001, 0.0]))
    xy = rng.uniform(-0.5, 0.5, size=(count, 2))
    world = np.column_stack([xy, z + rng.normal(0, noise, count)])
    points = (world - pose[:3, 3]) @ pose[:3, :3]
    return CameraCloud(serial, points.astype(np.float32), pose)


def _plane_site() -> Site:
    return Site(np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]), 0.0, 3.0)


def test_misaligned_views_read_the_same_at_every_grid_step() -> None:
    """Paper fig. 4: two surfaces 4 cm apart, one camera 4x as dense. Each point counts once,
    so a cell means the same whatever its size: a mean of the cameras' means read 0.52 m on
    5 cm cells, where both cameras have points, and ~0.514 m on 5 mm ones, where a quarter of
    the cells hold the dense camera's points only."""
    rng = np.random.default_rng(0)
    cameras = [_plane_camera("low", 0.50, 200_000, rng), _plane_camera("high", 0.54, 50_000, rng)]
    scan = Scan("s", "2026-11-22T00:00:00Z", "silo", _plane_site(), cameras)
    coarse, fine = (reconstruct(scan, ReconstructionConfig(grid_step_m=s)) for s in (0.05, 0.005))
    assert coarse.volume_m3 == pytest.approx(0.508, abs=0.002)
    assert fine.volume_m3 == pytest.approx(coarse.volume_m3, abs=0.001)
    assert coarse.surface.mean == pytest.approx(fine.surface.mean, abs=0.001)


def test_a_noise_free_flat_surface_is_measured_exactly() -> None:
    camera = _plane_camera("c", 0.40, 50_000, np.random.default_rng(2), noise=0.0)
    scan = Scan("s", "2026-11-22T00:00:00Z", "silo", _plane_site(), [camera])
    result = reconstruct(scan, ReconstructionConfig(grid_step_m=0.05))
    assert result.coverage == 1.0
    assert result.volume_m3 == pytest.approx(0.40, abs=1e-4)


def test_outliers_and_a_wall_do_not_lift_the_surface() -> None:
    rng = np.random.default_rng(1)
    camera = _plane_camera("c", 0.30, 200_000, rng)
    pose = camera.extrinsic
    # flying pixels 20-60 cm above, and a dense vertical column (a wall, a ladder) at x ~ 0.3
    flyers = np.column_stack([rng.uniform(-0.5, 0.5, (5000, 2)), rng.uniform(0.5, 0.9, 5000)])
    column = np.column_stack(
        [
            rng.uniform(0.28, 0.32, 20000),
            rng.uniform(-0.5, 0.5, 20000),
            rng.uniform(0.3, 1.5, 20000),
        ]
    )
    extra = (np.vstack([flyers, column]) - pose[:3, 3]) @ pose[:3, :3]
    noisy = replace(camera, points=np.vstack([camera.points, extra.astype(np.float32)]))
    scan = Scan("s", "2026-11-22T00:00:00Z", "silo", _plane_site(), [noisy])
    result = reconstruct(scan, ReconstructionConfig(grid_step_m=0.05))
    assert result.volume_m3 == pytest.approx(0.30, abs=0.003)
    assert result.surface.max < 0.33


# ---------------------------------------------------------------- fill, region, base


def test_membrane_fill_reproduces_a_tilted_plane_inside_the_region() -> None:
    rows, cols = np.mgrid[0:80, 0:100]
    plane = 0.3 + 0.01 * cols - 0.004 * rows
    known = np.ones(plane.shape, dtype=bool)
    known[20:60, 30:90] = False  # a big hole surrounded by data: filled exactly
    known[0:10, 0:10] = False  # a hole on the region's edge: free boundary, extends flat
    filled = membrane_fill(np.where(known, plane, np.nan), known, np.ones_like(known))
    np.testing.assert_allclose(filled[10:, 10:], plane[10:, 10:], atol=1e-9)
    corner = filled[0:10, 0:10]
    rim = np.concatenate([plane[10, 0:11], plane[0:11, 10]])
    assert rim.min() - 1e-9 <= corner.min() and corner.max() <= rim.max() + 1e-9


def test_large_holes_take_the_iterative_path_and_agree() -> None:
    rows, cols = np.mgrid[0:300, 0:300]
    surface = np.sin(rows / 40.0) + np.cos(cols / 55.0)
    known = np.ones(surface.shape, dtype=bool)
    known[40:260, 40:260] = False  # 48,400 unknowns: above the direct-solve limit
    filled = membrane_fill(np.where(known, surface, np.nan), known, np.ones_like(known))
    assert np.all(np.isfinite(filled))
    # harmonic: bounded by the boundary values, smooth
    assert filled[~known].max() <= surface[known].max() + 1e-6
    assert filled[~known].min() >= surface[known].min() - 1e-6


def test_bspline_fill_keeps_observed_cells_and_fills_the_rest() -> None:
    _, cols = np.mgrid[0:64, 0:64]
    plane = 1.0 + 0.02 * cols
    known = np.random.default_rng(0).random(plane.shape) > 0.3
    filled = bspline_fill(np.where(known, plane, np.nan), known)
    np.testing.assert_array_equal(filled[known], plane[known])
    assert np.abs(filled[~known] - plane[~known]).max() < 0.05


@pytest.mark.parametrize("sides", [3, 5, 40])
def test_cut_cells_are_weighted_by_their_area_inside(sides: int) -> None:
    angles = np.linspace(0, 2 * np.pi, sides, endpoint=False) + 0.3
    polygon = np.column_stack([1.7 * np.cos(angles) + 0.11, 1.7 * np.sin(angles) - 0.07])
    low = polygon.min(axis=0)
    step = 0.05
    shape = (int(np.ceil(np.ptp(polygon[:, 1]) / step)), int(np.ceil(np.ptp(polygon[:, 0]) / step)))
    fractions = cell_fractions(polygon, (low[0], low[1]), step, shape)
    assert fractions.sum() * step * step == pytest.approx(abs(polygon_area(polygon)), rel=2e-3)


def test_volume_over_a_triangle_region() -> None:
    scene = frustum_on_slab()
    triangle = np.array([[-1.9, -1.9], [1.9, -1.5], [-1.0, 1.8]])
    scan = observe(scene, ring_views(4, distance=2.0), np.random.default_rng(4), spacing=0.01)
    scan = replace(scan, site=Site(triangle, 0.0, 2.0))
    # truth by fine numeric integration of the analytic surface over the triangle
    step = 0.002
    xs, ys = np.meshgrid(np.arange(-2, 2, step) + step / 2, np.arange(-2, 2, step) + step / 2)
    from silo_agent.grid.geometry import points_in_polygon

    inside = points_in_polygon(xs, ys, triangle)
    truth = float(np.sum(scene.height(xs, ys)[inside]) * step * step)
    assert abs(_error(scan, truth, grid_step_m=0.03)) < 0.006


def test_boundary_base_measures_a_pile_standing_on_a_sloping_surface() -> None:
    base_pile = cone(radius=1.0, slope_deg=30.0, half=2.0)

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 0.5 + 0.05 * x + 0.02 * y + base_pile.height(x, y)

    scene = Scene(height, base_pile.volume, base_pile.region)
    scan = observe(scene, ring_views(4, distance=2.0), np.random.default_rng(5), spacing=0.01)
    scan = replace(scan, site=replace(scan.site, base="boundary"))
    assert abs(_error(scan, base_pile.volume, grid_step_m=0.02)) < 0.02
    # measured above the floor instead, the slab under the pile counts too
    floor = reconstruct(
        replace(scan, site=replace(scan.site, base="floor")), ReconstructionConfig(grid_step_m=0.02)
    )
    assert floor.volume_m3 == pytest.approx(base_pile.volume + 0.5 * 16, rel=0.01)


# ---------------------------------------------------------------- result contract


def test_low_coverage_is_marked_invalid(cone_scan_4: Scan) -> None:
    one = replace(cone_scan_4, cameras=cone_scan_4.cameras[:1])
    result = reconstruct(one, ReconstructionConfig(grid_step_m=0.02, min_coverage=0.9))
    assert result.valid is False
    assert "coverage" in result.invalid_reason
    assert 0 < result.coverage < 0.9


def test_nothing_in_the_region_gives_no_volume(cone_scan_4: Scan) -> None:
    far = np.array([[50.0, 50.0], [51.0, 50.0], [51.0, 51.0]])
    result = reconstruct(replace(cone_scan_4, site=Site(far, 0.0)), ReconstructionConfig())
    assert result.volume_m3 is None
    assert result.valid is False
    assert result.coverage == 0.0


def test_mass_from_density(cone_scan_4: Scan) -> None:
    scan = replace(cone_scan_4, site=replace(cone_scan_4.site, bulk_density_t_m3=0.77))
    result = reconstruct(scan, ReconstructionConfig())
    assert result.mass_t == pytest.approx(result.volume_m3 * 0.77)
    assert reconstruct(cone_scan_4, ReconstructionConfig()).mass_t is None


def test_heightmap_is_explicit_and_observed_layer_kept(
    cone_scan_4: Scan, cone_scene: Scene
) -> None:
    result = reconstruct(cone_scan_4, ReconstructionConfig(grid_step_m=0.05))
    hm = result.heightmap
    xs, ys = hm.cell_centres()
    inside = hm.inside > 0
    assert np.all(np.isfinite(hm.heights[inside]))
    assert np.all(np.isnan(hm.heights[~inside]))
    # rows run along +y from the origin corner: the cone apex sits in the middle of the map
    apex = np.unravel_index(np.nanargmax(hm.heights), hm.shape)
    assert abs(xs[apex] - 0.0) < 0.1 and abs(ys[apex] - 0.0) < 0.1
    assert hm.height_at(0.0, 0.0) == pytest.approx(
        float(cone_scene.height(np.array(0.0), np.array(0.0))), abs=0.03
    )
    assert result.coverage == pytest.approx(
        float((hm.observed & inside).sum() / inside.sum()), abs=1e-9
    )


@pytest.mark.slow
@pytest.mark.parametrize("method", ["rectangle", "hull", "alpha", "poisson"])
def test_baselines_give_a_volume(cone_scan_4: Scan, cone_scene: Scene, method: str) -> None:
    result = reconstruct(cone_scan_4, ReconstructionConfig(grid_step_m=0.05, method=method))
    assert result.method == method
    assert math.isfinite(result.volume_m3)
    # each is a volume of this pile, however rough
    assert 0.3 * cone_scene.volume < result.volume_m3 < 3 * cone_scene.volume


def test_hull_of_a_convex_pile_is_close(cone_scan_4: Scan, cone_scene: Scene) -> None:
    result = reconstruct(cone_scan_4, ReconstructionConfig(grid_step_m=0.05, method="hull"))
    assert result.volume_m3 == pytest.approx(cone_scene.volume, rel=0.1)


# ---------------------------------------------------------------- the `process` command


def test_process_json_is_one_object_and_reproducible(tmp_path, cone_scan_4: Scan) -> None:
    scan = replace(cone_scan_4, site=replace(cone_scan_4.site, bulk_density_t_m3=0.58))
    directory = write_scan(scan, tmp_path / "scan")
    first = run_cli("process", str(directory), "--json", "--grid-step", "0.05")
    second = run_cli("process", str(directory), "--json", "--grid-step", "0.05")
    assert first.returncode == 0, first.stderr
    summary = json.loads(first.stdout)  # exactly one JSON document
    for key in ("scan_id", "volume_m3", "mass_t", "coverage", "grid_step_m", "surface"):
        assert key in summary
    assert set(summary["surface"]) >= {"min_z", "mean_z", "max_z"}
    assert summary["grid_step_m"] == 0.05
    assert summary["mass_t"] == pytest.approx(summary["volume_m3"] * 0.58)
    # process levels each camera on the floor it sees first (the default outside bins)
    leveled, _, _ = level_scan(scan, CalibrationConfig())
    direct = reconstruct(leveled, ReconstructionConfig(grid_step_m=0.05))
    assert summary["volume_m3"] == direct.volume_m3
    strip = lambda s: {k: v for k, v in json.loads(s).items() if k != "timings_s"}  # noqa: E731
    assert strip(first.stdout) == strip(second.stdout)


def test_process_uses_the_scan_settings_then_config_then_flags(tmp_path, cone_scan_4: Scan) -> None:
    scan = replace(cone_scan_4, reconstruction={"grid_step_m": 0.08})
    directory = write_scan(scan, tmp_path / "scan")
    assert json.loads(run_cli("process", str(directory), "--json").stdout)["grid_step_m"] == 0.08
    config = tmp_path / "agent.toml"
    config.write_text(
        '[silo]\nid = "s"\nregion = [[-2.5, -2.5], [2.5, -2.5], [2.5, 2.5], [-2.5, 2.5]]\n'
        "floor_z = 0.0\nceiling_z = 2.0\n[reconstruction]\ngrid_step_m = 0.04\n"
        '[[cameras]]\nserial = "cam0"\nsource = "sim"\nview = "A1"\n'
    )
    out = run_cli("process", str(directory), "--json", "--config", str(config))
    assert json.loads(out.stdout)["grid_step_m"] == 0.04
    out = run_cli(
        "process", str(directory), "--json", "--config", str(config), "--grid-step", "0.1"
    )
    assert json.loads(out.stdout)["grid_step_m"] == 0.1
    human = run_cli("process", str(directory), "--method", "rectangle")
    assert human.returncode == 0 and "volume" in human.stdout and "rectangle" in human.stdout


def test_process_does_not_import_open3d_for_bicm(tmp_path, cone_scan_4: Scan) -> None:
    directory = write_scan(cone_scan_4, tmp_path / "scan")
    code = (
        "import sys\nfrom silo_agent.cli import main\n"
        f"main(['process', {str(directory)!r}, '--json'])\n"
        "assert 'open3d' not in sys.modules, 'open3d imported'\n"
        "assert 'pyrealsense2' not in sys.modules\n"
    )
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_slope_correction_reaches_the_whole_of_a_round_region() -> None:
    """Each cell's points sit off its centre on a tilted plane; the correction must bring every
    interior cell of a round silo to the plane at its centre. Outside the circle the map has no
    surface (NaN), which a plain 3 x 3 mean carried along whole rows, switching the correction
    off over most of the region."""
    from silo_agent.grid.filters import dilate_cross
    from silo_agent.grid.grid import Grid
    from silo_agent.reconstruct import _slope_corrected

    step, rows = 0.05, 60
    angle = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    region = np.column_stack([1.5 + 1.4 * np.cos(angle), 1.5 + 1.4 * np.sin(angle)])
    grid = Grid(
        (0.0, 0.0), step, (rows, rows), cell_fractions(region, (0.0, 0.0), step, (rows, rows))
    )
    inside = grid.inside > 0

    def plane(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 0.3 * x - 0.2 * y + 1.0

    xs, ys = grid.centres()
    cx, cy = xs - 0.3 * step, ys - 0.2 * step  # where each cell's points sit
    filled = np.where(inside, plane(cx, cy), np.nan)
    corrected = _slope_corrected(grid, filled, cx, cy, inside)
    interior = ~dilate_cross(~inside, 4)  # its 5 x 5 neighbourhood (mean, then gradient) inside
    assert interior.sum() > 0.6 * inside.sum()
    np.testing.assert_allclose(corrected[interior], plane(xs, ys)[interior], atol=1e-9)


def test_both_sorts_of_the_cell_key_give_the_same_cells(cone_scan_4: Scan, monkeypatch) -> None:
    """numpy's SIMD quicksort (where the CPU has a fast one) or its stable sort: same heights
    and clusters."""
    from silo_agent.reconstruct import cells

    settings = ReconstructionConfig(grid_step_m=0.02)
    results = []
    for simd in (True, False):
        monkeypatch.setattr(cells, "SIMD_SORT", simd)
        results.append(reconstruct(cone_scan_4, settings))
    fast, stable = results
    assert fast.volume_m3 == stable.volume_m3
    assert np.array_equal(fast.heightmap.heights, stable.heightmap.heights, equal_nan=True)
    assert np.array_equal(fast.heightmap.observed, stable.heightmap.observed)


@pytest.mark.parametrize("count", [1, 2, 3, 10, 11, 1000, 1001])
def test_median_is_numpys(count: int) -> None:
    from silo_agent.reconstruct.residual import median

    rng = np.random.default_rng(count)
    for values in (rng.normal(size=count), rng.integers(0, 3, count).astype(float)):
        assert median(values) == float(np.median(values))
    with pytest.raises(ValueError):
        median(np.array([]))
