"""A moving scene: a leveling robot drives a straight path across a walled bay (or a bin,
`in_bin`) and rakes it.

The robot is a box (0.6 x 0.4 x 0.3 m) dragging a 1 m wide rake at its rear edge: behind the
rake the grain is cut down to `rake_z` across the rake's width and slumps at its angle of
repose beside the cut; under and ahead of the robot it is untouched. Position, heading and the
raked surface are closed-form functions of time, so a test knows the exact surface and the
robot's footprint at the instant a frame is rendered, and the changed cells are exactly those
the rake cut.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from silo_agent.scan import Site
from silo_agent.sim.camera import Frame, NoiseModel, expose, trace
from silo_agent.sim.grains import Grain, grain
from silo_agent.sim.layouts import view_pose
from silo_agent.sim.mesh import CLUTTER, Mesh, World, build_world
from silo_agent.sim.raycast import Raycaster
from silo_agent.sim.scenes import (
    BAY_CAMERA_Z,
    BAY_CEILING_Z,
    BAY_WALL_TOP,
    HeightField,
    Scene,
    cone_height,
    square,
)
from silo_agent.sim.simulate import SimView, plan_view, rng_for, serial_for

ROBOT_SIZE_M = (0.6, 0.4, 0.3)  # length (along the path), width, height
RAKE_WIDTH_M = 1.0  # the rake it drags reaches out beside it
LEVEL_M = 0.8  # flat grain in the bay
MOUNDS = (((-1.0, -0.55), 0.9), ((0.9, 0.6), 0.8))  # centre, radius: spout heaps to level
PATH = ((-2.4, -1.5), (2.4, 1.5))  # the robot drives a -> b
SPEED_M_S = 0.3
REGION_HALF_M = 3.0  # the live map's 6 x 6 m
WALL_MARGIN_M = 0.5  # between the region and the walls
RAKE_CLEARANCE_M = 0.02  # the blade leaves this much above the flat level
MIXED_EDGE_SHARE = 0.5  # of the pixels along the robot's rim, reading between it and the grain
_NOISE_STREAM = 7  # random stream of the moving scene's frames (simulate.rng_for)


def mounded_bay(g: Grain) -> Scene:
    """A walled bay at LEVEL_M with two heaps at the angle of repose, what a leveling robot is
    sent in to flatten; the 6 x 6 m region stops WALL_MARGIN_M short of the walls (scenes.py:
    depth noise scatters wall points into the bay, 0.3 m there with a smaller region)."""
    half = REGION_HALF_M + WALL_MARGIN_M

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        heaps = np.max(np.stack([cone_height(x, y, c, r, g.slope) for c, r in MOUNDS]), axis=0)
        inside = (np.abs(x) <= half + 1e-9) & (np.abs(y) <= half + 1e-9)
        return np.where(inside, LEVEL_M + heaps, BAY_WALL_TOP)

    site = Site(
        region=square(REGION_HALF_M),
        floor_z=0.0,
        ceiling_z=BAY_CEILING_Z,
        bulk_density_t_m3=g.density_t_m3,
    )
    edge = half + 0.1
    return Scene(
        name="mounded-bay",
        grain=g,
        site=site,
        height=height,
        extent=(-edge, edge, -edge, edge),
        outer_z=None,
        volume_m3=float("nan"),
        target=(0.0, 0.0, LEVEL_M),
        layout="wall",
        wall_half_m=half,
        wall_camera_z=BAY_CAMERA_Z,
        params={"level": LEVEL_M, "mounds": MOUNDS},
    )


def in_bin(scene: Scene) -> RakingRobot:
    """The robot raking `scene`, a bin (scenes.bin_scene), along PATH across its centre: its
    heap cut down to the grain's level by the wall (`level_m`, not the lowest grain: a
    crater's or a side draw's bottom would have it dig a trench metres deep in one pass),
    seen by the bin's eave cameras."""
    return RakingRobot(scene, rake_z=float(scene.params["level"]) + RAKE_CLEARANCE_M)


