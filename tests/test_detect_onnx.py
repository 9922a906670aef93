"""The YOLO (ONNX) path end to end, with small models built here by the onnx helper API.

A synthetic camera looks straight down from 3 m on a cone (a pile) and a smooth bump (the
robot). The test model outputs fixed boxes whose class scores are the red value of the input
pixel at each pile's / robot's apex: only a correctly letterboxed image scores them above the
threshold. Expected letterbox, boxes, 3D points and volumes are computed here from the scene.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper
from pydantic import ValidationError

from silo_agent.analysis.scan_analysis import analyse
from silo_agent.analysis.summary import summarise
from silo_agent.config import Config, DetectionConfig, OnnxDetectionConfig, ReconstructionConfig
from silo_agent.detect import ModelError
from silo_agent.detect.onnx_yolo import YoloModel, camera_image, decode, letterbox, nms
from silo_agent.reconstruct import reconstruct
from silo_agent.scan import CameraCloud, Scan, Site

W, H, F = 640, 480, 400.0
PPX, PPY = (W - 1) / 2, (H - 1) / 2
CAMERA_Z = 3.0
IMGSZ = 320  # letterbox: scale 0.5, image 320 x 240, 40 px grey above and below
SCALE, LEFT, TOP = 0.5, 0, 40
CONE = (0.5, 0.3, 0.6, 0.3)  # x, y, radius, height
ROBOT = (-0.8, -0.6, 0.12, 0.12)  # x, y, height, Gaussian sigma
NAMES = {0: "pile", 1: "robot"}
RED, GREY = 255, 60


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    cx, cy, r, h = CONE
    cone = np.maximum(0.0, h * (1 - np.hypot(x - cx, y - cy) / r))
    rx, ry, rh, rs = ROBOT
    bump = rh * np.exp(-((x - rx) ** 2 + (y - ry) ** 2) / (2 * rs**2))
    return np.maximum(cone, bump)


def cast(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera-frame points where pixel rays hit the surface (fixed point: slopes are < 1)."""
    dx, dy = (u - PPX) / F, (v - PPY) / F
    t = np.full(np.shape(u), CAMERA_Z)
    for _ in range(80):
        t = CAMERA_Z - surface(dx * t, -dy * t)
    return np.stack([dx * t, dy * t, t], axis=-1)


EXTRINSIC = np.array(
    [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, CAMERA_Z], [0, 0, 0, 1]], dtype=float
)  # looking straight down: optical x = silo x, optical y = -silo y


def to_silo(points: np.ndarray) -> np.ndarray:
    return points @ EXTRINSIC[:3, :3].T + EXTRINSIC[:3, 3]


def project(x: float, y: float, z: float) -> tuple[float, float]:
    """Silo point -> (u, v) in continuous image coordinates (pixel i spans [i, i + 1))."""
    depth = CAMERA_Z - z
    return F * x / depth + PPX + 0.5, F * -y / depth + PPY + 0.5


@pytest.fixture(scope="module")
def scan() -> Scan:
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    points = cast(u, v).reshape(-1, 3)
    silo = to_silo(points)
    near_top = (np.hypot(silo[:, 0] - CONE[0], silo[:, 1] - CONE[1]) < 0.1) | (
        np.hypot(silo[:, 0] - ROBOT[0], silo[:, 1] - ROBOT[1]) < 0.1
    )
    colors = np.full((len(points), 3), GREY, dtype=np.uint8)
    colors[near_top, 0] = RED
    camera = CameraCloud(
        serial="top",
        points=points.astype(np.float32),
        extrinsic=EXTRINSIC,
        intrinsics={"width": W, "height": H, "fx": F, "fy": F, "ppx": PPX, "ppy": PPY},
        colors=colors,
    )
    region = np.array([[-1.5, -1.5], [1.5, -1.5], [1.5, 1.5], [-1.5, 1.5]])
    site = Site(region=region, floor_z=0.0, ceiling_z=2.0)
    return Scan("onnx-test", "2026-01-01T00:00:00Z", "test", site, [camera])


