"""Geometric pile detector against the simulator's per-pile truth (issue 8)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from silo_agent.analysis.scan_analysis import ScanAnalysis, analyse
from silo_agent.analysis.summary import ScanSummary, summarise
from silo_agent.config import DetectionConfig, ReconstructionConfig
from silo_agent.detect import Pile, match_ids
from silo_agent.detect.geometric import DETECTION_STEP_M, Surface, detection_map, grid_of
from silo_agent.grid.geometry import points_outside
from silo_agent.grid.volume import base_surface
from silo_agent.reconstruct import Reconstruction, reconstruct
from silo_agent.scan import Scan, write_scan
from silo_agent.sim import make_scene, simulate
from silo_agent.sim.scenes import _bay

VIEWS = ["A1", "A3", "A5", "A7"]
SETTINGS = ReconstructionConfig()


@pytest.fixture(scope="module")
def piles_scan() -> Scan:
    return simulate(make_scene("piles"), VIEWS, seed=1)


@pytest.fixture(scope="module")
def piles_result(piles_scan: Scan):
    return analyse(piles_scan, SETTINGS, DetectionConfig())


def nearest(piles: list[Pile], xy: tuple[float, float]) -> Pile:
    return min(piles, key=lambda p: np.hypot(p.centroid[0] - xy[0], p.centroid[1] - xy[1]))


@pytest.fixture(scope="module")
def fine_result(piles_scan: Scan):
    """The same scan on a 1 cm grid: its piles are found on 2 cm blocks (`detection_map`)."""
    return analyse(piles_scan, ReconstructionConfig(grid_step_m=0.01), DetectionConfig())


@pytest.mark.parametrize("result", ["piles_result", "fine_result"])
def test_finds_every_pile_with_its_centroid_and_volume(result: str, request) -> None:
    piles_result = request.getfixturevalue(result)
    truth = make_scene("piles").piles
    piles = piles_result.piles
    assert len(piles) == len(truth)
    assert {p.detector for p in piles} == {"geometric"}
    matched = [nearest(piles, t.centroid[:2]) for t in truth]
    assert len({p.id for p in matched}) == len(truth)  # one detected pile per true pile
    for t, p in zip(truth, matched, strict=True):
        assert np.hypot(p.centroid[0] - t.centroid[0], p.centroid[1] - t.centroid[1]) < 0.1
        assert abs(p.volume_m3 - t.volume_m3) < 0.03 * t.volume_m3, (t, p)
        assert abs(p.peak_height_m - t.apex[2]) < 0.05
        assert np.hypot(p.peak[0] - t.apex[0], p.peak[1] - t.apex[1]) < 0.1
    # the piles share the engine's volume: together they are the scan's volume
    volume = piles_result.reconstruction.volume_m3
    assert sum(p.volume_m3 for p in piles) == pytest.approx(volume, rel=0.01)
    # largest first, ids 1..n without an earlier scan
    assert [p.id for p in piles] == [1, 2, 3, 4]
    assert [p.volume_m3 for p in piles] == sorted((p.volume_m3 for p in piles), reverse=True)


def test_pile_columns_are_the_volume_s_own(piles_result) -> None:
    """Every cell's column is the published volume's: summed over the whole map they give the
    scan's volume to rounding, so piles never claim volume the scan does not count."""
    result = piles_result.reconstruction
    hm = result.heightmap
    base = base_surface(grid_of(hm), hm.heights.astype(float), "floor", result.floor_z)
    surface = Surface.of(hm, base, result.floor_z, None)
    assert float(np.sum(surface.columns)) == pytest.approx(result.volume_m3, rel=1e-12)


