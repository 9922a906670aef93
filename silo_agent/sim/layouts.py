"""Camera positions: the paper's A1-A8, a wall-mounted layout and a round bin's eave cameras
(A1-A8 at the same eight bearings, just under the eave, looking down and inward past the
centre); calibration-error injection.

A1-A8 go counter-clockwise around a square seen from above, A1 at the middle of the -y side
(then A3 at +x, A5 at +y, A7 at -x; the even ones are corners). This reproduces the relative
positions of the paper's Appendix A (A3 to the right of A1 and 2.6 m ahead, A5 opposite).
"""

from __future__ import annotations

import numpy as np

from silo_agent.base.choices import LAYOUTS, VIEW_NAMES, layout_misfit
from silo_agent.sim.scenes import Scene

VIEWS: dict[str, tuple[int, int]] = dict(
    zip(
        VIEW_NAMES,
        [
            (0, -1),
            (1, -1),
            (1, 0),
            (1, 1),
            (0, 1),
            (-1, 1),
            (-1, 0),
            (-1, -1),
        ],
        strict=True,
    )
)
PAPER_SQUARE_M = 5.0
PAPER_CAMERA_Z = 1.0
WALL_INSET_M = 0.05  # a wall camera's lens in front of the wall
EAVE_INSET_M = 0.3  # an eave camera's lens inside a round bin's wall
EAVE_AIM = 0.2  # eave cameras aim this fraction of the radius past the centre


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera -> silo transform of a level camera (no roll) at `position` aimed at `target`.

    Optical frame: +z towards the target, +x to the right, +y down.
    """
    forward = np.asarray(target, float) - np.asarray(position, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = position
    return pose


def view_pose(scene: Scene, view: str, layout: str | None = None) -> np.ndarray:
    """Nominal camera -> silo transform of a named view (`layout` defaults to the scene's).

    A layout that `base.choices.SCENE_LAYOUTS` does not list for the scene is refused, as the
    config check refuses it from the same table; the message adds the geometry's reason.
    """
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r}; known: {', '.join(VIEWS)}")
    layout = layout or scene.layout
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; known: {', '.join(LAYOUTS)}")
    misfit = layout_misfit(scene.name, layout)
    try:
        position, target = placement(scene, view, layout)
    except ValueError as exc:
        misfit = misfit or f"layout {layout!r} does not fit scene {scene.name!r}"
        raise ValueError(f"{misfit}: {exc}") from None
    if misfit is not None:  # the table rules, for the config check to say the same
        raise ValueError(misfit)
    return look_at(position, target)


def placement(scene: Scene, view: str, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """Where the geometry alone, without the table, puts a view's camera: its position and aim
    point, or a ValueError saying why there is no place for it (tests check the table by it).
    `layout` is one of LAYOUTS (`view_pose` checks)."""
    offset = np.asarray(VIEWS[view], dtype=float)
    target = np.asarray(scene.target, dtype=float)
    if layout == "paper":
        xy = target[:2] + offset * PAPER_SQUARE_M / 2
        z = scene.site.floor_z + PAPER_CAMERA_Z
    elif layout == "wall":
        xy = offset * (scene.wall_half_m - WALL_INSET_M)
        z = scene.wall_camera_z
    else:  # eave
        if scene.bin is None:
            raise ValueError("the eave layout needs a round bin")
        centre, radius = np.asarray(scene.bin.centre), scene.bin.radius_m
        direction = offset / np.linalg.norm(offset)
        xy = centre + direction * (radius - EAVE_INSET_M)
        z = scene.wall_camera_z
        target = np.append(centre - direction * EAVE_AIM * radius, target[2])
    surface = float(scene.height(np.array(xy[0]), np.array(xy[1])))
    if z <= surface + 0.1:
        raise ValueError(
            f"view {view} would be buried in the grain (camera {z:.2f} m high, the grain "
            f"{surface:.2f} m there)"
        )
    return np.array([xy[0], xy[1], z]), target


def axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues rotation matrix."""
    axis = axis / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * cross + (1 - np.cos(angle_rad)) * cross @ cross


def perturb(
    pose: np.ndarray, degrees: float, metres: float, rng: np.random.Generator
) -> np.ndarray:
    """The camera's true pose when its calibration is off by exactly `degrees` (about a random
    axis through the camera) and `metres` (in a random direction)."""
    axis, direction = rng.standard_normal(3), rng.standard_normal(3)
    true = pose.copy()
    true[:3, :3] = axis_angle(axis, np.radians(degrees)) @ pose[:3, :3]
    true[:3, 3] += metres * direction / np.linalg.norm(direction)
    return true
