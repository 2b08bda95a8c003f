"""`ros2:<topic>[,type=image|compressed][,domain=<id>]`: frames from a ROS 2 camera topic over
rmw_zenoh, with no ROS installed.

The robot's node (`robotd.ros2_node`) subscribes on the daemon's Zenoh session to the topic
whatever its type and hash (`<domain>/<topic>/*/*`) and announces the subscription (MS token)
with the type it reads: `sensor_msgs/msg/Image` (rgb8, bgr8, mono8, rgba8, bgra8) or
`sensor_msgs/msg/CompressedImage` (JPEG, PNG), its RIHS01 hash from rosbags' Jazzy type store.
Listening past the type lets a publisher of another type, or of the same type with another hash
(another ROS distribution's definition), be named in the log instead of never heard.

Camera semantics, as the `zenoh` source's (`robotd.sources.newest_frame`): the frame loop always
takes the newest message; one that arrives while another waits replaces it and the replaced one is
counted (`dropped_stale`, in each frame's telemetry and the run summary). Messages are decoded
when the loop takes them (`common.ros2_messages`), so frames dropped cost no decoding, and fitted
to the model's input size as the photo source frames its photographs
(`robotd.sources.frame_sources.fit_frame`: the largest centred rectangle of the model's aspect,
scaled). The header stamp is the frame's capture stamp (`last_stamp_ns`) and its frame id is kept
for the results published as Images.

Bad input (a wrong type or type hash, truncated CDR, an unknown encoding, an empty image, bytes
that do not decode) is one throttled line naming it, counted by error code as the `zenoh`
source's (`rejected_frames`, in the run summary); the loop waits for the next message and the
daemon keeps serving. The counts by error name are logged when the source closes.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from typing import TYPE_CHECKING

import numpy as np

from common import rmw_zenoh
from common.ros2_messages import MessageType, Ros2MessageError, decode_frame, typestore
from common.source_spec import Ros2FrameType, Ros2Spec
from common.throttled_log import ThrottledLog
from common.wire.errors import ErrorCode
from robotd.ros2_node import acquire_node
from robotd.sources.frame_sources import EndOfStream, FrameSource, fit_frame
from robotd.sources.newest_frame import NewestFrame

if TYPE_CHECKING:
    import zenoh

    from robotd.sources.frame_sources import SourceSession

log = logging.getLogger("robotd.ros2")

_MESSAGE = {
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
        self.domain = spec.domain if spec.domain is not None else session.config.ros2.domain()
        self.message = _MESSAGE[spec.type]
        self.topic_type = rmw_zenoh.TopicType.of(self.message.value, typestore())
        self.description = f"ros2 {spec.topic} ({self.message.value}, domain {self.domain})"
        # Refused messages by error name (the log's words) and by error code (the summary's).
        self.refused: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.taken = 0
        self._stop = stop
        self._frames = NewestFrame[bytes]()
        self._throttled = ThrottledLog(log, label=lambda: self.description)
        self._node = acquire_node(session.session, self.domain, session.robot)
        try:
            self._subscription = self._node.subscription(
                spec.topic,
                self.topic_type,
                rmw_zenoh.NEWEST_FRAME_QOS,
                rmw_zenoh.topic_any_type_key(self.domain, spec.topic),
                self._on_sample,
            )
        except BaseException:
            self._node.release()
            raise

    def wait_ready(self, timeout_s: float) -> bool:
        return self._frames.wait_ready(timeout_s, self._stop)

    def rejected_frames(self) -> dict[str, int]:
        return dict(self.rejected)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # A Zenoh callback thread: nothing may escape it.
        try:
            self._check_key(str(sample.key_expr))
            self._frames.put(sample.payload.to_bytes())
        except Ros2MessageError as exc:
            self._refuse(exc)
        except Exception:
            self._throttled.error("%s: message not taken", self.description, exc_info=True)

    def _check_key(self, key: str) -> None:
        _, _, dds, type_hash = rmw_zenoh.split_topic_key(key)
        if dds != self.topic_type.dds:
            raise WrongTopicType(
                f"{self.spec.topic} carries {dds}, this source reads {self.topic_type.dds} "
                f"(source option type={'compressed' if 'Compressed' in dds else 'image'}?)"
            )
        if type_hash != self.topic_type.hash:
            raise WrongTypeHash(
                f"{self.spec.topic}: type hash {type_hash} is not {self.message.value}'s "
                f"{self.topic_type.hash} (ROS 2 Jazzy's definition): another definition of the "
                "message"
            )

    def _refuse(self, exc: Ros2MessageError) -> None:
        name = type(exc).__name__
        self.refused[name] += 1
        self.rejected[exc.code.value] += 1
        self._throttled.warning("%s: message refused: %s: %s", self.description, name, exc)

    def read(self) -> np.ndarray:
        while True:  # bounded: each turn takes a new message, or ends at stop/close
            payload = self._frames.take(self._stop)
            self.dropped_stale = self._frames.dropped_stale
            if payload is None:
                raise EndOfStream
            try:
                frame = decode_frame(self.message, payload)
            except Ros2MessageError as exc:
                self._refuse(exc)
                continue
            self.taken += 1
            self.last_stamp_ns = frame.stamp_ns
            self._node.remember_frame(frame.stamp_ns, frame.header.frame_id)
            return fit_frame(frame.image, self.height, self.width)

    def close(self) -> None:
        self.dropped_stale = self._frames.dropped_stale
        self._frames.close()
        self._subscription.close()
        self._node.release()
        refused = ", ".join(f"{name} {n}" for name, n in sorted(self.refused.items()))
        log.info(
            "%s: %d frames taken, %d dropped as stale, %d refused%s",
            self.description,
            self.taken,
            self.dropped_stale,
            sum(self.refused.values()),
            f" ({refused})" if refused else "",
        )