@dataclass(frozen=True)
class RobotPose:
    x: float
    y: float
    z: float  # the box's bottom
    heading: float  # radians from +x

    def footprint(self, x: np.ndarray, y: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True where (x, y) lies under the robot, grown by `margin`."""
        c, s = np.cos(self.heading), np.sin(self.heading)
        along = (x - self.x) * c + (y - self.y) * s
        across = -(x - self.x) * s + (y - self.y) * c
        length, width, _ = ROBOT_SIZE_M
        return (np.abs(along) <= length / 2 + margin) & (np.abs(across) <= width / 2 + margin)


@dataclass(frozen=True)
class RakingRobot:
    """The robot's drive over `base` (the walled bay, or a bin: `in_bin`): everything a
    function of time."""

    base: Scene
    path: tuple[tuple[float, float], tuple[float, float]] = PATH
    speed_m_s: float = SPEED_M_S
    rake_z: float = LEVEL_M + RAKE_CLEARANCE_M

    @cached_property
    def _direction(self) -> tuple[np.ndarray, float]:
        a, b = np.asarray(self.path[0]), np.asarray(self.path[1])
        length = float(np.linalg.norm(b - a))
        return (b - a) / length, length

    def travelled(self, t: float) -> float:
        """Distance of the robot's centre from the path's start at time t (stops at its end)."""
        return float(np.clip(self.speed_m_s * t, 0.0, self._direction[1]))

    def rake(self, t: float) -> tuple[float, float]:
        """Where the rear edge (the rake) is at time t."""
        unit, _ = self._direction
        reach = max(0.0, self.travelled(t) - ROBOT_SIZE_M[0] / 2)
        return tuple(np.asarray(self.path[0]) + unit * reach)

    def height(self, t: float) -> HeightField:
        """The grain surface at time t: the base, cut down to rake_z behind the rake, slumping
        at the angle of repose beside the cut; nothing changes ahead of the rake (under the
        robot), so the last surface seen before the robot covered a cell is still the truth."""
        unit, _ = self._direction
        ax, ay = self.path[0]
        reach = float(np.hypot(*(np.asarray(self.rake(t)) - self.path[0])))
        half = RAKE_WIDTH_M / 2
        original, slope = self.base.height, self.base.grain.slope
        if reach == 0.0:
            return original

        def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            along = (x - ax) * unit[0] + (y - ay) * unit[1]
            across = -(x - ax) * unit[1] + (y - ay) * unit[0]
            gap = np.where(along < 0.0, np.hypot(along, across), np.abs(across))
            beyond = np.maximum(gap - half, 0.0)
            cut = np.minimum(original(x, y), self.rake_z + slope * beyond)
            return np.where(along <= reach, cut, original(x, y))

        return surface

    def pose(self, t: float) -> RobotPose:
        unit, _ = self._direction
        centre = np.asarray(self.path[0]) + unit * self.travelled(t)
        ground = float(self.height(t)(centre[:1], centre[1:])[0])
        return RobotPose(
            float(centre[0]), float(centre[1]), ground, float(np.arctan2(unit[1], unit[0]))
        )

    def world(self, t: float, mesh_step: float = 0.01) -> World:
        """The grain at time t, a bin's wall and roof if the base is a bin, and the robot."""
        snapshot = replace(self.base, height=self.height(t))
        return World((*build_world(snapshot, mesh_step).meshes, robot_mesh(self.pose(t))))


def robot_mesh(pose: RobotPose) -> Mesh:
    """The robot's box, turned to its heading, standing on its ground height."""
    length, width, height = ROBOT_SIZE_M
    local = np.array(
        [
            [sx * length / 2, sy * width / 2, sz * height]
            for sz in (0, 1)
            for sy in (-1, 1)
            for sx in (-1, 1)
        ]
    )
    c, s = np.cos(pose.heading), np.sin(pose.heading)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    vertices = local @ rotation.T + [pose.x, pose.y, pose.z]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = np.array(
        [t for a, b, c_, d in faces for t in ((a, b, c_), (a, c_, d))], dtype=np.uint32
    )
    return Mesh(vertices.astype(np.float32), triangles, CLUTTER)


class RobotRig:
    """Renders the moving scene from its cameras (a bay's wall cameras, a bin's eave ones): one
    noisy depth frame per camera per instant, with the scene's D455 noise and depth range."""

    def __init__(
        self,
        robot: RakingRobot | None = None,
        views: tuple[str, ...] = ("A2", "A4", "A6", "A8"),
        seed: int = 0,
        width: int = 848,
        height: int = 480,
        noise: NoiseModel | None = None,
        mesh_step: float = 0.01,
    ) -> None:
        """`mesh_step` 0.01 m keeps the rendered surface within a millimetre of the truth;
        coarser builds the moving world faster (the daemon's demo, not the accuracy tests)."""
        self.robot = robot or RakingRobot(mounded_bay(grain("wheat")))
        self.noise = noise or NoiseModel(
            mixed_edge_share=MIXED_EDGE_SHARE,
            surface_factor=self.robot.base.surface_factor,
            max_depth_m=self.robot.base.max_depth_m,
        )
        self.seed = seed
        self.mesh_step = mesh_step
        self.views: list[SimView] = [
            plan_view(
                v,
                serial_for(v),
                view_pose(self.robot.base, v),
                seed,
                (0.0, 0.0),
                width,
                height,
            )
            for v in views
        ]

    def frames(self, t: float, index: int = 0, color: bool = False) -> list[Frame]:
        """Every camera's frame at time t (`index` numbers the frame for its noise draw), with
        the colour image aligned to depth when `color` (the grain's, the robot grey)."""
        raycaster = Raycaster(self.robot.world(t, self.mesh_step))
        rgb = self.robot.base.grain.rgb if color else None
        return [
            expose(
                trace(raycaster, v.true, v.intrinsics, rgb),
                self.noise,
                rng_for(self.seed, v.key, _NOISE_STREAM, index),
            )
            for v in self.views
        ]
