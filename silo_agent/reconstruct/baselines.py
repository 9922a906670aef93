"""The paper's comparison methods (Table 1), computed the way the paper did, for benchmarks.

- rectangle: highest point per cell, empty cells count as floor (paper fig. 24, no filling)
- hull:      volume of the convex hull of the pile's points and their floor projections
- alpha:     volume of the alpha complex of the same points (Delaunay tetrahedra with
             circumradius below alpha)
             (the pile's points: more than PILE_ABOVE_FLOOR_M above the floor, as the paper
             built both from the pile's cropped cloud; the noisy bare floor would otherwise
             become a slab as thick as its noise)
- poisson:   open3d screened Poisson surface, rasterised from above onto the grid
The down-sampled cloud uses the grid step as voxel, as in the paper's experiment.
"""

from __future__ import annotations

import numpy as np

from silo_agent.config import ReconstructionConfig
from silo_agent.grid.grid import Grid
from silo_agent.grid.volume import base_surface, integrate
from silo_agent.reconstruct.fuse import FusedCloud
from silo_agent.scan import Site


def _voxel_down(points: np.ndarray, size: float) -> np.ndarray:
    keys = np.floor(points / size).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.stack([np.bincount(inverse, points[:, k]) for k in range(3)], axis=1)
    return sums / counts[:, None]


PILE_ABOVE_FLOOR_M = 0.05


def _pile_with_floor(points: np.ndarray, floor_z: float) -> np.ndarray:
    pile = points[points[:, 2] > floor_z + PILE_ABOVE_FLOOR_M]
    floor = pile.copy()
    floor[:, 2] = floor_z
    return np.vstack([pile, floor])


def _tetra_volumes_and_radii(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b, c, d = (vertices[:, i] for i in range(4))
    ab, ac, ad = b - a, c - a, d - a
    volume = np.abs(np.einsum("ij,ij->i", ab, np.cross(ac, ad))) / 6.0
    # circumcentre offset from a solves 2 [ab; ac; ad] x = [|ab|², |ac|², |ad|²]
    matrix = 2.0 * np.stack([ab, ac, ad], axis=1)
    rhs = np.stack([(ab**2).sum(1), (ac**2).sum(1), (ad**2).sum(1)], axis=1)
    ok = volume > 1e-15
    radius = np.full(len(vertices), np.inf)
    radius[ok] = np.linalg.norm(np.linalg.solve(matrix[ok], rhs[ok][..., None])[..., 0], axis=1)
    return volume, radius


def _rectangle(fused: FusedCloud, grid: Grid, site: Site) -> tuple[np.ndarray, np.ndarray]:
    top = np.full(grid.shape[0] * grid.shape[1], -np.inf)
    np.maximum.at(top, fused.cell, fused.points[:, 2].astype(np.float64))
    observed = np.isfinite(top).reshape(grid.shape)
    heights = np.where(observed, top.reshape(grid.shape), site.floor_z)
    return np.where(grid.inside > 0, heights, np.nan), observed & (grid.inside > 0)


def _poisson(points: np.ndarray, grid: Grid, site: Site, depth: int) -> np.ndarray:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=30))
    cloud.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=depth)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    xs, ys = grid.centres()
    top = float(points[:, 2].max()) + 10.0
    rays = np.zeros((xs.size, 6), dtype=np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = xs.ravel(), ys.ravel(), top, -1.0
    # open3d's stub makes Tensor's dtype and device required; they default (array's, CPU)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # type: ignore[call-overload]
    heights = np.where(np.isfinite(hit), top - hit, site.floor_z).reshape(grid.shape)
    return np.where(grid.inside > 0, heights, np.nan)


def baseline_heights(
    settings: ReconstructionConfig, fused: FusedCloud, grid: Grid, site: Site
) -> tuple[np.ndarray | None, np.ndarray, float | None]:
    """(heights or None, observed mask, volume) for a baseline method."""
    observed = np.zeros(grid.shape, dtype=bool)
    if len(fused.points) == 0:
        return None, observed, None
    if settings.method == "rectangle":
        heights, observed = _rectangle(fused, grid, site)
        base = base_surface(grid, heights, site.base, site.floor_z)
        return heights, observed, integrate(grid, heights, base)
    _, observed = _rectangle(fused, grid, site)
    sample = _voxel_down(fused.points.astype(np.float64), settings.grid_step_m)
    if settings.method == "poisson":
        heights = _poisson(sample, grid, site, settings.poisson_depth)
        base = base_surface(grid, heights, site.base, site.floor_z)
        return heights, observed, integrate(grid, heights, base)

    from scipy.spatial import ConvexHull, Delaunay

    solid = _pile_with_floor(sample, site.floor_z)
    if len(solid) < 8:
        return None, observed, 0.0
    if settings.method == "hull":
        return None, observed, float(ConvexHull(solid).volume)
    alpha = settings.alpha_m or 4.0 * settings.grid_step_m
    tetrahedra = Delaunay(solid).simplices
    volume, radius = _tetra_volumes_and_radii(solid[tetrahedra])
    return None, observed, float(np.sum(volume[radius < alpha]))
