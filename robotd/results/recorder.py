"""`elasticfog robot ... --record OUT.mcap`: each applied frame's input and result in an MCAP file.

Why: a run's frames and answers, kept in the format robots already replay and inspect: `ros2 bag
play OUT.mcap` republishes them, Foxglove shows them, and any MCAP reader (the `mcap` and
`mcap-ros2-support` packages, rosbags) reads them back, so a run can be checked or compared
later without elasticfog.

What: a result sink (`robotd.results.sinks`) that writes, for every applied frame, with rosbags'
rosbag2 writer (MCAP storage, messages built by `common.ros2_messages`), all with the frame's
capture stamp in their headers and the time the result was applied as their record time:
- the model's input as the model saw it (`ImageInput.image`: the frame at the model's size), a
  JPEG `sensor_msgs/msg/CompressedImage` on `<prefix>/input/compressed` (a model with several
  image inputs, a stereo pair: `<prefix>/input/<input name>/compressed`);
- each output as `std_msgs/msg/Float32MultiArray` on `<prefix>/<output name>` and, for an output
  of shape 1×1×H×W or H×W, also as a 32FC1 `sensor_msgs/msg/Image` on `<prefix>/<output
  name>/image`: the topics and messages of the robot's ROS 2 results (`results: {ros2: ...}`).
`<prefix>` is the robot's `results.ros2` where the fleet file sets one, else
`/elasticfog/<robot id>`; names are made ROS 2 name tokens (`output.1` -> `output_1`).

A path ending in `.mcap` is one MCAP file, written as a rosbag2 folder beside it
(`.<name>.partial`) and moved into place when the recording closes; any other path is a rosbag2
folder with MCAP storage. An existing path is refused at start. Frames are written by a thread of
the recorder's (JPEG encoding and file writes stay off the frame loop), through a queue of
`RECORD_QUEUE_FRAMES` frames: a full queue makes the loop wait rather than drop a frame. The
recording is flushed and closed at shutdown (SIGINT, SIGTERM, `--frames`, the end of a bag). A
write that fails (a full disk) stops the recording with one line; the robot goes on.
"""

from __future__ import annotations

import logging
import queue
import re
import shutil
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from common.errors import UserError
from common.image_input import ImageInputs
from common.ros2_messages import (
    Header,
    MessageType,
    Ros2MessageError,
    encode_compressed_image,
    encode_float32_multi_array,
    encode_image_32fc1,
    is_image_shaped,
    typestore,
)

if TYPE_CHECKING:
    from robotd.frame_path.frame import FrameResult

log = logging.getLogger("robotd")

# Frames waiting for the writer thread at most: about a second of a 30 fps camera.
RECORD_QUEUE_FRAMES = 32
MCAP_SUFFIX = ".mcap"
DEFAULT_PREFIX = "/elasticfog"
INPUT_TOPIC = "input"
COMPRESSED_SUFFIX = "compressed"
IMAGE_SUFFIX = "image"
# The frame id of the recorded input images and image-shaped outputs.
FRAME_ID = "camera"


def record_prefix(robot: str, results_ros2: str | None) -> str:
    """Where a robot's recording puts its topics: its ROS 2 results prefix, else
    `/elasticfog/<robot id as a name token>`."""
    if results_ros2:
        return "/" + results_ros2.strip("/")
    return f"{DEFAULT_PREFIX}/{name_token(robot)}"


