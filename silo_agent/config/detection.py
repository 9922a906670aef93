"""`[detection]`: pile detectors (geometric, ONNX YOLO)."""

from __future__ import annotations

from pathlib import Path

from pydantic import (
    Field,
    model_validator,
)

from silo_agent.config.base import Strict


class OnnxDetectionConfig(Strict):
    """A site's Ultralytics YOLO model exported to ONNX (paper 2.2); none ships with silo-agent."""

    model: Path = Field(
        description="the .onnx file of `yolo export format=onnx`; it must exist when the config "
        "is loaded (a relative path: from the working directory)"
    )
    confidence: float = Field(default=0.5, gt=0, lt=1, description="paper 2.2 threshold")
    iou: float = Field(default=0.45, gt=0, le=1, description="NMS overlap that drops a box")
    pile_classes: list[str] = Field(default=["pile"], description="class names that are piles")
    robot_classes: list[str] = Field(
        default=["robot"], description="class names that are the leveling robot"
    )
    cluster_radius_m: float = Field(
        default=0.98, gt=0, description="paper 2.3.2 radius clustering around the box's point"
    )

    @model_validator(mode="after")
    def _disjoint_classes(self) -> OnnxDetectionConfig:
        both = sorted(set(self.pile_classes) & set(self.robot_classes))
        if both:
            raise ValueError(f"classes both pile and robot: {', '.join(both)}")
        return self


class DetectionConfig(Strict):
    """Pile detection: the geometric detector on the height map, and optionally a YOLO model."""

    geometric: bool = True
    min_height_m: float = Field(default=0.10, gt=0, description="a pile's peak above its base")
    min_area_m2: float = Field(default=0.10, gt=0, description="smaller footprints are dropped")
    min_prominence_m: float = Field(
        default=0.10, gt=0, description="a peak this far above its saddle is a pile of its own"
    )
    min_separation_m: float = Field(default=0.3, gt=0, description="closer peaks are one pile")
    background_m: float | None = Field(
        default=None,
        gt=0,
        description="piles on a local background (opening of this width) instead of the base",
    )
    match_distance_m: float = Field(
        default=0.5, gt=0, description="a pile this close to one of the last scan keeps its id"
    )
    onnx: OnnxDetectionConfig | None = None
