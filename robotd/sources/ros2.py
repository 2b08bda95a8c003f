"""`ros2:<topic>[,type=image|compressed][,domain=<id>]`: frames from a ROS 2 camera topic over
rmw_zenoh, with no ROS installed (a stereo camera's two topics: `robotd.sources.ros2_stereo`).

The robot's node (`robotd.ros2_node`: on the robot's ROS 2 session when `ros2.endpoint` is set,
else on its fleet session) subscribes to the topic whatever its type and hash
(`<domain>/<topic>/*/*`) and announces the subscription (MS token) with the type it reads:
`sensor_msgs/msg/Image` (rgb8, bgr8, mono8, rgba8, bgra8) or `sensor_msgs/msg/CompressedImage`
(JPEG, PNG), its RIHS01 hash from rosbags' Jazzy type store. Listening past the type lets a
publisher of another type, or of the same type with another hash (another ROS distribution's
definition), be named in the log instead of never heard. It also follows the camera's
`sensor_msgs/msg/CameraInfo` on the sibling topic (`/camera/image_raw` ->
`/camera/camera_info`), when one is published: the results' CameraInfo of the model's view is
the camera's, cropped and scaled.

Camera semantics, as the `zenoh` source's (`robotd.sources.newest_frame`): the frame loop always
takes the newest message; one that arrives while another waits replaces it and the replaced one is
counted (`dropped_stale`, in each frame's telemetry and the run summary). Messages are decoded
when the loop takes them (`common.ros2_messages`), so frames dropped cost no decoding, and fitted
to the model's input size as the photo source frames its photographs
(`robotd.sources.frame_sources.fit_frame`: the largest centred rectangle of the model's aspect,
scaled). The header stamp is the frame's capture stamp (`last_stamp_ns`); the header, the
camera image's size and the CameraInfo are remembered for the results
(`robotd.ros2_node.remember_frame`).

Bad input (a wrong type or type hash, truncated CDR, an unknown encoding, an empty image, bytes
that do not decode, a CameraInfo without a focal length) is one throttled line naming it,
counted by error code as the `zenoh` source's (`rejected_frames`, in the run summary); the loop
waits for the next message and the daemon keeps serving. The counts by error name are logged
when the source closes.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from common import rmw_zenoh
from common.ros2_messages import (
    CameraInfo,
    MessageType,
    Ros2MessageError,
    decode_camera_info,
    decode_frame,
    typestore,
)
from common.source_spec import Ros2FrameType, Ros2Spec
from common.throttled_log import ThrottledLog
from common.wire.errors import ErrorCode
from robotd.ros2_node import InputFrame, Ros2Node, acquire_robot_node, remember_frame
from robotd.sources.frame_sources import EndOfStream, FrameSource, fit_frame
from robotd.sources.newest_frame import NewestFrame

if TYPE_CHECKING:
    import zenoh

    from robotd.ros2_node import Ros2Subscription
    from robotd.sources.frame_sources import SourceSession

log = logging.getLogger("robotd.ros2")

FRAME_MESSAGES = {
    Ros2FrameType.IMAGE: MessageType.IMAGE,
    Ros2FrameType.COMPRESSED: MessageType.COMPRESSED_IMAGE,
}


class WrongTopicType(Ros2MessageError):
    """A message on the topic of another type than the source reads."""

    code = ErrorCode.BAD_VALUE


class WrongTypeHash(Ros2MessageError):
    """A message of the right type name whose RIHS01 hash differs (another definition of it,
    as a message of another schema version)."""

    code = ErrorCode.SCHEMA_VERSION


class Refusals:
    """Messages a source refused: by error name (the log's words) and by error code (the run
    summary's `rejected_frames`), each one a throttled line."""

    def __init__(self, description: Callable[[], str]) -> None:
        self.by_name: Counter[str] = Counter()
        self.by_code: Counter[str] = Counter()
        self._description = description
        self._throttled = ThrottledLog(log, label=description)

    def refuse(self, exc: Ros2MessageError, what: str = "message") -> None:
        name = type(exc).__name__
        self.by_name[name] += 1
        self.by_code[exc.code.value] += 1
        self._throttled.warning("%s: %s refused: %s: %s", self._description(), what, name, exc)

    def unexpected(self, what: str) -> None:
        """An error that is not a named refusal (a bug): logged with its traceback."""
        self._throttled.error("%s: %s not taken", self._description(), what, exc_info=True)

    def summary(self) -> str:
        counts = ", ".join(f"{name} {n}" for name, n in sorted(self.by_name.items()))
        return f"{sum(self.by_name.values())} refused" + (f" ({counts})" if counts else "")


class ImageTopic:
    """A subscription to an image topic whatever its type and hash, whose samples of the type
    read are handed to `on_payload` and the others refused by name."""

    def __init__(
        self,
        node: Ros2Node,
        topic: str,
        message: MessageType,
        refusals: Refusals,
        on_payload: Callable[[bytes], None],
    ) -> None:
        self.topic = topic
        self.message = message
        self.topic_type = rmw_zenoh.TopicType.of(message.value, typestore())
        self._refusals = refusals
        self._on_payload = on_payload
        self._subscription: Ros2Subscription = node.subscription(
            topic,
            self.topic_type,
            rmw_zenoh.NEWEST_FRAME_QOS,
            rmw_zenoh.topic_any_type_key(node.node.domain, topic),
            self._on_sample,
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # A Zenoh callback thread: nothing may escape it.
        try:
            self._check_key(str(sample.key_expr))
            self._on_payload(sample.payload.to_bytes())
        except Ros2MessageError as exc:
            self._refusals.refuse(exc)
        except Exception:
            self._refusals.unexpected(f"message on {self.topic}")

    def _check_key(self, key: str) -> None:
        _, _, dds, type_hash = rmw_zenoh.split_topic_key(key)
        if dds != self.topic_type.dds:
            raise WrongTopicType(
                f"{self.topic} carries {dds}, this source reads {self.topic_type.dds} "
                f"(source option type={'compressed' if 'Compressed' in dds else 'image'}?)"
            )
        if type_hash != self.topic_type.hash:
            raise WrongTypeHash(
                f"{self.topic}: type hash {type_hash} is not {self.message.value}'s "
                f"{self.topic_type.hash} (ROS 2 Jazzy's definition): another definition of the "
                "message"
            )

    def close(self) -> None:
        self._subscription.close()


class CameraInfoWatch:
    """The newest CameraInfo of a camera (its sibling `camera_info` topic); None until a good
    one came. A bad one (no focal length, non-finite values) is refused by name and the last
    good one kept."""

    def __init__(self, node: Ros2Node, image_topic: str, refusals: Refusals) -> None:
        self.topic = rmw_zenoh.camera_info_topic(image_topic)
        self.info: CameraInfo | None = None
        self.received = 0
        self._refusals = refusals
        self._ready = threading.Event()
        topic_type = rmw_zenoh.TopicType.of(MessageType.CAMERA_INFO.value, typestore())
        self._subscription = node.subscription(
            self.topic,
            topic_type,
            rmw_zenoh.NEWEST_FRAME_QOS,
            rmw_zenoh.topic_key(node.node.domain, self.topic, topic_type),
            self._on_sample,
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            info = decode_camera_info(sample.payload.to_bytes())
        except Ros2MessageError as exc:
            self._refusals.refuse(exc, f"CameraInfo on {self.topic}")
            return
        except Exception:
            self._refusals.unexpected(f"CameraInfo on {self.topic}")
            return
        self.received += 1
        self.info = info
        self._ready.set()

    def wait(self, timeout_s: float) -> CameraInfo | None:
        """The CameraInfo, waiting up to `timeout_s` for the first one."""
        self._ready.wait(timeout_s)
        return self.info

    def close(self) -> None:
        self._subscription.close()


class Ros2Source(FrameSource):
    """Frames from a ROS 2 image topic (see the module docstring)."""

    def __init__(
        self,
        spec: Ros2Spec,
        session: SourceSession,
        stop: threading.Event | None = None,
        *,
        height: int,
        width: int,
    ) -> None:
        self.spec = spec
        self.height, self.width = height, width
        self.message = FRAME_MESSAGES[spec.type]
        self.taken = 0
        self._stop = stop if stop is not None else session.stop
        self._frames = NewestFrame[bytes]()
        self._node = acquire_robot_node(
            session.config, session.robot, session.session, domain=spec.domain
        )
        self.domain = self._node.node.domain
        self.description = f"ros2 {spec.topic} ({self.message.value}, domain {self.domain})"
        self.refusals = Refusals(lambda: self.description)
        self._entities: list[ImageTopic | CameraInfoWatch] = []
        try:
            self._image = ImageTopic(
                self._node, spec.topic, self.message, self.refusals, self._frames.put
            )
            self._entities.append(self._image)
            self.camera = CameraInfoWatch(self._node, spec.topic, self.refusals)
            self._entities.append(self.camera)
        except BaseException:
            self._release()
            raise

    # The counts the tests and the run summary read, by error name and by error code.
    @property
    def refused(self) -> Counter[str]:
        return self.refusals.by_name

    @property
    def rejected(self) -> Counter[str]:
        return self.refusals.by_code

    def wait_ready(self, timeout_s: float) -> bool:
        return self._frames.wait_ready(timeout_s, self._stop)

    def rejected_frames(self) -> dict[str, int]:
        return dict(self.refusals.by_code)

    def read(self) -> np.ndarray:
        while True:  # bounded: each turn takes a new message, or ends at stop/close
            payload = self._frames.take(self._stop)
            self.dropped_stale = self._frames.dropped_stale
            if payload is None:
                raise EndOfStream
            try:
                frame = decode_frame(self.message, payload)
            except Ros2MessageError as exc:
                self.refusals.refuse(exc)
                continue
            self.taken += 1
            self.last_stamp_ns = frame.stamp_ns
            height, width = frame.image.shape[:2]
            remember_frame(InputFrame(frame.header, height, width, self.camera.info))
            return fit_frame(frame.image, self.height, self.width)

    def _release(self) -> None:
        release_topics(self._entities, self._node)

    def close(self) -> None:
        self.dropped_stale = self._frames.dropped_stale
        self._frames.close()
        self._release()
        log.info(
            "%s: %d frames taken, %d dropped as stale, %s",
            self.description,
            self.taken,
            self.dropped_stale,
            self.refusals.summary(),
        )


def release_topics(entities: list[Any], node: Any) -> None:
    """Close a ROS 2 source's subscriptions (newest first), then let go of the robot's node."""
    for entity in reversed(entities):
        entity.close()
    entities.clear()
    node.release()
