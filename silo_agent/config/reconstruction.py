"""`[reconstruction]`: the BICM settings."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import (
    Field,
)

from silo_agent.base.choices import (
    DEFAULT_GRAIN,
    DEFAULT_GRID_STEP_M,
    DEFAULT_METHOD,
    REPOSE_DEG,
    Grain,
    Method,
)
from silo_agent.config.base import Strict


class ReconstructionConfig(Strict):
    """BICM settings (paper 2.3-2.4). `None` means: adapt to the data (see reconstruct.cells)."""

    method: Method = DEFAULT_METHOD
    grid_step_m: float = Field(default=DEFAULT_GRID_STEP_M, gt=0.001, le=1.0)
    voxel_size_m: float | None = Field(
        default=None, gt=0, description="paper 2.3.3 voxel down-sampling; default off"
    )
    cluster_eps_m: float | None = Field(
        default=None, gt=0, description="height gap that separates two clusters in a cell"
    )
    cluster_min_points: int | None = Field(
        default=None, ge=1, description="smallest cluster kept; default relative to the cell"
    )
    max_clusters: int = Field(default=2, ge=1, le=8)
    fill: Literal["auto", "membrane", "bspline", "repose"] = Field(
        default="auto",
        description="how empty cells are filled (reconstruct/fill.py); auto: the repose fill, "
        "in a bin the membrane",
    )
    grain: Grain = Field(
        default=DEFAULT_GRAIN, description="what is stored: its angle of repose bounds the fill"
    )
    repose_deg: float | None = Field(
        default=None, gt=0, lt=90, description="angle of repose; default the grain's"
    )
    slope_correction: bool = True
    depth_noise_factor: float = Field(
        default=2.5,
        gt=0,
        description="the cameras' depth RMS over the D455's ideal-target figure; sets how near "
        "the wall a point is left out while the grain height at the wall is found, and outside "
        "a bin the volume's clip correction (how much of the smoothed floor's noise is taken "
        "back off the clip at the base)",
    )
    min_coverage: float = Field(default=0.3, ge=0, le=1)
    alpha_m: float | None = Field(
        default=None, gt=0, description="alpha baseline radius; default 4 x grid step"
    )
    poisson_depth: int = Field(default=8, ge=4, le=12)

    def fill_for(self, in_bin: bool) -> Literal["membrane", "bspline", "repose"]:
        """The fill used on a site (`in_bin`: it has `[silo.bin]`): `fill`, or for "auto" the
        repose fill, better on every open scene of the accuracy bench, and in a bin the
        membrane, better in round bins (docs/method.md, the fills compared)."""
        if self.fill != "auto":
            return self.fill
        return "membrane" if in_bin else "repose"

    @property
    def repose_slope(self) -> float:
        """Rise per metre of the steepest free grain surface (`repose_deg`, or the grain's)."""
        angle = self.repose_deg if self.repose_deg is not None else REPOSE_DEG[self.grain]
        return math.tan(math.radians(angle))
