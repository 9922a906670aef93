"""Pile detection: the geometric detector on the height map, and a site's YOLO model (ONNX).

`analyse` is what `process`, `scan` and the daemon call: YOLO first when a model is configured
(its robot boxes are cut out of the cloud before the surface is built), then the reconstruction,
then the piles of both detectors, with ids carried over from the previous scan. onnxruntime is
imported only when a model is configured.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from silo_agent.config import CalibrationConfig, DetectionConfig, ReconstructionConfig
from silo_agent.detect.geometric import EDGE_M, Surface, detect_piles, grid_of
from silo_agent.detect.piles import ModelError, Pile, match_ids
from silo_agent.scan import CameraCloud, Scan, Site

if TYPE_CHECKING:
    from silo_agent.detect.onnx_yolo import Located
    from silo_agent.reconstruct import Result

__all__ = [
    "ModelError",
    "Pile",
    "Robot",
    "analyse",
    "match_ids",
    "onnx_piles",
    "points_outside",
    "robots_of",
]


@dataclass(frozen=True)
class Robot:
    """The leveling robot as the model saw it: its position and the disc cut from the cloud."""

    x: float
    y: float
    z: float
    radius_m: float
    confidence: float
    camera: str

    def to_json(self) -> dict[str, Any]:
        return {"x": self.x, "y": self.y, "z": self.z, "radius_m": self.radius_m,
                "confidence": self.confidence, "camera": self.camera}  # fmt: skip

    @property
    def disc(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.radius_m)


def points_outside(points: np.ndarray, discs: Sequence[tuple[float, float, float]]) -> np.ndarray:
    """Mask of the (N, 3) silo-frame points outside every (x, y, radius) disc."""
    keep = np.ones(len(points), dtype=bool)
    for x, y, radius in discs:
        keep &= np.hypot(points[:, 0] - x, points[:, 1] - y) > radius
    return keep


def robots_of(found: Sequence[Located], robot_classes: Sequence[str]) -> list[Robot]:
    return [
        Robot(f.point[0], f.point[1], f.point[2], f.size_m, f.box.score, f.camera)
        for f in found
        if f.box.name in robot_classes
    ]


def fused_points(cameras: Sequence[CameraCloud]) -> np.ndarray:
    """Every camera's points in the silo frame, one (N, 3) array."""
    if not cameras:
        return np.empty((0, 3), np.float32)
    return np.concatenate([c.points_in_silo() for c in cameras])


def onnx_piles(
    found: Sequence[Located],
    pile_classes: Sequence[str],
    cloud: np.ndarray,
    surface: Surface,
    radius_m: float,
) -> list[Pile]:
    """Piles of the model's boxes (paper 2.3.2): the fused points within `radius_m` of the point
    under each box are its cluster; the height-map cells those points fall in, where grain
    stands `EDGE_M` above the base (as for a geometric pile), are measured as the pile."""
    hm = surface.heightmap
    grid = grid_of(hm)
    rows, cols = hm.shape
    piles = []
    for f in found:
        if f.box.name not in pile_classes:
            continue
        near = np.linalg.norm(cloud - np.asarray(f.point, dtype=np.float32), axis=1) <= radius_m
        row, col = grid.cell_index(cloud[near, 0], cloud[near, 1])
        ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        cells = np.zeros(hm.shape, dtype=bool)
        cells[row[ok], col[ok]] = True
        cells &= np.isfinite(surface.smooth) & (surface.smooth > EDGE_M)
        if np.any(cells):
            piles.append(surface.pile(cells, "onnx", f.box.score))
    return piles


def analyse(
    scan: Scan,
    settings: ReconstructionConfig,
    detection: DetectionConfig,
    site: Site | None = None,
    previous: Sequence[Pile] = (),
    calibration: CalibrationConfig | None = None,
) -> Result:
    """Reconstruct `scan` and detect its piles (and robot) as `detection` configures.

    `calibration` sets how the registration residual is measured; with `refine` on, a bounded
    registration of the overlaps adjusts the scan's extrinsics first (silo_agent.calibrate).
    """
    from silo_agent.reconstruct import reconstruct
    from silo_agent.reconstruct.volume import base_surface

    site = site or scan.site
    found: list[Located] = []
    robots: list[Robot] = []
    onnx = detection.onnx
    if onnx is not None:
        from silo_agent.detect.onnx_yolo import YoloModel, locate

        found = locate(YoloModel(onnx.model), scan.cameras, onnx.confidence, onnx.iou)
        robots = robots_of(found, onnx.robot_classes)
    notes: list[str] = []
    if calibration is not None and calibration.refine:
        from silo_agent.calibrate import refine

        scan, notes = refine(scan, calibration, site)
    result = reconstruct(scan, settings, site, exclude=[r.disc for r in robots],
                         calibration=calibration)
    if calibration is not None and calibration.refine:
        result.parameters["refined"] = not notes
        result.parameters["refine_notes"] = notes
    result.robots = robots if onnx is not None else None
    if result.heightmap is None:
        result.piles = []
        return result
    hm = result.heightmap
    base = base_surface(grid_of(hm), hm.heights.astype(float), site.base, site.floor_z)
    surface = Surface.of(hm, base, site.floor_z, detection.background_m)
    piles: list[Pile] = []
    if detection.geometric:
        piles += detect_piles(surface, detection)
    if onnx is not None:
        cloud = fused_points(scan.cameras)
        cloud = cloud[points_outside(cloud, [r.disc for r in robots])]
        piles += onnx_piles(found, onnx.pile_classes, cloud, surface, onnx.cluster_radius_m)
    result.piles = match_ids(previous, piles, detection.match_distance_m)
    return result
