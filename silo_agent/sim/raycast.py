"""Ray casting against a `World`: the only module of the simulator that needs open3d."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from silo_agent.sim.mesh import World


@dataclass(frozen=True)
class Hits:
    t: np.ndarray  # (N,) ray parameter (inf: no hit); with unit-z camera rays this is depth
    normals: np.ndarray  # (N, 3) unit normal of the hit triangle, silo frame
    material: np.ndarray  # (N,) int, the hit mesh's material (-1: no hit)


class Raycaster:
    """An open3d `RaycastingScene` built once per world and reused for every camera."""

    def __init__(self, world: World) -> None:
        self._scene = o3d.t.geometry.RaycastingScene()
        for mesh in world.meshes:
            # open3d's stub makes Tensor's dtype and device required; they default (array's, CPU)
            self._scene.add_triangles(
                o3d.core.Tensor(mesh.vertices),  # type: ignore[call-overload]
                o3d.core.Tensor(mesh.triangles),  # type: ignore[call-overload]
            )
        self._materials = np.array([m.material for m in world.meshes] + [-1])

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        # open3d's stub makes Tensor's dtype and device required; they default (array's, CPU)
        result = self._scene.cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]
        t = result["t_hit"].numpy()
        geometry = result["geometry_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        geometry[~hit] = len(self._materials) - 1
        return Hits(
            t=t, normals=result["primitive_normals"].numpy(), material=self._materials[geometry]
        )
