"""The site's YOLO robot class in live maps: a model built here finds the robot in the moving
scene's colour frames, and the live map holds the robot's cells from its boxes alone.

The depth rule is made blind (`robot_min_height_m` above the robot's 0.3 m), so whatever holds
the robot's footprint comes from the model. The model computes its box from the image: the
bounding box of the pixels bluer than red (the robot's grey; wheat is far redder, the
letterbox padding is neutral), scored 1 when there are any, so it fires where the robot is.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from silo_agent.config import Config, parse_config
from silo_agent.grid.grid import Grid
from silo_agent.live.map import DepthFrame, LiveMap, LiveUpdate
from silo_agent.live.model import LiveRobotModel
from silo_agent.live.session import LiveSession
from silo_agent.sim.robot import ROBOT_SIZE_M, RobotPose, RobotRig
from silo_agent.telemetry.heightmap_codec import decode_live_heightmap
from tests.support.robot import robot_rig

IMGSZ = 320
TIMES = (0.0, 1.5, 3.0, 4.5, 6.0, 7.5)  # on the flat, then up the first heap
BLUER_THAN_RED = 0.005  # the robot's grey is 8/255 bluer at the darkest shading: 0.011
BLIND_DEPTH_M = 1.0  # the depth rule's threshold, above the robot's height


def build_robot_model(path: Path) -> Path:
    """Output [1, 5, 1]: the box around the pixels bluer than red, class 0 "robot" scored 1 when
    there are any (else 0: no detection)."""
    far = 1.0e4
    grid_y, grid_x = np.mgrid[0:IMGSZ, 0:IMGSZ].astype(np.float32)
    const = helper.make_tensor
    nodes = [
        helper.make_node("Gather", ["images", "red_index"], ["red"], axis=1),
        helper.make_node("Gather", ["images", "blue_index"], ["blue"], axis=1),
        helper.make_node("Sub", ["blue", "red"], ["bluer"]),
        helper.make_node("Greater", ["bluer", "threshold"], ["mask"]),
        helper.make_node("Cast", ["mask"], ["maskf"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMax", ["maskf"], ["score"], axes=[0, 1, 2, 3], keepdims=0),
        helper.make_node("Where", ["mask", "xs", "far"], ["x_low"]),
        helper.make_node("Where", ["mask", "xs", "near"], ["x_high"]),
        helper.make_node("Where", ["mask", "ys", "far"], ["y_low"]),
        helper.make_node("Where", ["mask", "ys", "near"], ["y_high"]),
        helper.make_node("ReduceMin", ["x_low"], ["x1"], axes=[0, 1, 2, 3], keepdims=0),
        helper.make_node("ReduceMax", ["x_high"], ["x2m"], axes=[0, 1, 2, 3], keepdims=0),
        helper.make_node("ReduceMin", ["y_low"], ["y1"], axes=[0, 1, 2, 3], keepdims=0),
        helper.make_node("ReduceMax", ["y_high"], ["y2m"], axes=[0, 1, 2, 3], keepdims=0),
        helper.make_node("Add", ["x2m", "one"], ["x2"]),  # a pixel spans [i, i + 1)
        helper.make_node("Add", ["y2m", "one"], ["y2"]),
        helper.make_node("Add", ["x1", "x2"], ["x_sum"]),
        helper.make_node("Add", ["y1", "y2"], ["y_sum"]),
        helper.make_node("Mul", ["x_sum", "half"], ["cx"]),
        helper.make_node("Mul", ["y_sum", "half"], ["cy"]),
        helper.make_node("Sub", ["x2", "x1"], ["w"]),
        helper.make_node("Sub", ["y2", "y1"], ["h"]),
        *[
            helper.make_node("Reshape", [name, "one_shape"], [f"{name}_1"])
            for name in ("cx", "cy", "w", "h", "score")
        ],
        helper.make_node("Concat", ["cx_1", "cy_1", "w_1", "h_1", "score_1"], ["column"], axis=0),
        helper.make_node("Reshape", ["column", "out_shape"], ["output0"]),
    ]
    inits = [
        const("red_index", TensorProto.INT64, [1], [0]),
        const("blue_index", TensorProto.INT64, [1], [2]),
        const("threshold", TensorProto.FLOAT, [], [BLUER_THAN_RED]),
        const("xs", TensorProto.FLOAT, [1, 1, IMGSZ, IMGSZ], grid_x.ravel().tolist()),
        const("ys", TensorProto.FLOAT, [1, 1, IMGSZ, IMGSZ], grid_y.ravel().tolist()),
        const("far", TensorProto.FLOAT, [], [far]),
        const("near", TensorProto.FLOAT, [], [-far]),
        const("one", TensorProto.FLOAT, [], [1.0]),
        const("half", TensorProto.FLOAT, [], [0.5]),
        const("one_shape", TensorProto.INT64, [1], [1]),
        const("out_shape", TensorProto.INT64, [3], [1, 5, 1]),
    ]
    graph = helper.make_graph(
        nodes,
        "robot-test",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, IMGSZ, IMGSZ])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 5, 1])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"imgsz": f"[{IMGSZ}, {IMGSZ}]", "names": repr({0: "robot"})})
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def config_for(rig: RobotRig, model: Path | None) -> Config:
    site = rig.robot.base.site
    data = {
        "silo": {"id": "live-model", "region": site.region.tolist(), "ceiling_z": site.ceiling_z},
        "cameras": [
            {
                "serial": v.serial,
                "source": "sim",
                "view": v.key,
                "color": True,
                "width": v.intrinsics.width,
                "height": v.intrinsics.height,
            }
            for v in rig.views
        ],
        "live": {"robot_min_height_m": BLIND_DEPTH_M, "model_rate_hz": 10},
    }
    if model is not None:
        data["detection"] = {"onnx": {"model": str(model)}}
    return parse_config(data, "test")


@dataclass
class Step:
    t: float
    pose: RobotPose
    truth: np.ndarray
    with_model: LiveUpdate
    depth_only: LiveUpdate


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Grid, list[Step]]:
    rig = robot_rig(width=424, height=240)
    model_path = build_robot_model(tmp_path_factory.mktemp("model") / "robot.onnx")
    config = config_for(rig, model_path)
    site = rig.robot.base.site
    grid = Grid.over(site.region, config.live.grid_step_m)
    model = LiveRobotModel(config)
    with_model = LiveMap(grid, config.live, site.ceiling_z)
    depth_only = LiveMap(grid, config.live, site.ceiling_z)
    xs, ys = grid.centres()
    steps = []
    for index, t in enumerate(TIMES):
        rendered = rig.frames(t, index, color=True)
        frames = [
            DepthFrame.rendered(v.serial, f, v.nominal, f.color)
            for v, f in zip(rig.views, rendered, strict=True)
        ]
        seen = model.robots(frames, with_model, t)
        truth = rig.robot.height(t)(xs, ys)
        steps.append(
            Step(
                t,
                rig.robot.pose(t),
                truth,
                with_model.update(frames, t, seen),
                depth_only.update(frames, t),
            )
        )
    return grid, steps


def test_the_model_alone_holds_the_robot_out_of_the_map(run):
    """Held cells keep the grain's last value: no robot-shaped bump. One frame of these
    424x240 cameras every 1.5 s leaves the held values a few cm of noise, and cells in the
    robot's shadow since the start take a lower neighbour's; the robot's top would stand
    0.3 m high."""
    grid, steps = run
    xs, ys = grid.centres()
    for step in steps:
        under = step.pose.footprint(xs, ys)
        assert step.with_model.held[under].all(), f"t={step.t}: footprint not all held"
        excess = step.with_model.heightmap.heights[under] - step.truth[under]
        # (< 2 cm before the simulator's frames had mixed pixels along the robot's rim: those
        # near the rim stay, and add a few mm)
        assert float(np.mean(excess)) < 0.025, f"t={step.t}: {np.mean(excess):.3f} m"
        assert float(np.max(excess)) < ROBOT_SIZE_M[2] / 3, f"t={step.t}: {np.max(excess):.3f}"
        # the model's own sighting (a camera that sees a sliver may add a small one elsewhere)
        robot = max(step.with_model.robots, key=lambda r: r.cells)
        assert robot.by == "model"
        assert np.hypot(robot.x - step.pose.x, robot.y - step.pose.y) < 0.2, f"t={step.t}"
        assert robot.top_z == pytest.approx(step.pose.z + ROBOT_SIZE_M[2], abs=0.05)


def test_without_the_model_the_blind_depth_rule_reads_the_robot_as_grain(run):
    """The same frames and settings without the model: nothing is held, the robot's top
    stands in the map (so the test above fails if the model's path is broken)."""
    grid, steps = run
    xs, ys = grid.centres()
    for step in steps[1:]:
        under = step.pose.footprint(xs, ys)
        assert not step.depth_only.held.any() and step.depth_only.robots == []
        excess = step.depth_only.heightmap.heights[under] - step.truth[under]
        assert float(np.mean(excess)) > ROBOT_SIZE_M[2] / 3, f"t={step.t}"  # vs < 0.02 above


def session_run(config: Config, maps: int) -> tuple[list[bytes], str]:
    """A live session until `maps` maps are published or it ends: the payloads, why it ended."""
    payloads: list[bytes] = []
    ended: list[str] = []
    done = threading.Event()

    def publish(payload: bytes, _period: float) -> None:
        payloads.append(payload)
        if len(payloads) >= maps:
            done.set()

    def on_end(reason: str) -> None:
        ended.append(reason)
        done.set()

    session = LiveSession(config, "s1", 2.0, 120.0, publish, on_end)
    session.start()
    try:
        assert done.wait(120), "no map and no end within 120 s"
    finally:
        session.stop("test over")
    return payloads, ended[0]


@pytest.fixture(scope="module")
def small_rig() -> RobotRig:
    return robot_rig(width=424, height=240)


def test_a_session_asks_sim_cameras_for_colour_and_publishes_the_model_robot(
    small_rig, tmp_path: Path
) -> None:
    model = build_robot_model(tmp_path / "robot.onnx")
    payloads, _ = session_run(config_for(small_rig, model), 2)
    for payload in payloads:
        robots = decode_live_heightmap(payload).meta["robots"]
        assert robots and max(robots, key=lambda r: r["cells"])["by"] == "model"


def test_a_model_that_cannot_load_ends_the_session_naming_the_file(
    small_rig, tmp_path: Path
) -> None:
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"not a model")
    payloads, reason = session_run(config_for(small_rig, broken), 1)
    assert payloads == []
    assert reason.startswith(f"cannot load the robot model: {broken}: cannot load the ONNX")


