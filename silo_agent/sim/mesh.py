"""Triangle meshes of a scene (pure numpy): the height field, the open floor around it, clutter.

The height-field mesh takes the surface's values at its vertices, so with a 1 cm step its
volume differs from the analytic truth by far less than the camera noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from silo_agent.grid.bin_shape import BinShape
from silo_agent.sim.scenes import Box, Scene

GRAIN, CLUTTER = 0, 1  # material of a mesh: shading colour of the colour image


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # (V, 3) float32
    triangles: np.ndarray  # (T, 3) uint32
    material: int


@dataclass(frozen=True)
class World:
    """Everything a camera can see."""

    meshes: tuple[Mesh, ...]


def grid_triangles(rows: int, cols: int) -> np.ndarray:
    """Two triangles per cell of a rows x cols vertex grid (row-major vertex ids)."""
    idx = np.arange(rows * cols, dtype=np.uint32).reshape(rows, cols)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def height_field_mesh(scene: Scene, step: float) -> Mesh:
    xmin, xmax, ymin, ymax = scene.extent
    cols = round((xmax - xmin) / step) + 1
    rows = round((ymax - ymin) / step) + 1
    gx, gy = np.meshgrid(np.linspace(xmin, xmax, cols), np.linspace(ymin, ymax, rows))
    vertices = np.stack([gx, gy, scene.height(gx, gy)], axis=-1).reshape(-1, 3)
    return Mesh(vertices.astype(np.float32), grid_triangles(rows, cols), GRAIN)


def ring_mesh(extent: tuple[float, float, float, float], z: float, reach: float) -> Mesh:
    """Flat floor from the height field's rectangle out to `reach` metres beyond it."""
    xmin, xmax, ymin, ymax = extent
    inner = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    outer = inner + np.array([[-reach, -reach], [reach, -reach], [reach, reach], [-reach, reach]])
    xy = np.concatenate([inner, outer])
    vertices = np.column_stack([xy, np.full(8, z)]).astype(np.float32)
    triangles = np.array(
        [[i, (i + 1) % 4, 4 + (i + 1) % 4] for i in range(4)]
        + [[i, 4 + (i + 1) % 4, 4 + i] for i in range(4)],
        dtype=np.uint32,
    )
    return Mesh(vertices, triangles, GRAIN)


def box_mesh(box: Box) -> Mesh:
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    vertices = (lo + corners * (hi - lo)).astype(np.float32)
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = np.array(
        [t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))], dtype=np.uint32
    )
    return Mesh(vertices, triangles, CLUTTER)


WALL_SIDES = 720  # a round wall's mesh: the chords sag 10 um per metre of radius
WALL_FOOT_M = 0.3  # the wall mesh starts this far under the bottom at the wall


def wall_mesh(shape: BinShape, sides: int = WALL_SIDES) -> Mesh:
    """The bin's wall, from under its foot to the eave: a band of quads around the wall."""
    theta = np.arange(sides) * (2 * np.pi / sides)
    cx, cy = shape.centre
    x, y = cx + shape.radius_m * np.cos(theta), cy + shape.radius_m * np.sin(theta)
    foot = float(np.min(shape.bottom(x, y))) - WALL_FOOT_M
    ring = np.column_stack([x, y])
    vertices = np.concatenate(
        [
            np.column_stack([ring, np.full(sides, foot)]),
            np.column_stack([ring, np.full(sides, shape.eave_z)]),
        ]
    )
    i = np.arange(sides, dtype=np.uint32)
    j = (i + 1) % sides
    triangles = np.concatenate(
        [np.stack([i, j, j + sides], 1), np.stack([i, j + sides, i + sides], 1)]
    ).astype(np.uint32)
    return Mesh(vertices.astype(np.float32), triangles, CLUTTER)


def roof_mesh(shape: BinShape, sides: int = WALL_SIDES) -> Mesh:
    """The conical roof from the eave to the peak over the centre."""
    theta = np.arange(sides) * (2 * np.pi / sides)
    cx, cy = shape.centre
    rim = np.column_stack(
        [
            cx + shape.radius_m * np.cos(theta),
            cy + shape.radius_m * np.sin(theta),
            np.full(sides, shape.eave_z),
        ]
    )
    vertices = np.concatenate([rim, [[cx, cy, shape.roof_peak_z]]])
    i = np.arange(sides, dtype=np.uint32)
    triangles = np.stack([i, (i + 1) % sides, np.full(sides, sides, np.uint32)], 1)
    return Mesh(vertices.astype(np.float32), triangles.astype(np.uint32), CLUTTER)


def build_world(scene: Scene, step: float | None = None) -> World:
    """The scene's meshes; `step` defaults to the scene's own height-field step."""
    meshes = [height_field_mesh(scene, step or scene.mesh_step_m)]
    if scene.outer_z is not None:
        meshes.append(ring_mesh(scene.extent, scene.outer_z, reach=30.0))
    if scene.bin is not None:
        meshes += [wall_mesh(scene.bin), roof_mesh(scene.bin)]
    meshes.extend(box_mesh(box) for box in scene.clutter)
    return World(tuple(meshes))
