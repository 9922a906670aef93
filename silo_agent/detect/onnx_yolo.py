"""YOLO pile / robot detector on an Ultralytics ONNX export (paper 2.2), and box -> silo frame.

The only module that imports onnxruntime. A model is whatever a site trained and exported with
`yolo export model=best.pt format=onnx`: input `[1, 3, H, W]` RGB in 0..1, letterboxed; output
`[1, 4 + nc, N]` (box centre x, y, width, height in input pixels, then one score per class);
class names and input size in the model's metadata (`names`, `imgsz`).

Box -> 3D follows paper 2.3.2: the depth point under the box centre (the colour image is aligned
to depth, so pixel = depth pixel), moved to the silo frame, then every fused point within a
radius of it is the pile's cluster.
"""

from __future__ import annotations

import ast
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
import structlog

from silo_agent.detect.piles import ModelError
from silo_agent.scan import CameraCloud

__all__ = [
    "Box",
    "Located",
    "ModelError",
    "YoloModel",
    "camera_image",
    "decode",
    "letterbox",
    "locate",
    "nms",
]

PAD_VALUE = 114  # Ultralytics' letterbox grey

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class Box:
    """One detection in image pixels (x right, y down; corners)."""

    class_id: int
    name: str
    score: float
    x1: float
    y1: float
    x2: float
    y2: float

    @property
    def centre(self) -> tuple[float, float]:
        return ((self.x1 + self.x2) / 2, (self.y1 + self.y2) / 2)


@dataclass(frozen=True)
class Located:
    """A box placed in the silo frame: the point under it and its radius cluster."""

    box: Box
    camera: str  # serial of the camera whose image it was found in
    point: tuple[float, float, float]  # silo frame, the depth point under the box centre
    size_m: float  # the box's half diagonal at that depth: how far the object reaches


def letterbox(
    image: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, float, tuple[int, int]]:
    """Ultralytics' letterbox: scale to fit `size` (h, w) keeping the aspect, pad centred.

    Returns the network input `[1, 3, h, w]` float32 in 0..1, the scale and the (left, top)
    padding, so that input pixel = image pixel * scale + padding.
    """
    height, width = image.shape[:2]
    scale = min(size[0] / height, size[1] / width)
    new_w, new_h = round(width * scale), round(height * scale)
    pad_w, pad_h = (size[1] - new_w) / 2, (size[0] - new_h) / 2
    left, top = round(pad_w - 0.1), round(pad_h - 0.1)
    resized = _resize_bilinear(image, new_h, new_w)
    canvas = np.full((size[0], size[1], 3), PAD_VALUE, dtype=np.float32)
    canvas[top : top + new_h, left : left + new_w] = resized
    tensor = (canvas / 255.0).transpose(2, 0, 1)[None].astype(np.float32)
    return np.ascontiguousarray(tensor), scale, (left, top)


