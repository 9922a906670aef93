"""Independent ground truth for engine tests: analytic height fields seen by camera-like views.

Deliberately separate from the simulator and the engine: the surface is sampled directly,
visibility is a march along the line of sight over the height field, noise follows the D455
model along the ray. Volumes come from closed forms.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from silo_agent.grid.geometry import transform_from_euler
from silo_agent.scan import CameraCloud, Scan, Site

HeightField = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Scene:
    height: HeightField  # metres above floor z = 0
    volume: float  # exact volume above the floor inside `region`
    region: np.ndarray


def cone(radius: float = 1.5, slope_deg: float = 25.0, centre=(0.0, 0.0), half=2.5) -> Scene:
    h = radius * math.tan(math.radians(slope_deg))

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r = np.hypot(x - centre[0], y - centre[1])
        return np.maximum(h * (1 - r / radius), 0.0)

    region = np.array([[-half, -half], [half, -half], [half, half], [-half, half]], float)
    return Scene(height, math.pi * radius**2 * h / 3, region)


def frustum_on_slab(half: float = 2.0) -> Scene:
    """A flat 0.3 m layer plus a truncated cone: a full floor with a pile on it."""
    r1, r2, h = 1.2, 0.4, 0.5

    def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r = np.hypot(x, y)
        pile = np.clip((r1 - r) / (r1 - r2), 0, 1) * h
        return 0.3 + pile

    region = np.array([[-half, -half], [half, -half], [half, half], [-half, half]], float)
    frustum = math.pi * h / 3 * (r1**2 + r1 * r2 + r2**2)
    return Scene(height, 0.3 * (2 * half) ** 2 + frustum, region)


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera (optical frame: x right, y down, z forward) -> silo transform."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    matrix = np.eye(4)
    matrix[:3, :3] = np.column_stack([right, down, forward])
    matrix[:3, 3] = position
    return matrix


def ring_views(count: int, distance: float = 2.5, height: float = 1.0) -> list[np.ndarray]:
    """`count` cameras evenly around the pile (count=2: opposite, like A1 A5)."""
    poses = []
    for k in range(count):
        a = -math.pi / 2 + 2 * math.pi * k / count
        pos = np.array([distance * math.cos(a), distance * math.sin(a), height])
        poses.append(look_at(pos, np.array([0.0, 0.0, 0.2])))
    return poses


def observe(
    scene: Scene,
    poses: list[np.ndarray],
    rng: np.random.Generator,
    spacing: float = 0.006,
    focal_px: float = 430.0,
    noise_scale: float = 1.0,
    dropout: float = 0.05,
    pose_error: tuple[float, float] = (0.0, 0.0),
) -> Scan:
    """Sample the surface on a jittered grid, keep what each camera sees, add D455 noise.

    `pose_error` (degrees, metres): the cloud is rendered from a perturbed pose while the
    manifest keeps the nominal one, which produces the misaligned double surfaces of fig. 4.
    """
    low, high = scene.region.min(0) - 0.2, scene.region.max(0) + 0.2
    gx, gy = np.meshgrid(np.arange(low[0], high[0], spacing), np.arange(low[1], high[1], spacing))
    x = (gx + rng.uniform(-spacing / 2, spacing / 2, gx.shape)).ravel()
    y = (gy + rng.uniform(-spacing / 2, spacing / 2, gy.shape)).ravel()
    z = scene.height(x, y)
    eps = 1e-3
    dzdx = (scene.height(x + eps, y) - scene.height(x - eps, y)) / (2 * eps)
    dzdy = (scene.height(x, y + eps) - scene.height(x, y - eps)) / (2 * eps)
    normal = np.column_stack([-dzdx, -dzdy, np.ones_like(z)])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    surface = np.column_stack([x, y, z])

    cameras = []
    for index, nominal in enumerate(poses):
        true_pose = nominal.copy()
        if pose_error != (0.0, 0.0):
            angles = rng.normal(size=3)
            angles *= pose_error[0] / np.linalg.norm(angles)
            shift = rng.normal(size=3)
            shift *= pose_error[1] / np.linalg.norm(shift)
            true_pose = nominal @ transform_from_euler(angles, [0, 0, 0])
            true_pose[:3, 3] += shift
        centre = true_pose[:3, 3]
        ray = centre - surface
        dist = np.linalg.norm(ray, axis=1)
        ray_dir = ray / dist[:, None]
        facing = np.einsum("ij,ij->i", normal, ray_dir) > 0.1
        visible = facing.copy()
        for t in np.linspace(0.02, 0.98, 40):  # march towards the camera over the height field
            p = surface + ray * t
            visible &= scene.height(p[:, 0], p[:, 1]) <= p[:, 2] + 1e-4
        visible &= rng.random(len(visible)) > dropout
        cam_pts = (surface[visible] - true_pose[:3, 3]) @ true_pose[:3, :3]
        depth = cam_pts[:, 2]
        in_view = (np.abs(cam_pts[:, 0] / depth) < 0.8) & (np.abs(cam_pts[:, 1] / depth) < 0.5)
        keep = (depth > 0.4) & in_view
        cam_pts = cam_pts[keep]
        sigma = noise_scale * cam_pts[:, 2] ** 2 * 0.08 / (focal_px * 0.095)
        cam_pts = cam_pts * (1 + rng.normal(size=len(cam_pts)) * sigma / cam_pts[:, 2])[:, None]
        cameras.append(
            CameraCloud(serial=f"cam{index}", points=cam_pts.astype(np.float32), extrinsic=nominal)
        )
    site = Site(region=scene.region, floor_z=0.0, ceiling_z=2.0)
    return Scan("synthetic-1", "2026-11-22T10:15:00Z", "silo-1", site, cameras, {}, {})