def build_model(
    path: Path,
    boxes: list[tuple[float, float, float, float, int, float, tuple[int, int]]],
    names: dict[int, str] | None = NAMES,
    imgsz: int = IMGSZ,
    extra_rows: int = 0,
) -> Path:
    """A model whose output [1, 4 + nc, N] holds `boxes` (cx, cy, w, h in input pixels, class,
    factor, (x, y) input pixel): box k scores factor_k x red(input at its pixel) for its class."""
    nc = len(names or NAMES)
    n = len(boxes)
    geometry = np.array([b[:4] for b in boxes], dtype=np.float32).T[None]  # [1, 4, N]
    onehot = np.zeros((1, nc + extra_rows, n), dtype=np.float32)
    for k, b in enumerate(boxes):
        onehot[0, b[4], k] = b[5]
    flat = np.array([b[6][1] * imgsz + b[6][0] for b in boxes], dtype=np.int64)  # channel 0
    const = helper.make_tensor
    nodes = [
        helper.make_node("Reshape", ["images", "flat_shape"], ["flat"]),
        helper.make_node("Gather", ["flat", "pixels"], ["red"]),
        helper.make_node("Reshape", ["red", "row_shape"], ["red_row"]),
        helper.make_node("Mul", ["red_row", "onehot"], ["scores"]),
        helper.make_node("Concat", ["geometry", "scores"], ["output0"], axis=1),
    ]
    inits = [
        const("flat_shape", TensorProto.INT64, [1], [-1]),
        const("pixels", TensorProto.INT64, [n], flat.tolist()),
        const("row_shape", TensorProto.INT64, [3], [1, 1, n]),
        const("onehot", TensorProto.FLOAT, list(onehot.shape), onehot.ravel().tolist()),
        const("geometry", TensorProto.FLOAT, list(geometry.shape), geometry.ravel().tolist()),
    ]
    graph = helper.make_graph(
        nodes,
        "yolo-test",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, imgsz, imgsz])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 4 + nc + extra_rows, n])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    props = {"imgsz": f"[{imgsz}, {imgsz}]", "task": "detect"}
    if names is not None:
        props["names"] = repr(names)
    helper.set_model_props(model, props)
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def to_input(u: float, v: float) -> tuple[float, float]:
    return u * SCALE + LEFT, v * SCALE + TOP


def apex_pixel(x: float, y: float, z: float) -> tuple[int, int]:
    u, v = to_input(*project(x, y, z))
    return int(u), int(v)


PILE_UV = project(CONE[0], CONE[1], CONE[3])
ROBOT_UV = project(ROBOT[0], ROBOT[1], ROBOT[2])


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pile_c = to_input(*PILE_UV)
    robot_c = to_input(*ROBOT_UV)
    pile_px = apex_pixel(CONE[0], CONE[1], CONE[3])
    robot_px = apex_pixel(ROBOT[0], ROBOT[1], ROBOT[2])
    boxes = [
        (*pile_c, 40.0, 40.0, 0, 1.0, pile_px),  # the pile
        (pile_c[0] + 2, pile_c[1] + 1, 40.0, 40.0, 0, 0.9, pile_px),  # a duplicate: NMS drops it
        (*robot_c, 36.0, 36.0, 1, 0.95, robot_px),  # the robot
        (100.0, 60.0, 30.0, 30.0, 0, 1.0, (100, 60)),  # grey floor: under the threshold
        (160.0, 20.0, 30.0, 30.0, 0, 1.0, (160, 20)),  # padding: 114/255 < 0.5
    ]
    return build_model(tmp_path_factory.mktemp("model") / "piles.onnx", boxes)


def test_letterbox_scales_pads_and_interpolates_like_ultralytics() -> None:
    image = np.zeros((H, W, 3), dtype=np.uint8)
    image[..., 0] = (np.arange(W) % 256)[None, :]  # a ramp along x, 0..255 repeated
    image[..., 1] = 200
    tensor, scale, (left, top) = letterbox(image, (IMGSZ, IMGSZ))
    assert tensor.shape == (1, 3, IMGSZ, IMGSZ) and tensor.dtype == np.float32
    assert (scale, left, top) == (SCALE, LEFT, TOP)
    grey = np.float32(114 / 255)
    assert np.all(tensor[0, :, :TOP] == grey) and np.all(tensor[0, :, TOP + 240 :] == grey)
    assert np.allclose(tensor[0, 1, TOP : TOP + 240], 200 / 255)
    # halving with centres aligned averages source columns 2i and 2i + 1 (inside one ramp)
    x = np.arange(10, 100)
    assert np.allclose(tensor[0, 0, TOP + 5, x] * 255, (2 * x + 0.5) % 256, atol=1e-3)


def test_nms_is_greedy_by_score_and_class_aware() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [20, 20, 30, 30]], float)
    scores = np.array([0.8, 0.9, 0.7, 0.6])
    classes = np.array([0, 0, 1, 0])
    # box 1 (0.9) suppresses box 0 (IoU 81/119 = 0.68); box 2 is another class; box 3 is apart
    assert nms(boxes, scores, classes, 0.45).tolist() == [1, 2, 3]
    assert nms(boxes, scores, classes, 0.7).tolist() == [1, 0, 2, 3]


def test_camera_image_puts_every_point_back_on_its_pixel(scan: Scan) -> None:
    image, index = camera_image(scan.cameras[0])
    assert image.shape == (H, W, 3)
    assert np.array_equal(index.ravel(), np.arange(H * W))  # deprojected row-major, all valid
    assert np.array_equal(image.reshape(-1, 3), scan.cameras[0].colors)


def test_model_boxes_after_decoding_threshold_and_nms(scan: Scan, model_path: Path) -> None:
    model = YoloModel(model_path)
    assert model.names == NAMES and model.imgsz == (IMGSZ, IMGSZ)
    image, _ = camera_image(scan.cameras[0])
    found = model.detect(image, confidence=0.5, iou=0.45)
    assert [(b.name, round(b.score, 6)) for b in found] == [("pile", 1.0), ("robot", 0.95)]
    pile, robot = found
    # back in image pixels: 40 input px = 80 image px around the projected apex
    assert pile.centre == pytest.approx(PILE_UV, abs=1e-3)
    assert (pile.x2 - pile.x1, pile.y2 - pile.y1) == pytest.approx((80.0, 80.0), abs=1e-3)
    assert robot.centre == pytest.approx(ROBOT_UV, abs=1e-3)


