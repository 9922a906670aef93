"""Triangle meshes of a scene (pure numpy): the height field, the open floor around it, clutter.

The height-field mesh takes the surface's values at its vertices, so with a 1 cm step its
volume differs from the analytic truth by far less than the camera noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


def build_world(scene: Scene, step: float = 0.01) -> World:
    meshes = [height_field_mesh(scene, step)]
    if scene.outer_z is not None:
        meshes.append(ring_mesh(scene.extent, scene.outer_z, reach=30.0))
    meshes.extend(box_mesh(box) for box in scene.clutter)
    return World(tuple(meshes))
