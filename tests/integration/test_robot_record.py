"""`--record`: the robot daemon (real Zenoh session on loopback) writes each applied frame's input
and outputs to MCAP, read back here by readers this project did not write (the `mcap` package's
reader with `mcap-ros2-support`'s decoder, and rosbags): as many frames as the run summary
counts, each output equal to what the robot applied, the input image the model saw, the capture
stamps in the headers; an image-shaped output also as a 32FC1 Image; an existing path refused at
start."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnx
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from onnx import TensorProto, numpy_helper

from common.errors import UserError
from common.image_input import ImageInputs
from common.partition import TensorSpec
from robotd.daemon import FrameResult, RobotDaemon, RobotOptions
from tests.integration.conftest import Router
from tests.integration.test_robotd import DEPLOYMENT, ROBOT, fleet_config
from tests.unit.test_partition import make_model, node, save, vi

FRAMES = 5
SIDE = 16
CLASSES = 4
WAIT_S = 0.2
# JPEG at quality 90 of the model's 16×16 input: the recorded image is close to what it saw.
MIN_INPUT_PSNR_DB = 28.0
PREFIX = "/robot1/results"


def depth_model() -> onnx.ModelProto:
    """image[1,3,16,16] → Conv → `depth` [1,1,16,16] → pool → Gemm → `logits` [1,4]: one
    image-shaped output and one vector."""
    rng = np.random.default_rng(1)

    def weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
        return numpy_helper.from_array((rng.standard_normal(shape) * 0.5).astype(np.float32), name)

    return make_model(
        [
            node("Conv", ["image", "w1", "b1"], ["depth"], pads=[1, 1, 1, 1]),
            node("GlobalAveragePool", ["depth"], ["g"]),
            node("Flatten", ["g"], ["f"]),
            node("Gemm", ["f", "w2", "b2"], ["logits"]),
        ],
        [vi("image", [1, 3, SIDE, SIDE], TensorProto.FLOAT)],
        [
            vi("depth", [1, 1, SIDE, SIDE], TensorProto.FLOAT),
            vi("logits", [1, CLASSES], TensorProto.FLOAT),
        ],
        [
            weight("w1", (1, 3, 3, 3)),
            weight("b1", (1,)),
            weight("w2", (1, CLASSES)),
            weight("b2", (CLASSES,)),
        ],
    )


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save(depth_model(), tmp_path_factory.mktemp("model") / "depth.onnx")


def run_recording(
    endpoint: str, model_file: Path, record: Path, *, results_ros2: str | None = None
) -> tuple[RobotDaemon, list[FrameResult]]:
    robot: dict[str, Any] = {"role": "robot", "listen": ["tcp/127.0.0.1:0"]}
    if results_ros2 is not None:
        robot["results"] = {"ros2": results_ros2}
    machines = {DEPLOYMENT: {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]}, ROBOT: robot}
    cfg = fleet_config(endpoint, model_file, policy={"kind": "robot"}, machines=machines)
    options = RobotOptions(
        source="photo",
        frames=FRAMES,
        record=record,
        registry_wait_s=WAIT_S,
        route_wait_s=WAIT_S,
    )
    results: list[FrameResult] = []
    daemon = RobotDaemon(cfg, ROBOT, options, on_result=results.append)
    assert daemon.run() == 0
    return daemon, results


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 99.0 if mse == 0 else 10 * np.log10(255.0**2 / mse)


def test_a_recording_holds_every_frame_as_ros2_messages_for_independent_readers(
    zenoh_router: Router, model_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run.mcap"
    daemon, results = run_recording(zenoh_router.endpoint, model_file, out, results_ros2=PREFIX)
    assert out.is_file() and not list(tmp_path.glob(".*partial"))
    assert daemon.summary.frames == FRAMES == len(results)

    by_topic: dict[str, list[Any]] = {}
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append(decoded)
    assert sorted(by_topic) == sorted(
        [
            f"{PREFIX}/input/compressed",
            f"{PREFIX}/logits",
            f"{PREFIX}/depth",
            f"{PREFIX}/depth/image",
        ]
    )
    assert all(len(messages) == daemon.summary.frames for messages in by_topic.values())

    adapter = ImageInputs([TensorSpec("image", "float32", (1, 3, SIDE, SIDE))]).adapters["image"]
    for result, logits, depth, image, frame in zip(
        results,
        by_topic[f"{PREFIX}/logits"],
        by_topic[f"{PREFIX}/depth"],
        by_topic[f"{PREFIX}/depth/image"],
        by_topic[f"{PREFIX}/input/compressed"],
        strict=True,
    ):
        np.testing.assert_array_equal(
            np.asarray(logits.data, np.float32), result.outputs["logits"].reshape(-1)
        )
        assert [d.label for d in logits.layout.dim] == ["axis0", "axis1"]
        assert [d.size for d in depth.layout.dim] == [1, 1, SIDE, SIDE]
        msg = image
        assert (msg.encoding, msg.height, msg.width, msg.step) == ("32FC1", SIDE, SIDE, 4 * SIDE)
        pixels = np.frombuffer(bytes(msg.data), "<f4").reshape(SIDE, SIDE)
        np.testing.assert_array_equal(pixels, result.outputs["depth"].reshape(SIDE, SIDE))
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert stamp == result.stamp_ns
        jpeg = frame
        assert jpeg.format == "jpeg"
        decoded = cv2.imdecode(np.frombuffer(bytes(jpeg.data), np.uint8), cv2.IMREAD_COLOR)
        assert psnr_db(decoded, adapter.image(result.feeds["image"])) > MIN_INPUT_PSNR_DB

    # The file's summary (its statistics and schemas) says the same.
    with out.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 4 * FRAMES
    schemas = {s.name for s in summary.schemas.values()}
    assert schemas == {
        "sensor_msgs/msg/CompressedImage",
        "std_msgs/msg/Float32MultiArray",
        "sensor_msgs/msg/Image",
    }

    # And rosbags reads it as a rosbag2 file.
    from rosbags.rosbag2 import Reader

    with Reader(out) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts == {topic: FRAMES for topic in by_topic}


def test_a_recording_to_a_folder_is_a_rosbag2_bag_under_the_default_prefix(
    zenoh_router: Router, model_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run_bag"
    daemon, _ = run_recording(zenoh_router.endpoint, model_file, out)
    assert (out / "metadata.yaml").is_file()
    from rosbags.rosbag2 import Reader

    with Reader(out) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts[f"/elasticfog/{ROBOT.replace('-', '_')}/logits"] == daemon.summary.frames


def test_an_existing_path_is_refused_before_anything_starts(
    zenoh_router: Router, model_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run.mcap"
    out.write_bytes(b"keep me")
    with pytest.raises(UserError, match="exists already; not overwriting"):
        RobotOptions(record=out).check()
    with pytest.raises(UserError, match="does not exist"):
        RobotOptions(record=tmp_path / "no" / "run.mcap").check()
    assert out.read_bytes() == b"keep me"
