"""Configuration: pydantic models of the TOML file, and the one home of every default.

A bad file is rejected before anything starts, with the file, the key path and what was
expected (`ConfigError`, exit status 78 = EX_CONFIG). Numbers are strict (TOML types already
are): `true` or `"30"` where a number belongs is an error, an integer where a float belongs is
fine. For the service, `load_config` also checks what the file points at (directories it must
write, TLS files) so that `check-config` catches what would otherwise fail only once running.
"""

from __future__ import annotations

import json
import tempfile
import tomllib
from itertools import pairwise
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from silo_agent.choices import (
    DEFAULT_GRAIN,
    DEFAULT_GRID_STEP_M,
    DEFAULT_LAYOUT,
    DEFAULT_METHOD,
    VIEW_NAMES,
    Grain,
    Layout,
    Method,
)
from silo_agent.geometry import (
    check_polygon,
    grid_shape,
    rigid_transform_problem,
    transform_from_euler,
)
from silo_agent.limits import MAX_DURATION_S, MAX_GRID_CELLS

SAFE_ID = r"^[A-Za-z0-9_-]+$"


class ConfigError(Exception):
    """A configuration that cannot be used; the message names file, key and expectation."""


class Strict(BaseModel):
    # defer_build: a model's validator is built when first used, so `process` (which validates
    # a scan's reconstruction, detection and calibration settings) does not build the rest;
    # sections default through default_factory for the same reason
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, defer_build=True)


def _host_name(host: str) -> str:
    if not host or any(c.isspace() for c in host):
        raise ValueError(f"want a host name or IP address, got {host!r}")
    return host


HostName = Annotated[str, AfterValidator(_host_name)]
Point2 = tuple[float, float]
Matrix4 = tuple[
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
    tuple[float, float, float, float],
]


class SiloConfig(Strict):
    id: str = Field(pattern=SAFE_ID, description="used in topics and scan ids")
    region: list[Point2] = Field(min_length=3, description="integration polygon, silo frame")
    floor_z: float = 0.0
    ceiling_z: float | None = None
    base: Literal["floor", "boundary"] = "floor"
    bulk_density_t_m3: float | None = Field(default=None, gt=0)
    timezone: str = Field(default="UTC", description="IANA zone of schedule.cron")

    @field_validator("timezone")
    @classmethod
    def _known_zone(cls, zone: str) -> str:
        from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

        try:
            ZoneInfo(zone)
        except (ZoneInfoNotFoundError, ValueError):
            raise ValueError(f"unknown time zone {zone!r} (want an IANA name)") from None
        return zone

    @field_validator("region")
    @classmethod
    def _region_is_simple(cls, region: list[Point2]) -> list[Point2]:
        problem = check_polygon(np.asarray(region, dtype=float))
        if problem:
            raise ValueError(problem)
        return region

    @model_validator(mode="after")
    def _ceiling_above_floor(self) -> SiloConfig:
        if self.ceiling_z is not None and self.ceiling_z <= self.floor_z:
            raise ValueError(f"ceiling_z ({self.ceiling_z}) must be above floor_z ({self.floor_z})")
        return self


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


class OnnxDetectionConfig(Strict):
    """A site's Ultralytics YOLO model exported to ONNX (paper 2.2); none ships with silo-agent."""

    model: Path = Field(description="the .onnx file of `yolo export format=onnx`")
    confidence: float = Field(default=0.5, gt=0, lt=1, description="paper 2.2 threshold")
    iou: float = Field(default=0.45, gt=0, le=1, description="NMS overlap that drops a box")
    pile_classes: list[str] = Field(default=["pile"], description="class names that are piles")
    robot_classes: list[str] = Field(
        default=["robot"], description="class names that are the leveling robot"
    )
    cluster_radius_m: float = Field(
        default=0.98, gt=0, description="paper 2.3.2 radius clustering around the box's point"
    )

    @model_validator(mode="after")
    def _disjoint_classes(self) -> OnnxDetectionConfig:
        both = sorted(set(self.pile_classes) & set(self.robot_classes))
        if both:
            raise ValueError(f"classes both pile and robot: {', '.join(both)}")
        return self


class DetectionConfig(Strict):
    """Pile detection: the geometric detector on the height map, and optionally a YOLO model."""

    geometric: bool = True
    min_height_m: float = Field(default=0.10, gt=0, description="a pile's peak above its base")
    min_area_m2: float = Field(default=0.10, gt=0, description="smaller footprints are dropped")
    min_prominence_m: float = Field(
        default=0.10, gt=0, description="a peak this far above its saddle is a pile of its own"
    )
    min_separation_m: float = Field(default=0.3, gt=0, description="closer peaks are one pile")
    background_m: float | None = Field(
        default=None,
        gt=0,
        description="piles on a local background (opening of this width) instead of the base",
    )
    match_distance_m: float = Field(
        default=0.5, gt=0, description="a pile this close to one of the last scan keeps its id"
    )
    onnx: OnnxDetectionConfig | None = None