def test_recordings_with_colour_give_it_aligned_only_on_the_maps_the_model_is_due(
    small_rig, tmp_path: Path
) -> None:
    """Real librealsense playback of `.db3` files holding depth and colour: a frame asked
    with colour carries the recorded image, one asked without carries none, and the model
    finds the robot in them as in the simulator's frames."""
    from silo_agent.capture.recording import write_recording
    from silo_agent.live.session import open_source

    times = (0.0, 0.5)
    rendered = [small_rig.frames(t, i, color=True) for i, t in enumerate(times)]
    # The recordings end with copies of the last scene: about once in forty runs on two busy
    # cores, a playback ending on the frame the second read wants gave that read no depth
    # frame within 10 s (how librealsense's syncer meets a recording's end); a live camera
    # always sends another, and the copies show the same scene.
    recorded = [*rendered, rendered[-1], rendered[-1]]
    for k, view in enumerate(small_rig.views):
        write_recording(
            tmp_path / f"{view.serial}.db3",
            view.serial,
            view.intrinsics.to_json(),
            [per_time[k].depth for per_time in recorded],
            0.001,
            30,
            color_frames=[per_time[k].color for per_time in recorded],
        )
    sim = config_for(small_rig, build_robot_model(tmp_path / "robot.onnx"))
    data = sim.model_dump(mode="json", exclude_none=True)
    data["cameras"] = [
        {
            "serial": v.serial,
            "source": "playback",
            "color": True,
            "playback": str(tmp_path / f"{v.serial}.db3"),
            "extrinsic": v.nominal.tolist(),
            # a bound, not a wait: four depth + colour playbacks opened at once took over 2 s
            # to give their first frame twice in a full suite on 2 busy cores
            "timeout_s": 10.0,
            "spatial_filter": False,
        }
        for v in small_rig.views
    ]
    config = parse_config(data, "test")
    site = small_rig.robot.base.site
    live = LiveMap(Grid.over(site.region, config.live.grid_step_m), config.live, site.ceiling_z)
    model = LiveRobotModel(config)
    source = open_source(config)
    try:
        plain = source.frames(times[0], color=False)
        assert all(f.color is None for f in plain)
        coloured = source.frames(times[1], color=True)
    finally:
        source.close()
    for frame, recorded in zip(coloured, rendered[1], strict=True):
        np.testing.assert_array_equal(frame.depth, recorded.depth)
        # align maps colour through depth: none where it is 0, and at depth edges a pixel
        # may take its neighbour's (0.07 % here)
        valid = recorded.depth > 0
        assert np.all(frame.color == recorded.color, axis=-1)[valid].mean() > 0.99
    update = live.update(coloured, times[1], model.robots(coloured, live, times[1]))
    robot = max(update.robots, key=lambda r: r.cells)  # the cameras' sightings merged
    pose = small_rig.robot.pose(times[1])
    assert robot.by == "model"
    assert np.hypot(robot.x - pose.x, robot.y - pose.y) < 0.2