def test_an_input_padded_at_the_top_instead_of_centred_misses_both(
    scan: Scan, model_path: Path
) -> None:
    """The model is sensitive to the letterbox: the same scaled image without the centring
    shift puts the apexes 40 px off their pixels, and nothing passes the threshold."""
    model = YoloModel(model_path)
    image, _ = camera_image(scan.cameras[0])
    tensor = np.full((1, 3, IMGSZ, IMGSZ), 114 / 255, dtype=np.float32)
    tensor[0, :, :240, :] = image[::2, ::2].transpose(2, 0, 1) / 255
    (output,) = model.session.run(None, {model.input_name: tensor})
    assert len(decode(output, 0.5)[0]) == 0


def test_boxes_become_a_pile_and_a_robot_in_the_silo_frame(scan: Scan, model_path: Path) -> None:
    detection = DetectionConfig(onnx=OnnxDetectionConfig(model=model_path))
    result = analyse(scan, ReconstructionConfig(), detection)
    cone_volume = np.pi * CONE[2] ** 2 * CONE[3] / 3
    bump_volume = 2 * np.pi * ROBOT[2] * ROBOT[3] ** 2
    # the robot: the point under its box centre, reach = half the box diagonal at that depth
    (robot,) = result.robots
    expected = to_silo(cast(np.floor(ROBOT_UV[0]), np.floor(ROBOT_UV[1])))
    assert (robot.x, robot.y, robot.z) == pytest.approx(tuple(expected), abs=1e-4)
    assert robot.radius_m == pytest.approx(
        np.hypot(72, 72) / F * (CAMERA_Z - expected[2]) / 2, rel=1e-4
    )
    assert robot.confidence == pytest.approx(0.95)
    # its points are not grain: the volume is the cone's, not the cone's and the bump's
    plain = reconstruct(scan, ReconstructionConfig())
    assert plain.volume_m3 == pytest.approx(cone_volume + bump_volume, rel=0.03)
    assert result.reconstruction.volume_m3 == pytest.approx(cone_volume, rel=0.03)
    # both detectors find the cone; the geometric one no longer sees the robot as a pile
    by_detector = {p.detector: p for p in result.piles}
    assert sorted(by_detector) == ["geometric", "onnx"] and len(result.piles) == 2
    onnx_pile = by_detector["onnx"]
    assert onnx_pile.confidence == pytest.approx(1.0)
    assert onnx_pile.centroid == pytest.approx(CONE[:2], abs=0.02)
    assert onnx_pile.peak == pytest.approx(CONE[:2], abs=0.03)
    assert onnx_pile.peak_height_m == pytest.approx(CONE[3], abs=0.02)
    assert onnx_pile.volume_m3 == pytest.approx(cone_volume, rel=0.03)
    assert by_detector["geometric"].volume_m3 == pytest.approx(cone_volume, rel=0.03)
    summary = summarise(result, "2026-11-22T02:00:00Z", [], {}).to_json()
    assert summary["robots"][0]["camera"] == "top"


def test_a_model_without_class_names_is_refused(tmp_path: Path) -> None:
    path = build_model(tmp_path / "nonames.onnx", [(5, 5, 2, 2, 0, 1.0, (5, 5))], names=None)
    with pytest.raises(ModelError, match=r"nonames\.onnx: metadata has no 'names'"):
        YoloModel(path)


def test_a_model_with_the_wrong_output_shape_is_refused(tmp_path: Path) -> None:
    path = build_model(tmp_path / "seg.onnx", [(5, 5, 2, 2, 0, 1.0, (5, 5))], extra_rows=32)
    problem = r"seg\.onnx: output shape \[1, 38, 1\] is not \[1, 6, N\]"
    with pytest.raises(ModelError, match=problem):
        YoloModel(path)


def test_a_file_that_is_no_model_is_refused(tmp_path: Path, scan: Scan) -> None:
    path = tmp_path / "broken.onnx"
    path.write_bytes(b"not a model")
    with pytest.raises(ModelError, match=r"broken\.onnx: cannot load the ONNX model"):
        analyse(scan, ReconstructionConfig(), DetectionConfig(onnx=OnnxDetectionConfig(model=path)))


def test_onnx_config_keys() -> None:
    example = Path(__file__).parents[1] / "config" / "silo-agent.example.toml"
    text = example.read_text().replace("# [detection.onnx]", "[detection.onnx]")
    for key in ("model", "confidence", "iou", "pile_classes", "robot_classes", "cluster_radius_m"):
        text = text.replace(f"# {key} =", f"{key} =")
    config = Config.model_validate(tomllib.loads(text))
    assert config.detection.onnx == OnnxDetectionConfig(model=Path("/etc/silo-agent/piles.onnx"))
    with pytest.raises(ValidationError, match="both pile and robot: robot"):
        OnnxDetectionConfig(model=Path("m.onnx"), pile_classes=["pile", "robot"])
