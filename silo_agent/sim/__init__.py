"""A virtual silo: scene library with exact volumes, a virtual D455, camera layouts.

Pure numpy; open3d is used by `raycast` alone (the ray casting behind `SimRig`).
"""

from silo_agent.sim.grains import GRAINS, Grain
from silo_agent.sim.layouts import LAYOUTS, VIEWS, view_pose
from silo_agent.sim.scenes import SCENES, Scene, make_scene
from silo_agent.sim.simulate import SimRig, simulate

__all__ = [
    "GRAINS",
    "LAYOUTS",
    "SCENES",
    "VIEWS",
    "Grain",
    "Scene",
    "SimRig",
    "make_scene",
    "simulate",
    "view_pose",
]