def test_the_model_runs_at_most_model_rate_hz_and_maps_between_reuse_its_sightings(
    small_rig, tmp_path: Path
) -> None:
    config = config_for(small_rig, build_robot_model(tmp_path / "robot.onnx"))
    config = config.model_copy(
        update={"live": config.live.model_copy(update={"model_rate_hz": 1.0})}
    )
    site = small_rig.robot.base.site
    live = LiveMap(Grid.over(site.region, config.live.grid_step_m), config.live, site.ceiling_z)
    model = LiveRobotModel(config)
    frames = [
        DepthFrame.rendered(v.serial, f, v.nominal, f.color)
        for v, f in zip(small_rig.views, small_rig.frames(0.0, 0, color=True), strict=True)
    ]
    # the same frames with the robot painted the grain's colour: a run finds nothing there
    wheat = np.array(small_rig.robot.base.grain.rgb, dtype=np.uint8)
    no_robot = [replace(f, color=np.broadcast_to(wheat, f.color.shape).copy()) for f in frames]
    assert model.due(0.0)
    first = model.robots(frames, live, 0.0)
    assert first
    assert not model.due(0.9)
    assert model.robots(no_robot, live, 0.9) == first  # not run: the last sightings
    assert model.due(1.0)
    assert model.robots(no_robot, live, 1.0) == []  # run, and the robot is gone
