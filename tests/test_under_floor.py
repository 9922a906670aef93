"""A measured surface under the floor is a setup error, not an empty silo: the result says so
and is invalid (a floor_z typed 5 m too high read "valid, 0 m³")."""

from __future__ import annotations

import dataclasses

import pytest

from silo_agent.config import ReconstructionConfig
from silo_agent.reconstruct import UNDER_BASE_M, reconstruct
from silo_agent.sim import simulate


@pytest.mark.parametrize(("scene", "views"), [("cone", ["A1", "A5"]), ("hopper-low", ["A1", "A5"])])
def test_a_floor_above_the_grain_makes_the_result_invalid(scene: str, views: list[str]) -> None:
    scan = simulate(scene, views, seed=1, grid_step=0.05, resolution=(424, 240))
    settings = ReconstructionConfig(grid_step_m=0.05)
    right = reconstruct(scan, settings)
    assert right.valid, right.invalid_reason  # the true floor: a measurement, however empty
    raised = 2.0  # metres: above the whole surface of either scene
    site = dataclasses.replace(scan.site, floor_z=scan.site.floor_z + raised)
    if scan.site.bin is not None:
        site = dataclasses.replace(
            site, bin=dataclasses.replace(scan.site.bin, floor_z=scan.site.bin.floor_z + raised)
        )
    wrong = reconstruct(scan, settings, site=site)
    assert not wrong.valid
    assert "under the floor" in (wrong.invalid_reason or "")
    depth = float(wrong.invalid_reason.split(" m under")[0].rsplit(" ", 1)[1])
    assert UNDER_BASE_M < depth <= raised  # the grain stands above the true floor


def test_a_level_empty_floor_is_no_setup_error() -> None:
    """The empty scene's floor, measured with D455 noise around the floor height itself, is
    not 'under' it: the result stays valid."""
    scan = simulate("empty", ["A1", "A5"], seed=2, grid_step=0.05, resolution=(424, 240))
    result = reconstruct(scan, ReconstructionConfig(grid_step_m=0.05))
    assert result.valid, result.invalid_reason