def test_a_fine_map_is_searched_in_blocks_that_keep_its_volume(fine_result) -> None:
    """A 1 cm map is searched in 2 x 2 blocks, up to DETECTION_STEP_M wide, whose columns
    still add up to the published volume; a map whose cells are wider than half of it is
    searched as it is."""
    fine = fine_result.reconstruction.heightmap
    blocks = detection_map(fine)
    assert blocks.step == pytest.approx(DETECTION_STEP_M)
    assert blocks.shape == tuple(-(-n // 2) for n in fine.shape)
    # the blocks' share of the region is the region's area
    assert float(np.sum(blocks.inside)) * blocks.step**2 == pytest.approx(
        float(np.sum(fine.inside)) * fine.step**2, rel=1e-12
    )
    surface = Surface.for_piles(fine, "floor", fine.floor_z, None)  # as `analyse` finds piles
    assert surface.heightmap.step == pytest.approx(DETECTION_STEP_M)
    volume = fine_result.reconstruction.volume_m3
    assert float(np.sum(surface.columns)) == pytest.approx(volume, rel=1e-9)
    assert detection_map(blocks) is blocks
    wider = dataclasses.replace(fine, step=0.015)  # two of its cells would be 3 cm
    assert detection_map(wider) is wider


def test_summary_and_description_carry_the_piles(piles_result) -> None:
    summary = json.loads(json.dumps(_summary(piles_result).to_json(), allow_nan=False))
    assert summary["robots"] is None  # no model configured
    first = summary["piles"][0]
    assert set(first) == {
        "id",
        "detector",
        "centroid",
        "peak",
        "peak_height_m",
        "footprint_m2",
        "volume_m3",
        "confidence",
    }
    assert Pile.from_json(first) == piles_result.piles[0]
    text = piles_result.describe()
    assert "piles     4" in text and text.count(" geometric ") == 4


def _summary(result: ScanAnalysis) -> ScanSummary:
    return summarise(result, "2026-11-22T02:00:00Z", [], {"capture_s": 1.0})


def test_the_reconstruction_leaves_piles_and_robots_to_the_analysis(piles_result) -> None:
    """`Reconstruction` is the reconstruction's alone; the summary puts the detection's keys
    and lines where result.json, `P/scan` and `process` have always had them."""
    assert isinstance(piles_result, ScanAnalysis)
    assert not {f.name for f in dataclasses.fields(Reconstruction)} & {"piles", "robots"}
    assert list(_summary(piles_result).to_json()) == [
        "scan_id",
        "method",
        "volume_m3",
        "mass_t",
        "coverage",
        "grid_step_m",
        "surface",
        "level",
        "valid",
        "invalid_reason",
        "capacity_m3",
        "fill_ratio",
        "headspace_m",
        "headspace_mean_m",
        "cameras",
        "points",
        "parameters",
        "timings_s",
        "piles",
        "robots",
        "registration_residual_m",
        "registration_residual",
        "captured_at",
        "degraded",
        "timings",
    ]
    lines = piles_result.describe().splitlines()
    at = lines.index("piles     4")
    assert lines[at - 1] == "valid     yes" and lines[-1].startswith("time ")
    assert len(lines) == at + 1 + 4 + 1  # the pile count, a line per pile, the time


def flat_scene(level: float):
    """A walled bay with grain at one level everywhere: no pile anywhere."""
    crater = make_scene("crater")
    return dataclasses.replace(
        crater,
        name="flat",
        height=_bay(lambda x, y: np.full(np.shape(x), level), 3.0),
        volume_m3=level * 36.0,
        target=(0.0, 0.0, level),
    )


def test_no_pile_on_a_bare_floor() -> None:
    floor = dataclasses.replace(
        make_scene("cone"),
        name="floor",
        height=lambda x, y: np.zeros(np.shape(x)),
        volume_m3=0.0,
        target=(0.0, 0.0, 0.0),
    )
    result = analyse(simulate(floor, VIEWS, seed=3), SETTINGS, DetectionConfig())
    assert result.piles == []


def test_a_flat_level_is_one_heap_above_the_floor_and_no_pile_above_its_background() -> None:
    scan = simulate(flat_scene(1.2), VIEWS, seed=4)
    heap = analyse(scan, SETTINGS, DetectionConfig())
    assert len(heap.piles) == 1  # noise bumps on the level are not piles of their own
    assert heap.piles[0].volume_m3 == pytest.approx(heap.reconstruction.volume_m3, rel=1e-6)
    assert heap.piles[0].footprint_m2 == pytest.approx(36.0, rel=0.01)
    assert analyse(scan, SETTINGS, DetectionConfig(background_m=2.0)).piles == []


def shifted(scan: Scan, dx: float, dy: float) -> Scan:
    """The same rig moved by (dx, dy) in the silo frame: every pile appears shifted by it."""
    cameras = []
    for c in scan.cameras:
        extrinsic = c.extrinsic.copy()
        extrinsic[:2, 3] += (dx, dy)
        cameras.append(dataclasses.replace(c, extrinsic=extrinsic))
    return dataclasses.replace(scan, cameras=cameras)


def test_pile_ids_stay_with_their_piles_across_scans(piles_result) -> None:
    truth = make_scene("piles").piles
    second_scan = shifted(simulate(make_scene("piles"), VIEWS, seed=2), 0.06, -0.04)
    # an earlier scan whose ids are not 1..4 in volume order
    piles = reversed(piles_result.piles)
    earlier = [dataclasses.replace(p, id=10 + i) for i, p in enumerate(piles)]
    second = analyse(second_scan, SETTINGS, DetectionConfig(), previous=earlier)
    for t in truth:
        before = nearest(earlier, t.centroid[:2])
        after = nearest(second.piles, (t.centroid[0] + 0.06, t.centroid[1] - 0.04))
        assert after.id == before.id
        assert (
            np.hypot(
                after.centroid[0] - before.centroid[0] - 0.06,
                after.centroid[1] - before.centroid[1] + 0.04,
            )
            < 0.05
        )


def pile(pile_id: int, x: float, y: float, detector: str = "geometric") -> Pile:
    return Pile(pile_id, detector, (x, y), (x, y), 0.5, 1.0, 0.2)


def test_match_ids_pairs_by_position_and_numbers_new_piles_above_the_old() -> None:
    old = [pile(3, 0.0, 0.0), pile(7, 1.0, 0.0), pile(5, 3.0, 3.0)]
    new = [pile(0, 1.1, 0.1), pile(0, -2.0, 0.0), pile(0, 0.05, -0.05), pile(0, 0.2, 0.0)]
    ids = [p.id for p in match_ids(old, new, max_distance_m=0.5)]
    # 1.1,0.1 -> 7; -2,0 is new; of the two near pile 3 the nearer keeps it; pile 5 vanished
    assert ids == [7, 8, 3, 9]
    # a pile of another detector never takes over an id
    assert match_ids([pile(4, 0.0, 0.0, "onnx")], [pile(0, 0.0, 0.0)], 0.5)[0].id == 5
    assert [p.id for p in match_ids([], new[:2], 0.5)] == [1, 2]


def test_exclusion_discs_drop_exactly_the_points_inside(piles_scan: Scan) -> None:
    plain = reconstruct(piles_scan, SETTINGS)
    again = reconstruct(piles_scan, SETTINGS, exclude=())
    assert again.volume_m3 == plain.volume_m3  # default behaviour unchanged
    assert np.array_equal(again.heightmap.heights, plain.heightmap.heights, equal_nan=True)
    disc = (1.3, 1.1, 0.3)
    cut = reconstruct(piles_scan, SETTINGS, exclude=[disc])
    # independent count: in-region points within 0.3 m of (1.3, 1.1), by brute force
    silo = np.concatenate([c.points_in_silo() for c in piles_scan.cameras]).astype(float)
    region = piles_scan.site.region
    inside = (np.abs(silo[:, 0]) < region[:, 0].max()) & (np.abs(silo[:, 1]) < region[:, 1].max())
    inside &= silo[:, 2] <= piles_scan.site.ceiling_z
    in_disc = inside & ((silo[:, 0] - 1.3) ** 2 + (silo[:, 1] - 1.1) ** 2 <= 0.09)
    assert plain.points["in_region"] - cut.points["in_region"] == int(in_disc.sum())
    assert points_outside(silo, [disc]).sum() == len(silo) - int(
        (((silo[:, 0] - 1.3) ** 2 + (silo[:, 1] - 1.1) ** 2) <= 0.09).sum()
    )


def test_process_prints_piles_by_default_without_onnxruntime(piles_scan: Scan, tmp_path) -> None:
    directory = write_scan(piles_scan, tmp_path / "scan")
    code = (
        "import json, sys\n"
        "from silo_agent.cli import main\n"
        f"status = main(['process', {str(directory)!r}, '--json'])\n"
        "assert 'onnxruntime' not in sys.modules\n"
        "sys.exit(status)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert len(summary["piles"]) == 4
    assert {p["detector"] for p in summary["piles"]} == {"geometric"}


def test_scan_carries_pile_ids_over_from_the_latest_earlier_result(tmp_path) -> None:
    from silo_agent.config import AuditConfig
    from silo_agent.service.scan_path import previous_piles
    from silo_agent.storage.audit import AuditCache

    def result(scan_id: str, piles: list[Pile]) -> None:
        (tmp_path / scan_id).mkdir()
        manifest = {"silo_id": "silo-1"}  # a cached scan of this silo, time from mtime
        (tmp_path / scan_id / "scan.json").write_text(json.dumps(manifest))
        summary = {"scan_id": scan_id, "piles": [p.to_json() for p in piles]}
        (tmp_path / scan_id / "result.json").write_text(json.dumps(summary))

    result("silo-1-20260101T000000Z", [pile(1, 0.0, 0.0)])
    result("silo-1-20260101T010000Z", [pile(2, 1.0, 1.0), pile(5, 2.0, 0.0, "onnx")])
    result("silo-1-20260101T030000Z", [pile(9, 0.0, 0.0)])  # later than the scan: ignored
    cache = AuditCache(AuditConfig(directory=tmp_path), "silo-1")
    assert previous_piles(cache, "silo-1-20260101T020000Z") == [
        pile(2, 1.0, 1.0),
        pile(5, 2.0, 0.0, "onnx"),
    ]
    assert previous_piles(cache, "silo-1-20251231T000000Z") == []


def test_basin_peaks_are_ndimage_maximum_at_the_first_highest_cell() -> None:
    from scipy import ndimage

    from silo_agent.detect.geometric import _basin_peaks

    rng = np.random.default_rng(3)
    for trial in range(50):
        shape = (int(rng.integers(5, 40)), int(rng.integers(5, 40)))
        values = (
            rng.integers(0, 4, shape).astype(float)
            if trial % 2  # many ties
            else rng.normal(size=shape)
        )
        values[rng.random(shape) < 0.2] = np.nan  # outside the region, label 0
        labels = rng.integers(1, 9, shape)
        labels[np.isnan(values)] = 0
        count = int(labels.max())
        index = np.arange(1, count + 1)
        peaks, where = _basin_peaks(values, labels, count)
        assert np.array_equal(peaks, ndimage.maximum(values, labels, index=index))
        for k, (row, col) in zip(index, where.tolist(), strict=True):
            highest = np.argwhere((labels == k) & (values == peaks[k - 1]))
            assert (row, col) == tuple(highest[0])  # argwhere: row-major order


@pytest.mark.slow
def test_an_18_m_bin_seen_from_its_eave_is_one_heap_not_the_noise_of_its_far_ring(
    tmp_path,
) -> None:
    """Eight eave cameras 9-19 m from the grain leave bumps of 0.1-0.4 m on the level ring by
    the wall; on the bench's 10 cm smoothing they passed the 0.1 m prominence, and `process`
    reported 52 piles where the bin holds one heap. A peak now stands out of the cameras'
    noise there (NOISE_SIGMAS), and only the heap is left, holding the bin's grain."""
    scene = make_scene("bin-18")
    views = [f"A{k}" for k in range(1, 9)]
    scan = simulate(scene, views, seed=0, layout="eave")
    directory = write_scan(scan, tmp_path / "scan")
    done = subprocess.run(
        [sys.executable, "-m", "silo_agent", "process", str(directory), "--json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    (heap,) = summary["piles"]
    assert np.hypot(heap["peak"]["x"], heap["peak"]["y"]) < 0.5  # the heap's apex, at the centre
    assert abs(heap["volume_m3"] - scene.volume_m3) < 0.01 * scene.volume_m3
