"""The `--record` sink on its own (robotd/results/recorder.py): a stereo model's views on topics of
their names, a queue far shorter than the run loses no frame (the loop waits), an output no ROS 2
message carries is counted and the others recorded, names made ROS 2 tokens; read back with
rosbags."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader

from common import ros2_messages as rm
from common.image_input import ImageInputs
from common.partition import TensorSpec
from robotd.frame_path.frame import FrameResult
from robotd.results.recorder import McapRecorder, name_token, record_prefix
from tests.unit.bag_support import photo_frames

H, W = 24, 32


def result(n: int, feeds: dict[str, np.ndarray], outputs: dict[str, np.ndarray]) -> FrameResult:
    return FrameResult(n, feeds, outputs, None, "robot", False, 1_700_000_000_000_000_000 + n)  # type: ignore[arg-type]


def topics_of(path: Path) -> dict[str, list[Any]]:
    with Reader(path) as reader:
        out: dict[str, list[Any]] = {}
        for connection, _, raw in reader.messages():
            out.setdefault(connection.topic, []).append(
                rm.typestore().deserialize_cdr(raw, connection.msgtype)
            )
    return out


def test_a_stereo_models_views_are_recorded_on_topics_of_their_names(tmp_path: Path) -> None:
    inputs = ImageInputs(
        [TensorSpec("left", "float32", (1, 3, H, W)), TensorSpec("right", "float32", (1, 3, H, W))]
    )
    left, right = photo_frames(2, H, W)
    recorder = McapRecorder(tmp_path / "pair.mcap", "rover.2", inputs)
    feeds = inputs.feeds({"left": left, "right": right})
    recorder.publish(result(0, feeds, {"disparity": np.ones((1, 1, H, W), np.float32)}))
    recorder.close()
    topics = topics_of(tmp_path / "pair.mcap")
    prefix = "/elasticfog/rover_2"
    assert sorted(topics) == [
        f"{prefix}/disparity",
        f"{prefix}/disparity/image",
        f"{prefix}/input/left/compressed",
        f"{prefix}/input/right/compressed",
    ]
    decoded = rm.decode_compressed_image(
        rm.typestore().serialize_cdr(
            topics[f"{prefix}/input/right/compressed"][0], rm.MessageType.COMPRESSED_IMAGE.value
        )
    )
    assert np.abs(decoded.image.astype(int) - right.astype(int)).mean() < 8  # JPEG of the view


def test_a_short_queue_makes_the_loop_wait_and_loses_nothing(tmp_path: Path) -> None:
    inputs = ImageInputs([TensorSpec("image", "uint8", (1, H, W, 3))])
    recorder = McapRecorder(tmp_path / "run", "r", inputs, queue_frames=1)
    frame = photo_frames(1, H, W)[0]
    for n in range(40):
        recorder.publish(result(n, inputs.feeds(frame), {"out.1": np.full((1, 3), n, np.float32)}))
    recorder.close()
    assert recorder.recorded == 40 and recorder.lost == 0
    arrays = topics_of(tmp_path / "run")["/elasticfog/r/out_1"]
    assert [int(a.data[0]) for a in arrays] == list(range(40))


def test_an_output_no_message_carries_is_counted_and_the_rest_recorded(tmp_path: Path) -> None:
    inputs = ImageInputs([TensorSpec("image", "float32", (1, 3, H, W))])
    recorder = McapRecorder(tmp_path / "run.mcap", "r", inputs)
    feeds = inputs.feeds(photo_frames(1, H, W)[0])
    recorder.publish(result(0, feeds, {"label": np.array(["cat"]), "score": np.ones((1, 2))}))
    recorder.close()
    assert recorder.recorded == 1 and recorder.skipped_messages == 1
    assert "/elasticfog/r/score" in topics_of(tmp_path / "run.mcap")


def test_names_become_ros2_tokens_and_the_prefix_follows_the_results_topics() -> None:
    assert name_token("output.1") == "output_1"
    assert name_token("3d") == "_3d"
    assert record_prefix("robot-1", None) == "/elasticfog/robot_1"
    assert record_prefix("robot-1", "/robot1/results") == "/robot1/results"
    assert record_prefix("robot-1", "robot1/results/") == "/robot1/results"