def name_token(name: str) -> str:
    """`name` as one ROS 2 name token: characters other than letters, digits and '_' become '_',
    and a leading digit gets a '_' before it."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    return "_" + token if token[0].isdigit() else token


def check_record_path(path: Path) -> Path:
    """`path` if a recording can be made there; UserError (before anything starts) otherwise."""
    if path.exists():
        raise UserError(f"--record: {path} exists already; not overwriting it")
    if not path.parent.is_dir():
        raise UserError(f"--record: folder {path.parent} does not exist")
    partial = _partial_folder(path)
    if path.suffix == MCAP_SUFFIX and partial.exists():
        raise UserError(f"--record: {partial} (an unfinished recording) is in the way")
    return path


def _partial_folder(path: Path) -> Path:
    return path.with_name(f".{path.name}.partial")


class McapRecorder:
    """The `--record` result sink (see the module docstring)."""

    def __init__(
        self,
        path: Path,
        robot: str,
        inputs: ImageInputs,
        *,
        results_ros2: str | None = None,
        queue_frames: int = RECORD_QUEUE_FRAMES,
    ) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path = check_record_path(Path(path))
        self.prefix = record_prefix(robot, results_ros2)
        self.inputs = inputs
        self.recorded = 0
        self.lost = 0
        self.skipped_messages = 0
        self._folder = _partial_folder(self.path) if self.path.suffix == MCAP_SUFFIX else self.path
        self._writer = Writer(
            self._folder, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP
        )
        try:
            self._writer.open()
        except Exception as exc:  # WriterError, OSError: the folder cannot be made
            raise UserError(f"--record: cannot write {self.path}: {exc}") from None
        self._connections: dict[str, Any] = {}
        self._input_topics = self._inputs_topics(inputs)
        self._failed: str | None = None
        self._queue: queue.Queue[tuple[int, FrameResult] | None] = queue.Queue(queue_frames)
        self._thread = threading.Thread(target=self._run, name=f"record-{robot}", daemon=True)
        self._thread.start()

    def _inputs_topics(self, inputs: ImageInputs) -> dict[str, str]:
        if len(inputs.names) == 1:
            return {inputs.names[0]: f"{self.prefix}/{INPUT_TOPIC}/{COMPRESSED_SUFFIX}"}
        return {
            name: f"{self.prefix}/{INPUT_TOPIC}/{name_token(name)}/{COMPRESSED_SUFFIX}"
            for name in inputs.names
        }

    # -- the sink ------------------------------------------------------------------------------
    def publish(self, result: FrameResult) -> None:
        """Queue the frame for the writer (waits while the queue is full: nothing is dropped)."""
        self._queue.put((time.time_ns(), result))

    def close(self) -> None:
        """Write what is queued, close the file and put it in place."""
        self._queue.put(None)
        self._thread.join()
        self._writer.close()
        if self._folder != self.path:
            (stored,) = self._folder.glob(f"*{MCAP_SUFFIX}")
            stored.replace(self.path)
            shutil.rmtree(self._folder)
        log.info(
            "recorded %d frames to %s%s%s",
            self.recorded,
            self.path,
            f" ({self.lost} not recorded: {self._failed})" if self.lost else "",
            f" ({self.skipped_messages} messages not encodable)" if self.skipped_messages else "",
        )

    # -- the writer thread ----------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._failed is not None:
                self.lost += 1
                continue
            try:
                self._write(*item)
            except Exception as exc:  # a full disk, a closed file: the robot goes on
                self._failed = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
                self.lost += 1
                log.error(
                    "recording to %s stopped after %d frames (%s); the robot goes on",
                    self.path,
                    self.recorded,
                    self._failed,
                )

    def _write(self, log_ns: int, result: FrameResult) -> None:
        header = Header(result.stamp_ns, FRAME_ID)
        messages: list[tuple[str, MessageType, bytes]] = []
        for name, feed in result.feeds.items():
            adapter = self.inputs.adapters.get(name)
            if adapter is not None:
                frame = adapter.image(feed)
                messages.append(
                    (
                        self._input_topics[name],
                        MessageType.COMPRESSED_IMAGE,
                        encode_compressed_image(frame, header),
                    )
                )
        for name, value in result.outputs.items():
            topic = f"{self.prefix}/{name_token(name)}"
            try:
                messages.append(
                    (topic, MessageType.FLOAT32_MULTI_ARRAY, encode_float32_multi_array(value))
                )
                if is_image_shaped(value.shape):
                    messages.append(
                        (
                            f"{topic}/{IMAGE_SUFFIX}",
                            MessageType.IMAGE,
                            encode_image_32fc1(value, header),
                        )
                    )
            except Ros2MessageError as exc:  # an output no ROS 2 message carries (not numeric)
                self.skipped_messages += 1
                log.debug("recording: output %s of frame %d: %s", name, result.frame, exc)
        for topic, msgtype, payload in messages:
            self._writer.write(self._connection(topic, msgtype), log_ns, payload)
        self.recorded += 1

    def _connection(self, topic: str, msgtype: MessageType) -> Any:
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msgtype.value, typestore=typestore())
            self._connections[topic] = connection
        return connection
