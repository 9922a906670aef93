"""`[calibration]`: extrinsics calibration, per-scan refinement, measured spacings."""

from __future__ import annotations

from typing import Literal

from pydantic import (
    Field,
    model_validator,
)

from silo_agent.config.base import Strict

SPACING_SIGMA_M = 0.003  # default uncertainty of a measured camera spacing (laser meter)


class SpacingConfig(Strict):
    """A measured distance between two cameras' origins (`[[calibration.spacing]]`).

    The point meant is each camera's origin as its extrinsic places it: the translation of the
    camera -> silo transform (for a D455, the depth frame's origin, the left imager's optical
    centre). `calibrate` holds the two to `distance_m` within about `sigma_m`."""

    a: str = Field(min_length=1, description="serial of one camera")
    b: str = Field(min_length=1, description="serial of the other camera")
    distance_m: float = Field(gt=0, description="measured distance between the two origins")
    sigma_m: float = Field(
        default=SPACING_SIGMA_M, gt=0, description="the measurement's standard uncertainty"
    )

    @model_validator(mode="after")
    def _two_cameras(self) -> SpacingConfig:
        if self.a == self.b:
            raise ValueError(f"a and b are the same camera ({self.a!r}); a spacing needs two")
        return self


class CalibrationConfig(Strict):
    """Calibration (`silo-agent calibrate`), the per-scan registration check and drift alarm."""

    residual_min_points: int = Field(
        default=5, ge=1, description="points each camera needs in a cell for it to be compared"
    )
    residual_min_cells: int = Field(
        default=50, ge=1, description="cells two cameras must share for their residual to count"
    )
    drift_threshold_m: float = Field(
        default=0.005, gt=0, description="|median height disagreement| of a pair that is drift"
    )
    drift_consecutive: int = Field(
        default=3, ge=1, description="scans in a row over a threshold before the alarm is raised"
    )
    max_correction_deg: float = Field(
        default=3.0, gt=0, description="calibrate refuses to turn a camera by more than this"
    )
    max_correction_m: float = Field(
        default=0.10, gt=0, description="calibrate refuses to move a camera by more than this"
    )
    prior_deg: float = Field(
        default=1.0, gt=0, description="expected placement error (rotation) of a configured camera"
    )
    prior_m: float = Field(
        default=0.02, gt=0, description="expected placement error (position) of a configured camera"
    )
    icp_voxel_m: float = Field(default=0.02, gt=0, description="ICP down-sampling voxel")
    icp_max_distance_m: float = Field(
        default=0.08, gt=0, description="ICP's first (coarsest) correspondence distance"
    )
    min_overlap: float = Field(
        default=0.2, gt=0, le=1, description="ICP fitness below which two views do not overlap"
    )
    floor_band_m: float = Field(
        default=0.15, gt=0, description="points this close to floor_z are floor candidates"
    )
    floor_max_range_m: float = Field(
        default=8.0,
        gt=0,
        description="floor points farther from their camera are left out (the fit weighs the "
        "rest by their noise)",
    )
    refine: bool = Field(
        default=False, description="every scan: bounded ICP on the overlaps before reconstructing"
    )
    level: Literal["auto"] | bool = Field(
        default="auto",
        description="every scan: each camera that sees bare floor is leveled on it (as --floor); "
        "auto: on a site without [silo.bin] whose base is the floor",
    )
    refine_max_deg: float = Field(
        default=0.5, gt=0, description="per-scan bound of refine's and level's corrections"
    )
    refine_max_m: float = Field(
        default=0.02, gt=0, description="per-scan bound of refine's and level's corrections"
    )
    spacing: list[SpacingConfig] = Field(
        default=[], description="measured camera-to-camera distances calibrate holds to"
    )

    def levels(self, in_bin: bool, base: str) -> bool:
        """Whether every scan on a site is leveled on its floor (`in_bin`: the site has
        `[silo.bin]`; `base`: its `silo.base`): `level`, or for "auto" on a site without a bin
        whose base is the floor. With 0.1 deg / 3 mm placement errors it
        took the open scenes' volume error from 0.96 / 0.99 / 1.35 % to 0.59 / 0.31 / 0.15 %
        with 2 / 3 / 4 views (docs/calibration.md); in a bin the grain covers the floor, and
        thin level grain would be taken for it."""
        if self.level != "auto":
            return self.level
        return not in_bin and base == "floor"
