"""Simulated scans for the calibration tests: cameras whose true pose differs from their
extrinsic by a known amount, rendered by the simulator (no mocks)."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from silo_agent.scan import Scan
from silo_agent.sim import make_scene
from silo_agent.sim.layouts import axis_angle, view_pose
from silo_agent.sim.simulate import SimRig, SimView, d455_intrinsics, focal_for, serial_for


@lru_cache(maxsize=2)
def rig(scene: str = "cone") -> SimRig:
    return SimRig(make_scene(scene))


def knocked(
    nominal: np.ndarray, degrees: float, axis_in_camera: tuple[float, float, float]
) -> np.ndarray:
    """`nominal` turned by `degrees` about an axis through the camera (camera-frame axis)."""
    true = nominal.copy()
    axis = nominal[:3, :3] @ np.asarray(axis_in_camera, dtype=float)
    true[:3, :3] = axis_angle(axis, np.radians(degrees)) @ nominal[:3, :3]
    return true


def _sim_views(
    r: SimRig, views: list[str], seed: int, true_poses: dict[str, np.ndarray] | None
) -> list[SimView]:
    """The simulator's cameras at their nominal extrinsics, really sitting at `true_poses`."""
    out = []
    for view in views:
        nominal = view_pose(r.scene, view)
        true = (true_poses or {}).get(view, nominal)
        out.append(
            SimView(view, serial_for(view), nominal, true, d455_intrinsics(focal_for(seed, view)))
        )
    return out


def render(
    views: list[str],
    seed: int,
    true_poses: dict[str, np.ndarray] | None = None,
    scene: str = "cone",
) -> Scan:
    """A scan of `views` whose cameras really sit at `true_poses` (default: their nominal)."""
    r = rig(scene)
    cameras = [r.cloud(v, seed) for v in _sim_views(r, views, seed, true_poses)]
    return Scan(
        scan_id=f"calib-{seed}",
        captured_at="2026-11-22T10:00:00Z",
        silo_id="sim",
        site=r.scene.site,
        cameras=cameras,
        reconstruction={"grid_step_m": 0.02},
    )


def render_repeats(
    views: list[str],
    seed: int,
    count: int,
    true_poses: dict[str, np.ndarray] | None = None,
    scene: str = "cone",
) -> list[Scan]:
    """`count` scans of the same cameras taken one after another: the same (possibly wrong)
    poses and units, independent sensor noise in each (the simulator's successive frames)."""
    r = rig(scene)
    per_view = []
    for sim_view in _sim_views(r, views, seed, true_poses):
        template = r.cloud(sim_view, seed)
        frames = r.frames(sim_view, seed, count)
        per_view.append([replace(template, points=f.points()[0]) for f in frames])
    return [
        Scan(
            scan_id=f"calib-{seed}-{k}",
            captured_at="2026-11-22T10:00:00Z",
            silo_id="sim",
            site=r.scene.site,
            cameras=[clouds[k] for clouds in per_view],
            reconstruction={"grid_step_m": 0.02},
        )
        for k in range(count)
    ]
