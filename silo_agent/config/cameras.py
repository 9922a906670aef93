"""`[[cameras]]` and `[simulation]`: the cameras, real or simulated."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    Field,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from silo_agent.base.choices import (
    DEFAULT_GRAIN,
    DEFAULT_LAYOUT,
    DEFAULT_MAX_DEPTH_M,
    DEFAULT_MIN_DEPTH_M,
    SCENE_NAMES,
    VIEW_NAMES,
    Grain,
    Layout,
    layout_misfit,
    site_misfit,
)
from silo_agent.base.d455 import MAX_HEIGHT_PX, MAX_WIDTH_PX, MIN_IMAGE_PX
from silo_agent.base.limits import MAX_DURATION_S
from silo_agent.config.base import Matrix4, Strict
from silo_agent.grid.geometry import (
    rigid_transform_problem,
    transform_from_euler,
)


class CameraConfig(Strict):
    serial: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    source: Literal["realsense", "playback", "sim"] = "realsense"
    playback: Path | None = None
    extrinsic: Matrix4 | None = None
    rotate_deg: tuple[float, float, float] | None = None
    translate_m: tuple[float, float, float] | None = None
    view: str | None = Field(default=None, description="sim only: a named layout position")
    width: int = Field(
        default=848, ge=MIN_IMAGE_PX, le=MAX_WIDTH_PX, description="depth image width, pixels"
    )
    height: int = Field(
        default=480, ge=MIN_IMAGE_PX, le=MAX_HEIGHT_PX, description="depth image height, pixels"
    )
    fps: int = 30
    frames: int = Field(default=10, ge=1, description="depth frames aggregated per capture")
    warmup_frames: int = Field(default=30, ge=0)
    timeout_s: float = Field(default=10.0, gt=0, le=MAX_DURATION_S)
    color: bool = Field(
        default=False, description="also stream colour, aligned to depth, one RGB per point"
    )
    emitter: bool = Field(default=True, description="IR projector on (texture for flat grain)")
    visual_preset: Literal["default", "high_accuracy", "high_density", "medium_density", "hand"] = (
        Field(default="high_accuracy", description="D4xx depth preset: fewer, surer points")
    )
    laser_power_mw: float | None = Field(
        default=None, ge=0, description="projector power; None keeps the device's default"
    )
    min_depth_m: float = Field(
        default=DEFAULT_MIN_DEPTH_M, ge=0, description="threshold filter: nearer is dropped"
    )
    max_depth_m: float = Field(
        default=DEFAULT_MAX_DEPTH_M, gt=0, description="threshold filter: farther dropped"
    )
    decimation: int = Field(default=1, ge=1, le=8, description="decimation factor; 1 = off")
    spatial_filter: bool = Field(default=True, description="edge-preserving spatial smoothing")
    temporal_filter: bool = Field(default=True, description="smoothing over successive frames")
    aggregation: Literal["median", "temporal"] = Field(
        default="median",
        description="per-pixel median of the N filtered frames, or the temporal filter's last",
    )
    min_valid_fraction: float = Field(
        default=0.5, gt=0, le=1, description="median: a pixel needs depth in this share of frames"
    )
    retries: int = Field(default=2, ge=0, description="live: hardware resets + retries on failure")
    reset_wait_s: float = Field(
        default=20.0,
        gt=0,
        le=MAX_DURATION_S,
        description="live: how long to wait for re-enumeration after a reset",
    )
    imu_samples: int = Field(default=50, ge=1, description="accelerometer samples averaged")
    gravity_tolerance_deg: float = Field(
        default=3.0, gt=0, description="warn when IMU and extrinsic vertical differ by more"
    )

    @field_validator("view")
    @classmethod
    def _known_view(cls, view: str | None) -> str | None:
        if view is not None and view not in VIEW_NAMES:
            raise ValueError(f"unknown view {view!r}, expected one of {', '.join(VIEW_NAMES)}")
        return view

    @model_validator(mode="after")
    def _one_pose(self) -> CameraConfig:
        has_matrix = self.extrinsic is not None
        has_euler = self.rotate_deg is not None or self.translate_m is not None
        if has_matrix and has_euler:
            raise ValueError("give either extrinsic or rotate_deg/translate_m, not both")
        if self.source == "playback" and self.playback is None:
            raise ValueError("source = 'playback' needs playback = FILE")
        if not has_matrix and not has_euler:
            if self.source != "sim":
                raise ValueError("needs extrinsic (4x4) or rotate_deg + translate_m")
            if self.view is None:  # it could not be placed: every capture of it failed
                raise ValueError(
                    "a sim camera needs view = 'A1'..'A8', extrinsic (4x4) "
                    "or rotate_deg + translate_m"
                )
        if self.max_depth_m <= self.min_depth_m:
            raise ValueError(
                f"max_depth_m ({self.max_depth_m}) must be above min_depth_m ({self.min_depth_m})"
            )
        if self.aggregation == "temporal" and not self.temporal_filter:
            raise ValueError("aggregation = 'temporal' needs temporal_filter = true")
        matrix = self.extrinsic_matrix()
        if matrix is not None:
            problem = rigid_transform_problem(matrix)
            if problem:
                raise ValueError(f"{'extrinsic' if has_matrix else 'translate_m'}: {problem}")
        return self

    def extrinsic_matrix(self) -> np.ndarray | None:
        """Camera -> silo transform, or None for a sim camera placed by its `view`."""
        if self.extrinsic is not None:
            return np.asarray(self.extrinsic, dtype=float)
        if self.rotate_deg is None and self.translate_m is None:
            return None
        return transform_from_euler(self.rotate_deg or (0, 0, 0), self.translate_m or (0, 0, 0))


def _known_scene(scene: str) -> str:
    if scene not in SCENE_NAMES:
        raise ValueError(f"unknown scene {scene!r}, expected one of {', '.join(SCENE_NAMES)}")
    return scene


SceneName = Annotated[str, AfterValidator(_known_scene)]


class SimulationConfig(Strict):
    scene: SceneName = "cone"
    sequence: list[SceneName] = Field(
        default=[], description="scenes taken scan after scan (the last one stays); overrides scene"
    )
    vary_noise: bool = Field(
        default=False, description="new sensor noise every scan, as a real camera gives"
    )
    capture_s: float = Field(
        default=0.0,
        ge=0,
        le=600,
        description="seconds each camera's capture takes (a D455's warm-up and frames: ~1.5 s)",
    )
    grain: Grain = DEFAULT_GRAIN
    seed: int = Field(default=0, ge=0, description="same seed, same scans (numpy takes >= 0)")
    layout: Layout = DEFAULT_LAYOUT
    calib_error_deg: float = Field(default=0.0, ge=0)
    calib_error_m: float = Field(default=0.0, ge=0)

    @model_validator(mode="after")
    def _layout_fits(self) -> SimulationConfig:
        """A layout that cannot place the cameras in a scene passed `check-config` and failed
        every capture of that scene; refused here, naming the layout or the sequence entry. So
        is a sequence entry on another site than the first (`base.choices.SCENE_SITES`)."""
        scenes = [(f"simulation.sequence.{k}", name) for k, name in enumerate(self.sequence)]
        for key, scene in scenes or [("simulation.layout", self.scene)]:
            misfit = layout_misfit(scene, self.layout)
            if misfit is not None:
                raise PydanticCustomError("config_key", "{misfit}", {"key": key, "misfit": misfit})
        for key, scene in scenes:  # another site's scene was rendered from the first's cameras
            misfit = site_misfit(self.sequence[0], scene)
            if misfit is not None:
                raise PydanticCustomError("config_key", "{misfit}", {"key": key, "misfit": misfit})
        return self
