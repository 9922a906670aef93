"""Render a scene from named views into a `Scan` carrying the scene's truth.

Every random draw comes from a stream keyed by (seed, view, purpose), so a view renders the
same whichever other views are asked for, and a seed always gives the same scan.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np

from silo_agent.grid.geometry import gravity_angle_deg
from silo_agent.scan import CameraCloud, Scan, measured_only
from silo_agent.sim.camera import Frame, Intrinsics, NoiseModel, d455_intrinsics, expose, trace
from silo_agent.sim.layouts import perturb, view_pose
from silo_agent.sim.mesh import build_world
from silo_agent.sim.raycast import Raycaster
from silo_agent.sim.scenes import Scene, make_scene

FOCAL_RANGE_PX = (430.0, 450.0)  # D455 depth focal length at 848x480 varies unit to unit
_CALIBRATION, _FOCAL, _NOISE = 0, 1, 2  # random streams


def rng_for(seed: int, key: str, stream: int, index: int = 0) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(key.encode()), stream, index])


def serial_for(view: str) -> str:
    return f"sim-{view}"


def focal_for(seed: int, key: str) -> float:
    """This simulated unit's focal length (px at 848 wide)."""
    return float(rng_for(seed, key, _FOCAL).uniform(*FOCAL_RANGE_PX))


GRAVITY_M_S2 = 9.80665


def gravity_reading(view: SimView) -> dict[str, object]:
    """The IMU keys a live D455 adds to its cloud (capture/realsense.py): gravity, pointing
    down, in depth-camera axes of the camera's true pose (an ideal accelerometer), and its angle
    to the vertical the nominal extrinsic implies."""
    gravity = GRAVITY_M_S2 * view.true[:3, :3].T @ np.array([0.0, 0.0, -1.0])
    return {
        "gravity": [float(g) for g in gravity],
        "gravity_samples": 1,
        "gravity_angle_deg": gravity_angle_deg(gravity, view.nominal),
    }


@dataclass(frozen=True)
class SimView:
    """One simulated camera: where it is said to be, and where it really is."""

    key: str  # view name, or serial for a camera placed by an explicit extrinsic
    serial: str
    nominal: np.ndarray  # 4x4 camera -> silo, what the manifest / config says
    true: np.ndarray  # 4x4 camera -> silo used for rendering
    intrinsics: Intrinsics


def plan_view(
    key: str,
    serial: str,
    nominal: np.ndarray,
    seed: int,
    calib_error: tuple[float, float],
    width: int = 848,
    height: int = 480,
) -> SimView:
    true = perturb(nominal, calib_error[0], calib_error[1], rng_for(seed, key, _CALIBRATION))
    return SimView(key, serial, nominal, true, d455_intrinsics(focal_for(seed, key), width, height))


class SimRig:
    """A scene's world, built once (the costly part), rendered from any camera."""

    def __init__(
        self, scene: Scene, mesh_step: float | None = None, noise: NoiseModel | None = None
    ) -> None:
        """`mesh_step` and `noise` default to the scene's (its height-field step; the D455
        model at the scene's surface factor and depth range)."""
        self.scene = scene
        self.noise = noise or NoiseModel(
            surface_factor=scene.surface_factor, max_depth_m=scene.max_depth_m
        )
        self.raycaster = Raycaster(build_world(scene, mesh_step))

    def frames(self, view: SimView, seed: int, count: int = 1, color: bool = False) -> list[Frame]:
        """`count` successive frames of a camera: one trace, independent noise per frame."""
        seen = trace(
            self.raycaster, view.true, view.intrinsics, self.scene.grain.rgb if color else None
        )
        return [expose(seen, self.noise, rng_for(seed, view.key, _NOISE, i)) for i in range(count)]

    def cloud(self, view: SimView, seed: int, color: bool = False) -> CameraCloud:
        points, colors = self.frames(view, seed, color=color)[0].points()
        cloud = CameraCloud(
            serial=view.serial,
            points=points,
            extrinsic=view.nominal,
            intrinsics=view.intrinsics.to_json(),
            colors=colors,
            extra={
                "sim_view": view.key,
                "sim_true_extrinsic": view.true.tolist(),
                "depth_range_m": [self.noise.min_depth_m, self.noise.max_depth_m],
                **gravity_reading(view),
            },
        )
        return measured_only(cloud)  # as a reader of the scan will see it


def plan_views(
    scene: Scene,
    views: Sequence[str],
    seed: int,
    calib_error: tuple[float, float] = (0.0, 0.0),
    layout: str | None = None,
    resolution: tuple[int, int] = (848, 480),
) -> list[SimView]:
    width, height = resolution
    return [
        plan_view(v, serial_for(v), view_pose(scene, v, layout), seed, calib_error, width, height)
        for v in views
    ]


def simulate(
    scene: Scene | str,
    views: Sequence[str],
    seed: int = 0,
    calib_error: tuple[float, float] = (0.0, 0.0),
    grid_step: float = 0.02,
    *,
    layout: str | None = None,
    color: bool = False,
    rig: SimRig | None = None,
    captured_at: datetime | None = None,
    resolution: tuple[int, int] = (848, 480),
) -> Scan:
    """A silo-scan of `scene` from `views`, with `extra["truth"]` the scene's exact volume;
    `resolution` is the depth image's (width, height): 848x480 or the D455's full 1280x720."""
    if isinstance(scene, str):
        scene = make_scene(scene)
    if not views:
        raise ValueError("simulate needs at least one view")
    if rig is None:
        rig = SimRig(scene)
    elif rig.scene is not scene:
        raise ValueError(f"the rig renders scene {rig.scene.name!r}, not {scene.name!r}")
    planned = plan_views(scene, views, seed, calib_error, layout, resolution)
    when = (captured_at or datetime.now(UTC)).strftime("%Y-%m-%dT%H:%M:%SZ")
    truth = scene.truth() | {
        "seed": seed,
        "views": list(views),
        "layout": layout or scene.layout,
        "calib_error": {"deg": calib_error[0], "m": calib_error[1]},
    }
    return Scan(
        scan_id=f"sim-{scene.name}-{'-'.join(views)}-s{seed}",
        captured_at=when,
        silo_id="sim",
        site=scene.site,
        cameras=[rig.cloud(v, seed, color) for v in planned],
        reconstruction={"grid_step_m": grid_step},
        extra={"truth": truth},
    )
