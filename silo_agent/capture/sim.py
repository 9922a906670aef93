"""`source = "sim"` cameras: the simulator behind the same `Camera` protocol as a live D455,
so the daemon runs end to end on a laptop (config/demo.toml).

The cloud carries the configured (nominal) extrinsic; `[simulation] calib_error_*` moves the
pose the scene is really rendered from, as a badly calibrated camera would. A camera with both
a `view` and an extrinsic really hangs at its view (plus the error) whatever the extrinsic
says, so a calibrated config (`silo-agent calibrate --write`) converges on it.
"""

from __future__ import annotations

import time
from dataclasses import replace
from functools import lru_cache

from silo_agent.capture import CaptureError
from silo_agent.config import CameraConfig, Config
from silo_agent.scan import CameraCloud
from silo_agent.sim.layouts import view_pose
from silo_agent.sim.scenes import make_scene
from silo_agent.sim.simulate import SimRig, plan_view


@lru_cache(maxsize=4)
def _rig(scene: str, grain: str) -> SimRig:
    """One world per scene for all cameras and all scans: building it is the costly part."""
    return SimRig(make_scene(scene, grain))


class SimCamera:
    """A virtual D455 of `[simulation]`, placed by its `view` or its configured extrinsic."""

    def __init__(self, camera: CameraConfig, config: Config, scan_number: int = 0) -> None:
        self.serial = camera.serial
        sim = config.simulation
        scene = sim.scene
        if sim.sequence:  # a scene that changes scan by scan; the last one stays
            scene = sim.sequence[min(scan_number, len(sim.sequence) - 1)]
        try:
            rig = _rig(scene, sim.grain)
            nominal = camera.extrinsic_matrix()
            if nominal is None:
                if camera.view is None:
                    raise ValueError("a sim camera needs view = 'A1'..'A8' or an extrinsic")
                # cameras stay put while the scene changes: placed for the sequence's first
                placed = _rig(sim.sequence[0], sim.grain) if sim.sequence else rig
                nominal = view_pose(placed.scene, camera.view, sim.layout)
        except ValueError as exc:
            raise CaptureError(f"camera {camera.serial}: {exc}") from None
        self._rig = rig
        self._seed = sim.seed + (scan_number if sim.vary_noise else 0)
        self._color = camera.color
        self._capture_s = sim.capture_s
        # the pose error stays: it is the camera's, not the scan's
        error = (sim.calib_error_deg, sim.calib_error_m)
        key = camera.view or camera.serial
        self._view = plan_view(
            key, camera.serial, nominal, sim.seed, error, camera.width, camera.height
        )
        if camera.view is not None and camera.extrinsic_matrix() is not None:
            # the camera hangs at its view (off by calib_error); the configured extrinsic is
            # only what the config believes, e.g. after `silo-agent calibrate --write`
            placed = _rig(sim.sequence[0], sim.grain) if sim.sequence else rig
            mounted = plan_view(
                key,
                camera.serial,
                view_pose(placed.scene, camera.view, sim.layout),
                sim.seed,
                error,
                camera.width,
                camera.height,
            )
            self._view = replace(self._view, true=mounted.true)

    def capture(self) -> CameraCloud:
        if self._capture_s:  # as long as a real camera's warm-up and frames
            time.sleep(self._capture_s)
        return self._rig.cloud(self._view, self._seed, self._color)

    def close(self) -> None:
        """Nothing to release: the rendered world is shared and cached."""
