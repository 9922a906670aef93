"""The raking-robot rig as the tests render it."""

from __future__ import annotations

from typing import Any

from silo_agent.sim.robot import RobotRig

# The moving world's mesh step. At 0.02 m the live map's errors on the raking scene are the same
# to 0.01 mm as at the simulator's 0.01 m default (21 maps, 848x480), and each frame's ray-casting
# scene has a quarter of the triangles: the live tests' renders take 30 % less CPU.
MESH_STEP_M = 0.02


def robot_rig(**kwargs: Any) -> RobotRig:
    return RobotRig(mesh_step=MESH_STEP_M, **kwargs)