class CameraConfig(Strict):
    serial: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    source: Literal["realsense", "playback", "sim"] = "realsense"
    playback: Path | None = None
    extrinsic: Matrix4 | None = None
    rotate_deg: tuple[float, float, float] | None = None
    translate_m: tuple[float, float, float] | None = None
    view: str | None = Field(default=None, description="sim only: a named layout position")
    width: int = 848
    height: int = 480
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
    min_depth_m: float = Field(default=0.3, ge=0, description="threshold filter: nearer is dropped")
    max_depth_m: float = Field(default=10.0, gt=0, description="threshold filter: farther dropped")
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
        if self.source != "sim" and not has_matrix and not has_euler:
            raise ValueError("needs extrinsic (4x4) or rotate_deg + translate_m")
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


class SimulationConfig(Strict):
    scene: str = "cone"
    sequence: list[str] = Field(
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
    seed: int = 0
    layout: Layout = DEFAULT_LAYOUT
    calib_error_deg: float = Field(default=0.0, ge=0)
    calib_error_m: float = Field(default=0.0, ge=0)


class MqttTlsConfig(Strict):
    """TLS to the broker; without `ca_file` the system trust store verifies the broker."""

    ca_file: Path | None = None
    cert_file: Path | None = Field(default=None, description="client certificate (PEM)")
    key_file: Path | None = Field(default=None, description="client private key (PEM)")
    key_password_file: Path | None = None
    key_password_env: str | None = None

    @model_validator(mode="after")
    def _pairs(self) -> MqttTlsConfig:
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("cert_file and key_file go together")
        if self.key_password_file is not None and self.key_password_env is not None:
            raise ValueError("give key_password_file or key_password_env, not both")
        return self


class SparkplugConfig(Strict):
    """Eclipse Sparkplug B 3.0 dialect, published next to the JSON topics."""

    enabled: bool = False
    group_id: str = Field(default="silos", pattern=r"^[^#+/]+$")
    edge_node_id: str | None = Field(
        default=None, pattern=r"^[^#+/]+$", description="default: silo.id"
    )
    primary_host_id: str | None = Field(
        default=None, pattern=r"^[^#+/]+$", description="wait for this host's STATE online"
    )


class HomeAssistantConfig(Strict):
    """Home Assistant MQTT discovery (device-based)."""

    enabled: bool = False
    discovery_prefix: str = Field(default="homeassistant", pattern=r"^[^#+]+$")


class MqttConfig(Strict):
    host: HostName = Field(default="127.0.0.1", description="broker name or address")
    port: int = Field(default=1883, ge=1, le=65535)
    topic_prefix: str = Field(default="silo", pattern=r"^[^#+]+$")
    protocol: Literal["5", "3.1.1"] = "5"
    client_id: str | None = Field(
        default=None, min_length=1, max_length=64, description="default: silo-agent-<silo.id>"
    )
    keepalive_s: int = Field(default=30, ge=5, le=65535)
    username: str | None = None
    password_file: Path | None = None
    password_env: str | None = None
    tls: MqttTlsConfig | None = None
    reconnect_min_s: float = Field(default=1.0, gt=0, le=MAX_DURATION_S)
    reconnect_max_s: float = Field(default=60.0, gt=0, le=MAX_DURATION_S)
    max_inflight: int = Field(default=20, ge=1, le=65535)
    outbox_path: Path = Path("/var/lib/silo-agent/outbox.sqlite")
    outbox_max_messages: int = Field(default=100_000, ge=10)
    outbox_max_bytes: int = Field(default=500_000_000, ge=100_000)
    outbox_max_age_days: float = Field(default=30.0, gt=0)
    shutdown_timeout_s: float = Field(default=5.0, ge=0, le=MAX_DURATION_S)
    sparkplug: SparkplugConfig = Field(default_factory=SparkplugConfig)
    homeassistant: HomeAssistantConfig = Field(default_factory=HomeAssistantConfig)

    @model_validator(mode="after")
    def _consistent(self) -> MqttConfig:
        if self.password_file is not None and self.password_env is not None:
            raise ValueError("give password_file or password_env, not both")
        if (self.password_file is not None or self.password_env is not None) and not self.username:
            raise ValueError("a password needs a username")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("reconnect_max_s must be >= reconnect_min_s")
        return self


class ScheduleConfig(Strict):
    interval_s: float | None = Field(default=None, gt=0, le=MAX_DURATION_S)
    cron: str | None = Field(default=None, description="crontab line, in silo.timezone")
    scan_at_start: bool = True
    misfire_grace_s: float = Field(
        default=300,
        gt=0,
        le=MAX_DURATION_S,
        description="a scan due this long ago (machine asleep) still runs",
    )
    scan_timeout_s: float = Field(
        default=600, gt=0, le=MAX_DURATION_S, description="overall deadline of one scan"
    )
    stop_timeout_s: float = Field(
        default=30,
        ge=0,
        le=MAX_DURATION_S,
        description="on SIGTERM, how long a running scan may finish",
    )

    @field_validator("cron")
    @classmethod
    def _valid_cron(cls, cron: str | None) -> str | None:
        if cron is None:
            return None
        from apscheduler.triggers.cron import CronTrigger

        try:
            CronTrigger.from_crontab(cron)
        except ValueError as exc:
            raise ValueError(f"not a crontab expression ({exc})") from None
        return cron


STALE_AFTER_GAPS = 2  # a reading goes stale when this many scheduled scans brought none
CRON_LOOKAHEAD_FIRES = 2000  # a week of a cron's fire times, at most, to find its longest gap


def scan_gap_s(schedule: ScheduleConfig, timezone: str) -> float | None:
    """Longest time between two scheduled scans (None: scans only at start or on request)."""
    from datetime import UTC, datetime, timedelta

    gaps = [schedule.interval_s] if schedule.interval_s is not None else []
    if schedule.cron is not None:
        from apscheduler.triggers.cron import CronTrigger

        trigger = CronTrigger.from_crontab(schedule.cron, timezone=timezone)
        fires: list[datetime] = []
        fire = trigger.get_next_fire_time(None, datetime.now(UTC))
        while fire is not None and len(fires) < CRON_LOOKAHEAD_FIRES:
            fires.append(fire)
            if fire - fires[0] > timedelta(days=8):
                break
            fire = trigger.get_next_fire_time(fire, fire)
        if len(fires) > 1:
            gaps.append(max((b - a).total_seconds() for a, b in pairwise(fires)))
    return min(gaps) if gaps else None


def stale_after_s(schedule: ScheduleConfig, timezone: str) -> int | None:
    """Seconds after which a published reading is stale (HA's `expire_after`): one scheduled
    scan may fail or be skipped, the next one, up to its deadline, must bring a new one."""
    gap = scan_gap_s(schedule, timezone)
    if gap is None:
        return None
    return int(np.ceil(STALE_AFTER_GAPS * gap + schedule.scan_timeout_s))


class AlarmsConfig(Strict):
    """Alarm thresholds (silo_agent/alarms.py); each alarm raises and clears with hysteresis."""

    enabled: bool = True
    collapse_depth_m: float = Field(default=0.10, gt=0, description="drop vs the baseline")
    collapse_min_area_m2: float = Field(default=0.25, gt=0, description="smallest collapse")
    collapse_noise_k: float = Field(
        default=5.0, gt=0, description="a drop must also exceed k x the maps' noise sigma"
    )
    baseline_scan_id: str | None = Field(
        default=None,
        pattern=r"^[A-Za-z0-9_.-]+$",
        description="pin the collapse baseline to this cached scan; default the last valid scan",
    )
    high_level_margin_m: float | None = Field(
        default=0.30, gt=0, description="level_high when the surface is this close to ceiling_z"
    )
    low_volume_m3: float | None = Field(default=None, ge=0, description="level_low below this")
    change_fraction: float | None = Field(
        default=0.20, gt=0, description="change: volume moved by more than this share in a scan"
    )
    min_coverage: float = Field(default=0.30, ge=0, le=1, description="coverage fault below")
    hysteresis: float = Field(
        default=0.5,
        gt=0,
        lt=1,
        description="an active alarm clears only when its measure falls below this share "
        "of the raise threshold (level: this share of the margin further away)",
    )


class MetricsConfig(Strict):
    """Prometheus exposition (prometheus-client); off by default."""

    enabled: bool = False
    host: HostName = Field(default="127.0.0.1", description="listen address")
    port: int = Field(default=9464, ge=1, le=65535)


class AuditConfig(Strict):
    directory: Path = Path("/var/lib/silo-agent/scans")
    max_bytes: int = Field(default=20_000_000_000, gt=0)
    max_age_days: float = Field(default=90, gt=0)


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
        default=6.0, gt=0, description="floor points farther from their camera are too noisy"
    )
    refine: bool = Field(
        default=False, description="every scan: bounded ICP on the overlaps before reconstructing"
    )
    refine_max_deg: float = Field(default=0.5, gt=0, description="per-scan refinement bound")
    refine_max_m: float = Field(default=0.02, gt=0, description="per-scan refinement bound")
    spacing: list[SpacingConfig] = Field(
        default=[], description="measured camera-to-camera distances calibrate holds to"
    )


