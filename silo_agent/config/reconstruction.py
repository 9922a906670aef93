"""`[reconstruction]`: the BICM settings."""

from __future__ import annotations

from typing import Literal

from pydantic import (
    Field,
)

from silo_agent.base.choices import (
    DEFAULT_GRID_STEP_M,
    DEFAULT_METHOD,
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
    fill: Literal["membrane", "bspline"] = Field(
        default="membrane", description="how empty cells are filled (reconstruct/fill.py)"
    )
    slope_correction: bool = True
    min_coverage: float = Field(default=0.3, ge=0, le=1)
    alpha_m: float | None = Field(
        default=None, gt=0, description="alpha baseline radius; default 4 x grid step"
    )
    poisson_depth: int = Field(default=8, ge=4, le=12)