def _resize_bilinear(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear resize with pixel centres aligned (OpenCV's INTER_LINEAR convention)."""
    src_h, src_w = image.shape[:2]
    if (src_h, src_w) == (height, width):
        return image.astype(np.float32)
    ys = np.clip((np.arange(height) + 0.5) * src_h / height - 0.5, 0, src_h - 1)
    xs = np.clip((np.arange(width) + 0.5) * src_w / width - 0.5, 0, src_w - 1)
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, src_h - 1), np.minimum(x0 + 1, src_w - 1)
    wy, wx = (ys - y0)[:, None, None], (xs - x0)[None, :, None]
    img = image.astype(np.float32)
    top = img[y0][:, x0] * (1 - wx) + img[y0][:, x1] * wx
    bottom = img[y1][:, x0] * (1 - wx) + img[y1][:, x1] * wx
    return top * (1 - wy) + bottom * wy


def decode(output: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`[1, 4 + nc, N]` -> (corner boxes (M, 4) in input pixels, scores (M,), classes (M,)),
    keeping the candidates whose best class scores at least `confidence`."""
    rows = output[0].T  # (N, 4 + nc)
    scores_all = rows[:, 4:]
    classes = np.argmax(scores_all, axis=1)
    scores = scores_all[np.arange(len(rows)), classes]
    keep = scores >= confidence
    cx, cy, w, h = rows[keep, :4].T
    boxes = np.column_stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])
    return boxes, scores[keep], classes[keep]


def nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou: float) -> np.ndarray:
    """Class-aware non-maximum suppression: indices kept, best score first.

    Boxes of different classes never suppress each other (a robot on a pile stays a robot):
    each class is shifted by an offset larger than any coordinate, as Ultralytics does.
    """
    if len(boxes) == 0:
        return np.empty(0, dtype=np.int64)
    shifted = boxes + classes[:, None] * (float(np.abs(boxes).max()) + 1.0) * 2
    area = (shifted[:, 2] - shifted[:, 0]) * (shifted[:, 3] - shifted[:, 1])
    order = np.argsort(-scores, kind="stable")
    kept = []
    while len(order):
        best, rest = order[0], order[1:]
        kept.append(best)
        lo = np.maximum(shifted[best, :2], shifted[rest, :2])
        hi = np.minimum(shifted[best, 2:], shifted[rest, 2:])
        inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
        overlap = inter / (area[best] + area[rest] - inter)
        order = rest[overlap <= iou]
    return np.asarray(kept, dtype=np.int64)


class YoloModel:
    """An Ultralytics YOLO detection model exported to ONNX, checked when loaded."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self.session = ort.InferenceSession(str(self.path), providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise ModelError(f"{self.path}: cannot load the ONNX model: {exc}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        self.names = self._names(meta)
        self.imgsz = self._imgsz(meta)
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise ModelError(f"{self.path}: expected one [1, 3, H, W] image input")
        self.input_name = inputs[0].name
        self._check_output(outputs[0].shape)

    def _names(self, meta: dict[str, str]) -> dict[int, str]:
        if "names" not in meta:
            raise ModelError(
                f"{self.path}: metadata has no 'names' (class names); export the model with "
                "Ultralytics `yolo export format=onnx`"
            )
        try:
            names = ast.literal_eval(meta["names"])
            return {int(k): str(v) for k, v in dict(names).items()}
        except (ValueError, SyntaxError, TypeError) as exc:
            raise ModelError(f"{self.path}: metadata 'names' is not a class map: {exc}") from None

    def _imgsz(self, meta: dict[str, str]) -> tuple[int, int]:
        if "imgsz" not in meta:
            raise ModelError(f"{self.path}: metadata has no 'imgsz' (input size)")
        try:
            size = ast.literal_eval(meta["imgsz"])
            h, w = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
        except (ValueError, SyntaxError, TypeError, IndexError) as exc:
            raise ModelError(f"{self.path}: metadata 'imgsz' is not a size: {exc}") from None
        return h, w

    def _check_output(self, shape: Sequence[int | str | None]) -> None:
        """The output must be [1, 4 + nc, N]; a dynamic dimension is checked at the first run."""
        expected = 4 + len(self.names)
        if len(shape) != 3 or (isinstance(shape[1], int) and shape[1] != expected):
            raise ModelError(
                f"{self.path}: output shape {list(shape)} is not [1, {expected}, N] "
                f"(4 box values + {len(self.names)} classes): not a YOLO detection export"
            )

    def detect(self, image: np.ndarray, confidence: float, iou: float) -> list[Box]:
        """Boxes in `image` pixels (RGB, (H, W, 3) uint8) after threshold and NMS."""
        tensor, scale, (left, top) = letterbox(image, self.imgsz)
        (output,) = self.session.run(None, {self.input_name: tensor})[:1]
        self._check_output(output.shape)
        if output.shape[0] != 1:
            raise ModelError(f"{self.path}: output batch {output.shape[0]}, expected 1")
        boxes, scores, classes = decode(output, confidence)
        keep = nms(boxes, scores, classes, iou)
        height, width = image.shape[:2]
        out = []
        for i in keep:
            x1, y1, x2, y2 = boxes[i]
            out.append(
                Box(
                    class_id=int(classes[i]),
                    name=self.names.get(int(classes[i]), str(int(classes[i]))),
                    score=float(scores[i]),
                    x1=float(np.clip((x1 - left) / scale, 0, width)),
                    y1=float(np.clip((y1 - top) / scale, 0, height)),
                    x2=float(np.clip((x2 - left) / scale, 0, width)),
                    y2=float(np.clip((y2 - top) / scale, 0, height)),
                )
            )
        return out


def camera_image(cloud: CameraCloud) -> tuple[np.ndarray, np.ndarray] | None:
    """The colour image aligned to depth, rebuilt from the cloud, and per pixel the index of its
    point (-1: no depth); None when the camera captured no colour or no intrinsics.

    Points are projected through the pinhole intrinsics (the D455 depth stream has no lens
    distortion), which lands each point back on the pixel it was deprojected from.
    """
    k = cloud.intrinsics
    if cloud.colors is None or k is None or len(cloud.points) == 0:
        return None
    width, height = int(k["width"]), int(k["height"])
    pts = cloud.points.astype(np.float64)
    z = pts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(pts[:, 0] / z * k["fx"] + k["ppx"])
        v = np.rint(pts[:, 1] / z * k["fy"] + k["ppy"])
    ok = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    index = np.full((height, width), -1, dtype=np.int64)
    rows, cols = v[ok].astype(np.int64), u[ok].astype(np.int64)
    index[rows, cols] = np.flatnonzero(ok)
    image = np.zeros((height, width, 3), dtype=np.uint8)
    image[rows, cols] = cloud.colors[ok]
    return image, index


def point_under(box: Box, index: np.ndarray) -> int | None:
    """Index of the point at the box centre, or of the nearest pixel with depth inside the box
    (stereo holes are common at a pile's apex); None when the box holds no depth at all."""
    height, width = index.shape
    cu, cv = box.centre
    u0, u1 = int(np.floor(box.x1)), min(int(np.ceil(box.x2)), width)
    v0, v1 = int(np.floor(box.y1)), min(int(np.ceil(box.y2)), height)
    window = index[v0:v1, u0:u1]
    rows, cols = np.nonzero(window >= 0)
    if len(rows) == 0:
        return None
    distance = np.hypot(cols + u0 + 0.5 - cu, rows + v0 + 0.5 - cv)
    best = int(np.argmin(distance))
    return int(window[rows[best], cols[best]])


def locate(
    model: YoloModel, cameras: Sequence[CameraCloud], confidence: float, iou: float
) -> list[Located]:
    """Run the model on every camera that captured colour; each box placed in the silo frame.

    A camera without colour is skipped with a warning: YOLO needs the RGB image
    (`[[cameras]] color = true`)."""
    found = []
    for cloud in cameras:
        rebuilt = camera_image(cloud)
        if rebuilt is None:
            log.warning("no colour image: the YOLO model cannot look", camera=cloud.serial)
            continue
        image, index = rebuilt
        k = cloud.intrinsics or {}  # present: camera_image needs it
        silo = cloud.points_in_silo()
        for box in model.detect(image, confidence, iou):
            i = point_under(box, index)
            if i is None:
                continue
            depth = float(cloud.points[i, 2])
            reach = np.hypot((box.x2 - box.x1) / k["fx"], (box.y2 - box.y1) / k["fy"]) * depth / 2
            x, y, z = (float(c) for c in silo[i])
            found.append(Located(box, cloud.serial, (x, y, z), float(reach)))
    return found