class LiveConfig(Strict):
    """`[live]`: the live height map a leveling robot follows (`P/cmd/live`, `P/heightmap/live`)."""

    rate_hz: float = Field(default=2.0, gt=0, le=10, description="maps per second, at most")
    grid_step_m: float = Field(default=0.02, gt=0.005, le=0.5)
    cameras: list[str] | None = Field(
        default=None, description="serials of the cameras used; default all [[cameras]]"
    )
    duration_s: float = Field(default=600.0, gt=0, description="a session without duration_s")
    max_duration_s: float = Field(default=3600.0, gt=0, description="longest session allowed")
    decimation: int = Field(default=1, ge=1, le=8, description="depth pixels step per axis")
    smoothing: float = Field(
        default=0.3, gt=0, le=1, description="weight of the newest frame in a cell's running value"
    )
    reset_m: float = Field(
        default=0.07, gt=0, description="a confirmed frame this far from a cell's value replaces it"
    )
    change_m: float = Field(
        default=0.02, gt=0, description="a cell this far from its last reported value is changed"
    )
    stale_s: float = Field(
        default=3.0, gt=0, description="a cell not measured for this long is not `observed`"
    )
    robot_min_height_m: float = Field(
        default=0.15, gt=0, description="a robot stands at least this far above the local grain"
    )
    robot_radius_m: float = Field(
        default=0.4, gt=0, description="the robot's half diagonal: held around its centre"
    )
    robot_margin_m: float = Field(
        default=0.15, ge=0, description="kept out of the map around the robot's footprint"
    )
    model_rate_hz: float = Field(
        default=1.0,
        gt=0,
        le=10,
        description="runs per second, at most, of [detection.onnx]'s model on the colour frames",
    )
    qos: Literal[0, 1] = 0


