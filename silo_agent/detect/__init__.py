"""Pile detection: the geometric detector on the height map, and a site's YOLO model (ONNX).

Detection works on what the reconstruction produced (it sits above `silo_agent.reconstruct`);
`silo_agent.analysis.scan_analysis.analyse` runs the two in order. onnxruntime is imported
only when a model is configured.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from silo_agent.detect.geometric import EDGE_M, Surface, grid_of
from silo_agent.detect.piles import ModelError, Pile, match_ids
from silo_agent.scan import CameraCloud

if TYPE_CHECKING:
    from silo_agent.detect.onnx_yolo import Located

__all__ = [
    "ModelError",
    "Pile",
    "Robot",
    "fused_points",
    "match_ids",
    "onnx_piles",
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
        return {
            "x": self.x,
            "y": self.y,
            "z": self.z,
            "radius_m": self.radius_m,
            "confidence": self.confidence,
            "camera": self.camera,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Robot:
        """A robot of an earlier result.json."""
        return cls(
            float(data["x"]),
            float(data["y"]),
            float(data["z"]),
            float(data["radius_m"]),
            float(data["confidence"]),
            str(data["camera"]),
        )

    @property
    def disc(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.radius_m)


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
