"""Alarms against height maps built here, independently of the reconstruction: a flat grain
surface with D455-like noise, and the same surface with an analytic funnel cut into it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from silo_agent.analysis.alarm_types import ALARM_TYPES
from silo_agent.analysis.alarms import (
    DETECTORS,
    AlarmState,
    Finding,
    Inputs,
    evaluate,
    find_collapses,
    noise_floor,
)
from silo_agent.config import AlarmsConfig
from silo_agent.grid.heightmap import HeightMap

STEP = 0.05
HALF = 3.0
LEVEL = 1.2
FUNNEL = (0.4, -0.3)
FUNNEL_RADIUS = 1.0
FUNNEL_DEPTH = 0.5


def grid() -> tuple[np.ndarray, np.ndarray]:
    n = int(2 * HALF / STEP)
    centres = -HALF + (np.arange(n) + 0.5) * STEP
    return np.meshgrid(centres, centres)


def surface(
    rng: np.random.Generator,
    *,
    funnel: bool = False,
    sigma: float = 0.01,
    observed_share: float = 0.9,
) -> HeightMap:
    """Flat grain at LEVEL with independent noise plus smooth (correlated) noise, a share of the
    cells unobserved at random; optionally a cone-shaped funnel of FUNNEL_DEPTH."""
    x, y = grid()
    z = np.full(x.shape, LEVEL) + rng.normal(0, sigma, x.shape)
    z += 0.5 * sigma * np.sin(x * 2.1 + rng.uniform(0, 6)) * np.cos(y * 1.7 + rng.uniform(0, 6))
    if funnel:
        r = np.hypot(x - FUNNEL[0], y - FUNNEL[1])
        z -= FUNNEL_DEPTH * np.clip(1 - r / FUNNEL_RADIUS, 0, None)
    observed = rng.random(x.shape) < observed_share
    return HeightMap((-HALF, -HALF), STEP, z.astype(np.float32), observed, np.ones(x.shape))


def inputs(
    hm: HeightMap,
    scan_id: str,
    baseline: HeightMap | None = None,
    baseline_id: str | None = None,
    **kw,
) -> Inputs:
    return Inputs(
        scan_id=scan_id,
        heightmap=hm,
        volume_m3=kw.pop("volume_m3", 43.0),
        coverage=kw.pop("coverage", 0.9),
        valid=True,
        ceiling_z=kw.pop("ceiling_z", 2.8),
        max_z=kw.pop("max_z", 1.3),
        baseline=baseline,
        baseline_scan_id=baseline_id,
        **kw,
    )


def test_funnel_is_found_where_it_is_with_its_size_depth_and_volume():
    rng = np.random.default_rng(1)
    found = find_collapses(surface(rng), surface(rng, funnel=True), 0.10, 0.25, 5.0)
    assert len(found) == 1
    c = found[0]
    assert np.hypot(c.centroid[0] - FUNNEL[0], c.centroid[1] - FUNNEL[1]) < 0.05
    # cells dropped by more than 0.10 m: r < R (1 - 0.1/D)
    r_edge = FUNNEL_RADIUS * (1 - 0.10 / FUNNEL_DEPTH)
    assert c.area_m2 == pytest.approx(np.pi * r_edge**2, rel=0.15)
    assert c.depth_m == pytest.approx(FUNNEL_DEPTH, abs=0.05)
    cone_volume = np.pi * FUNNEL_RADIUS**2 * FUNNEL_DEPTH / 3  # nearly all of it is in the region
    assert c.volume_m3 == pytest.approx(cone_volume, rel=0.15)


def test_noise_alone_never_raises_a_collapse():
    rng = np.random.default_rng(2)
    for sigma in (0.005, 0.02, 0.05):  # 5 cm: worse than a D455 at 4 m on grain
        for _ in range(10):
            assert (
                find_collapses(
                    surface(rng, sigma=sigma), surface(rng, sigma=sigma), 0.10, 0.25, 5.0
                )
                == []
            )


def correlated(rng: np.random.Generator, sigma: float) -> HeightMap:
    """Flat grain with depth error correlated over ~0.25 m (the D455's is partly correlated,
    and a recalibrated or warmed-up camera shifts whole patches): blobs, not speckle."""
    hm = surface(rng, sigma=0.005)
    blobs = ndimage.gaussian_filter(rng.normal(0, 1, hm.heights.shape), 0.25 / STEP)
    blobs *= sigma / blobs.std()
    return HeightMap(
        hm.origin, STEP, (hm.heights + blobs).astype(np.float32), hm.observed, hm.inside
    )


def test_correlated_noise_raises_nothing_thanks_to_the_noise_floor():
    rng = np.random.default_rng(12)
    pairs = [(correlated(rng, 0.04), correlated(rng, 0.04)) for _ in range(10)]
    assert all(find_collapses(a, b, 0.10, 0.25, 5.0) == [] for a, b in pairs)
    # without the noise floor (k = 0) the same blobs pass for collapses
    assert sum(bool(find_collapses(a, b, 0.10, 0.25, 0.0)) for a, b in pairs) >= 3


def test_noise_floor_tracks_the_maps_noise():
    rng = np.random.default_rng(3)
    a, b = surface(rng, sigma=0.03), surface(rng, sigma=0.03)
    both = a.observed & b.observed
    assert noise_floor(a, b, both) == pytest.approx(0.03 * np.sqrt(2), rel=0.3)
    # and it raises the bar: a 0.12 m drop over a large area is not above 5 sigma of 4 cm noise
    x, y = grid()
    dip = np.where(np.hypot(x, y) < 0.8, 0.12, 0.0)
    lowered = HeightMap(
        b.origin, b.step, (b.heights - dip).astype(np.float32), b.observed, b.inside
    )
    assert find_collapses(a, lowered, 0.10, 0.25, 5.0) == []
    quiet_a, quiet_b = surface(rng, sigma=0.005), surface(rng, sigma=0.005)
    quiet_lowered = HeightMap(
        quiet_b.origin,
        STEP,
        (quiet_b.heights - dip).astype(np.float32),
        quiet_b.observed,
        quiet_b.inside,
    )
    assert len(find_collapses(quiet_a, quiet_lowered, 0.10, 0.25, 5.0)) == 1


def test_only_cells_observed_in_both_maps_count():
    rng = np.random.default_rng(4)
    before, after = surface(rng), surface(rng, funnel=True)
    x, y = grid()
    hidden = np.hypot(x - FUNNEL[0], y - FUNNEL[1]) < FUNNEL_RADIUS
    after = HeightMap(after.origin, STEP, after.heights, after.observed & ~hidden, after.inside)
    assert find_collapses(before, after, 0.10, 0.25, 5.0) == []


def test_small_drops_below_the_minimum_area_are_ignored():
    rng = np.random.default_rng(5)
    before, after = surface(rng), surface(rng, funnel=True)
    assert find_collapses(before, after, 0.10, 5.0, 5.0) == []  # 5 m²: larger than the funnel


def test_lifecycle_raises_once_keeps_the_baseline_and_clears_when_filled():
    cfg = AlarmsConfig()
    rng = np.random.default_rng(6)
    state = AlarmState()
    maps = {
        "s1": surface(rng),
        "s2": surface(rng),
        "s3": surface(rng, funnel=True),
        "s4": surface(rng, funnel=True),
        "s5": surface(rng),
        "s6": surface(rng),
    }
    log = []
    for scan_id, hm in maps.items():
        base_id = state.baseline_scan_id
        events, state = evaluate(state, inputs(hm, scan_id, maps.get(base_id), base_id), cfg)
        log.append((scan_id, [(e.type, e.state) for e in events], state.baseline_scan_id))
    assert log == [
        ("s1", [], "s1"),
        ("s2", [], "s2"),
        ("s3", [("collapse", "raised")], "s2"),  # baseline pinned while the hole is open
        ("s4", [], "s2"),
        ("s5", [("collapse", "cleared")], "s5"),
        ("s6", [], "s6"),
    ]


def test_collapse_event_payload():
    rng = np.random.default_rng(7)
    before, after = surface(rng), surface(rng, funnel=True)
    events, state = evaluate(
        AlarmState(baseline_scan_id="b"), inputs(after, "n", before, "b"), AlarmsConfig()
    )
    (event,) = events
    assert event.type == "collapse" and event.state == "raised"
    assert event.severity == "critical" and event.scan_id == "n"
    assert np.hypot(event.position[0] - FUNNEL[0], event.position[1] - FUNNEL[1]) < 0.05
    assert event.depth_m > 0.4 and event.area_m2 > 1.5 and event.volume_m3 > 0.4
    assert "collapse" in state.active
    from silo_agent.telemetry.payloads import Envelope, alarm_payload

    alarm_payload(Envelope.new(1), event)  # publishable as it is


def test_level_high_with_hysteresis():
    cfg = AlarmsConfig(high_level_margin_m=0.3, hysteresis=0.5)
    rng = np.random.default_rng(8)
    hm = surface(rng)
    state = AlarmState()
    seen = []
    for max_z in (2.4, 2.55, 2.4, 2.3):  # ceiling 2.8: raise within 0.3, clear beyond 0.45
        events, state = evaluate(state, inputs(hm, f"s{max_z}", max_z=max_z), cfg)
        seen.append([(e.type, e.state) for e in events if e.type == "level_high"])
    assert seen == [[], [("level_high", "raised")], [], [("level_high", "cleared")]]


def test_low_volume_change_and_faults():
    cfg = AlarmsConfig(low_volume_m3=10.0, change_fraction=0.2)
    rng = np.random.default_rng(9)
    hm = surface(rng)
    state = AlarmState()

    def step(scan_id, **kw):
        nonlocal state
        events, state = evaluate(state, inputs(hm, scan_id, **kw), cfg)
        return sorted((e.type, e.state) for e in events)

    assert step("a", volume_m3=40.0) == []
    assert step("b", volume_m3=30.0) == [("change", "raised")]  # -25 % in one scan
    assert step("c", volume_m3=29.5) == [("change", "cleared")]
    assert step("d", volume_m3=9.0) == [("change", "raised"), ("level_low", "raised")]
    assert step("e", volume_m3=9.2) == [("change", "cleared")]
    assert step("f", volume_m3=10.5) == []  # above 10, but low clears only above 10 x 1.5
    assert step("f2", volume_m3=12.5) == []  # +19 %: below the 20 % of a change
    assert step("f3", volume_m3=15.2) == [("change", "raised"), ("level_low", "cleared")]
    assert step("f4", volume_m3=15.5) == [("change", "cleared")]
    assert step(
        "g", volume_m3=15.5, failed_cameras=(("cam-2", "timeout"),), coverage=0.1, cache_full=True
    ) == [("cache", "raised"), ("camera", "raised"), ("coverage", "raised")]
    assert step("h", volume_m3=15.5) == [
        ("cache", "cleared"),
        ("camera", "cleared"),
        ("coverage", "cleared"),
    ]


def test_another_alarm_type_plugs_in():
    def drift(inp, cfg, active):
        return Finding(inp.scan_id == "x2", "warning", "camera moved", {"value": 1.5})

    rng = np.random.default_rng(10)
    state = AlarmState()
    kinds = []
    for scan_id in ("x1", "x2", "x3"):
        events, state = evaluate(
            state,
            inputs(surface(rng), scan_id),
            AlarmsConfig(),
            detectors={"calibration_drift": drift},
        )
        kinds.append([(e.type, e.state, e.value) for e in events])
    assert kinds == [
        [],
        [("calibration_drift", "raised", 1.5)],
        [("calibration_drift", "cleared", 1.5)],
    ]


def test_disabled_alarms_raise_nothing_but_state_carries_on():
    rng = np.random.default_rng(11)
    events, state = evaluate(
        AlarmState(), inputs(surface(rng), "a", coverage=0.0), AlarmsConfig(enabled=False)
    )
    assert events == [] and state.baseline_scan_id == "a"
    assert AlarmState.from_json(state.to_json()) == state


def test_a_switched_off_detector_clears_its_alarm_in_the_next_scan():
    """level_low raised, then low_volume_m3 removed (restart with the new config): the next
    scan clears it with a `cleared` event; alarms.enabled = false clears whatever is raised."""
    rng = np.random.default_rng(12)
    _, state = evaluate(
        AlarmState(),
        inputs(surface(rng), "a", volume_m3=5.0, coverage=0.1),
        AlarmsConfig(low_volume_m3=10.0),
    )
    assert set(state.active) == {"level_low", "coverage"}
    events, after = evaluate(
        state, inputs(surface(rng), "b", volume_m3=5.0, coverage=0.1), AlarmsConfig()
    )
    assert [(e.type, e.state, e.scan_id) for e in events] == [("level_low", "cleared", "b")]
    assert "low_volume_m3" in events[0].message and set(after.active) == {"coverage"}
    events, off = evaluate(
        state, inputs(surface(rng), "c", coverage=0.1), AlarmsConfig(enabled=False)
    )
    assert sorted((e.type, e.state) for e in events) == [
        ("coverage", "cleared"),
        ("level_low", "cleared"),
    ]
    assert off.active == {}


def test_alarm_types_every_consumer_declares_are_the_detectors_ones():
    assert set(ALARM_TYPES) == set(DETECTORS) | {"calibration", "outbox"}


@pytest.mark.slow
def test_a_big_bins_collapse_is_judged_by_the_noise_where_it_is() -> None:
    """Two scans of the simulator's 18 m bin from eight full-resolution eave cameras: the ring
    15-19 m from them is three times as noisy as the heap below them, and one sigma for the
    whole map, set by the ring's many cells, asked a drop of 0.58 m anywhere: a funnel 0.5 m
    deep in the heap's flank was missed. Judged by the noise where it is (the cameras' noise
    model, `Inputs.information`), it raises the alarm there, and the same bin scanned again
    with nothing changed raises none."""
    from dataclasses import replace

    from silo_agent.config import ReconstructionConfig
    from silo_agent.reconstruct import reconstruct
    from silo_agent.sim.simulate import simulate

    views = [f"A{k}" for k in range(1, 9)]
    first, second = (
        reconstruct(
            simulate("bin-18", views, seed=seed, layout="eave", resolution=(1280, 720)),
            ReconstructionConfig(grid_step_m=0.02),
        )
        for seed in (0, 1)
    )
    before, after = first.heightmap, second.heightmap
    assert before is not None and after is not None and second.information is not None
    x, y = after.cell_centres()
    at = (2.0, 0.0)  # on the heap's flank, under the cameras
    funnel = 0.5 * np.clip(1 - np.hypot(x - at[0], y - at[1]) / 1.0, 0, None)
    dropped = replace(after, heights=(after.heights - funnel).astype(after.heights.dtype))
    cfg = AlarmsConfig()

    def collapse(new: HeightMap, information: np.ndarray | None) -> list[tuple[float, float]]:
        state = AlarmState(baseline_scan_id="first")
        scan = inputs(new, "second", before, "first", information=information)
        events, _ = evaluate(state, scan, cfg)
        return [e.position for e in events if e.type == "collapse" and e.state == "raised"]

    (where,) = collapse(dropped, second.information)
    assert np.hypot(where[0] - at[0], where[1] - at[1]) < 0.3
    assert collapse(after, second.information) == []  # the same bin again: no collapse
    assert collapse(dropped, None) == []  # one sigma for the whole map misses it