class Config(Strict):
    silo: SiloConfig
    reconstruction: ReconstructionConfig = Field(default_factory=ReconstructionConfig)
    detection: DetectionConfig = Field(default_factory=DetectionConfig)
    cameras: Annotated[list[CameraConfig], Field(min_length=1)]
    simulation: SimulationConfig = Field(default_factory=SimulationConfig)
    mqtt: MqttConfig = Field(default_factory=MqttConfig)
    schedule: ScheduleConfig = Field(default_factory=ScheduleConfig)
    audit: AuditConfig = Field(default_factory=AuditConfig)
    alarms: AlarmsConfig = Field(default_factory=AlarmsConfig)
    metrics: MetricsConfig = Field(default_factory=MetricsConfig)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    live: LiveConfig = Field(default_factory=LiveConfig)

    @model_validator(mode="after")
    def _grid_fits(self) -> Config:
        rows, cols = grid_shape(np.asarray(self.silo.region), self.reconstruction.grid_step_m)
        cells = rows * cols
        if cells > MAX_GRID_CELLS:
            raise PydanticCustomError(
                "config_key",
                "the region at this step is {cells} cells, more than the limit of {limit}; "
                "use a coarser grid_step_m",
                {
                    "key": "reconstruction.grid_step_m",
                    "cells": f"{cells:,}",
                    "limit": f"{MAX_GRID_CELLS:,}",
                },
            )
        return self

    @model_validator(mode="after")
    def _unique_serials(self) -> Config:
        serials = [c.serial for c in self.cameras]
        dupes = sorted({s for s in serials if serials.count(s) > 1})
        if dupes:
            raise ValueError(f"camera serials must be unique, repeated: {', '.join(dupes)}")
        known = set(serials)
        for k, spacing in enumerate(self.calibration.spacing):
            for key in ("a", "b"):
                serial = getattr(spacing, key)
                if serial not in known:
                    raise PydanticCustomError(
                        "config_key",
                        "unknown camera serial '{serial}', expected the serial of one of the "
                        "[[cameras]] ({known})",
                        {
                            "key": f"calibration.spacing.{k}.{key}",
                            "serial": serial,
                            "known": ", ".join(serials),
                        },
                    )
        for k, serial in enumerate(self.live.cameras or []):
            if serial not in known:
                raise PydanticCustomError(
                    "config_key",
                    "unknown camera serial '{serial}', expected the serial of one of the "
                    "[[cameras]] ({known})",
                    {"key": f"live.cameras.{k}", "serial": serial, "known": ", ".join(serials)},
                )
        return self


