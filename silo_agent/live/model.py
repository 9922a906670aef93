"""The site's YOLO model in live mode: robot boxes on the cameras' colour frames.

Depth alone misses a robot too flat for `robot_min_height_m` or one in a camera's shadow; a
model trained on the site's robot sees it in colour. Inference costs far more than a live map,
so the model runs at most `[live] model_rate_hz` times a second, on every camera that gives
colour; the maps in between reuse its last sightings (a robot moves a few decimetres in that
time, and the depth rule still follows it). onnxruntime is loaded only here, through
detect/onnx_yolo.py, and only when `[detection.onnx]` names a model with a robot class.
"""

from __future__ import annotations

from collections.abc import Sequence

import structlog

from silo_agent.config import Config
from silo_agent.live.map import DepthFrame, LiveMap, RobotSighting

log = structlog.get_logger(__name__)


class LiveRobotModel:
    """`[detection.onnx]`'s model and its robot classes, rate-limited, with its last sightings."""

    def __init__(self, config: Config) -> None:
        """Raises ModelError (names the file) when the model cannot be loaded."""
        from silo_agent.detect.onnx_yolo import YoloModel

        settings = config.detection.onnx
        assert settings is not None  # the caller checks `wanted` first
        self.settings = settings
        self.model = YoloModel(settings.model)
        self.robot_classes = set(settings.robot_classes) & set(self.model.names.values())
        if not self.robot_classes:
            log.warning(
                "the model has none of [detection.onnx] robot_classes: live maps find "
                "the robot from depth alone",
                model=str(settings.model),
                robot_classes=settings.robot_classes,
            )
        self.period_s = 1.0 / config.live.model_rate_hz
        self.last_run_s = -float("inf")
        self.sightings: list[RobotSighting] = []
        self._blind: set[str] = set()  # cameras already reported without colour

    @staticmethod
    def wanted(config: Config) -> bool:
        return config.detection.onnx is not None and bool(config.detection.onnx.robot_classes)

    def due(self, now_s: float) -> bool:
        """Whether the next map should bring colour frames for the model."""
        return bool(self.robot_classes) and now_s - self.last_run_s >= self.period_s

    def robots(
        self, frames: Sequence[DepthFrame], live: LiveMap, now_s: float
    ) -> list[RobotSighting]:
        """The robots in the frames' colour images when a run is due, else the last run's."""
        if not self.due(now_s):
            return self.sightings
        self.last_run_s = now_s
        found = []
        for frame in frames:
            if frame.color is None:
                if frame.serial not in self._blind:
                    self._blind.add(frame.serial)
                    log.warning(
                        "no colour image: the YOLO model cannot look for the robot",
                        camera=frame.serial,
                    )
                continue
            for box in self.model.detect(frame.color, self.settings.confidence, self.settings.iou):
                if box.name not in self.robot_classes:
                    continue
                sighting = live.sighting_of(frame, (box.x1, box.y1, box.x2, box.y2))
                if sighting is not None:
                    found.append(sighting)
        self.sightings = found
        return found