def describe_validation_error(exc: ValidationError, source: str) -> str:
    """One line per problem: `source: key.path: what was expected`."""
    lines = []
    for error in exc.errors():
        path = ".".join(str(p) for p in error["loc"]) or "(top level)"
        if error["type"] == "config_key":  # a cross-check raised at the top, naming its key
            path = error["ctx"]["key"]
        message = error["msg"].removeprefix("Value error, ")
        if error["type"] == "extra_forbidden":
            message = "unknown key"
        elif error["type"] == "missing":
            message = "required key is missing"
        lines.append(f"{source}: {path}: {message}")
    return "\n".join(lines)


def _toml_value(value: object) -> object:
    """A TOML date or time in the JSON handed to the strict validator: an object, which no
    key of the config accepts, so the error names the key."""
    return {"toml date/time": str(value)}


def parse_config(data: dict, source: str) -> Config:
    """Validate a parsed TOML document, strictly (no `true` or `"30"` for a number); `source`
    names it in errors. Validated as JSON, where strict mode still takes a string for a path
    and an array for a tuple, as TOML writes them."""
    try:
        document = json.dumps(data, default=_toml_value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{source}: {exc}") from None
    try:
        return Config.model_validate_json(document, strict=True)
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, source)) from None


def _writable_directory_problem(directory: Path) -> str | None:
    """Why the agent could not create and write `directory`, or None. The nearest existing
    ancestor must be a directory the agent can create entries in (tried, and undone)."""
    existing = directory
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a directory"
    try:
        tempfile.TemporaryDirectory(prefix=".silo-agent-check.", dir=existing).cleanup()
    except OSError as exc:
        return f"cannot create files in {existing}: {exc.strerror or exc}"
    return None


def _readable_file_problem(path: Path) -> str | None:
    if not path.exists():
        return f"{path} does not exist"
    if not path.is_file():  # checked before opening: a FIFO would block the open
        return f"{path} is not a regular file"
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    return None


def environment_problems(config: Config) -> list[str]:
    """`key: problem` for what the config points at and the agent could not use: directories
    it writes, files it reads. Checked at start and by check-config, not on every parse."""
    problems = []
    for key, directory in (
        ("audit.directory", config.audit.directory),
        ("mqtt.outbox_path", config.mqtt.outbox_path.parent),
    ):
        problem = _writable_directory_problem(Path(directory))
        if problem:
            problems.append(f"{key}: {problem}")
    outbox = config.mqtt.outbox_path
    if outbox.exists() and not outbox.is_file():
        problems.append(f"mqtt.outbox_path: {outbox} exists and is not a regular file")
    files = {"mqtt.password_file": config.mqtt.password_file}
    if config.mqtt.tls is not None:
        tls = config.mqtt.tls
        files.update(
            {
                "mqtt.tls.ca_file": tls.ca_file,
                "mqtt.tls.cert_file": tls.cert_file,
                "mqtt.tls.key_file": tls.key_file,
                "mqtt.tls.key_password_file": tls.key_password_file,
            }
        )
    for key, path in files.items():
        problem = _readable_file_problem(path) if path is not None else None
        if problem:
            problems.append(f"{key}: {problem}")
    return problems


def config_warnings(config: Config) -> list[str]:
    """Settings that are valid but probably not meant: a cron line that never fires."""
    warnings = []
    if config.schedule.cron is not None:
        from datetime import UTC, datetime

        from apscheduler.triggers.cron import CronTrigger

        trigger = CronTrigger.from_crontab(config.schedule.cron, timezone=config.silo.timezone)
        if trigger.get_next_fire_time(None, datetime.now(UTC)) is None:
            warnings.append(
                f"schedule.cron: {config.schedule.cron!r} never fires "
                "(no such date); only scan_at_start, interval_s and requests scan"
            )
    return warnings


def load_config(path: str | Path, *, service: bool = False) -> Config:
    """Read and validate a TOML config file. `service`: also what the daemon will write and
    read (`environment_problems`), for `run`, its reloads and `check-config`; offline commands
    such as `process --config` need none of it."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at offset "
            f"{exc.start} ({exc.reason})"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    config = parse_config(data, str(path))
    problems = environment_problems(config) if service else []
    if problems:
        raise ConfigError("\n".join(f"{path}: {problem}" for problem in problems))
    return config
