"""`bag:PATH[:TOPIC]`: a robot's frames from a rosbag2 recording (sqlite3 or MCAP storage).

A ROS 2 robot records its camera with `ros2 bag record`; replaying that recording through
elasticfog shows what the fleet would have done with the robot's own frames. The bag is read
with rosbags' rosbag2 reader (a folder with metadata.yaml, or one `.mcap` or `.db3` file); each
record of the topic, a sensor_msgs/msg/Image or CompressedImage, is decoded by
`common.ros2_messages` into a BGR frame. A frame's capture stamp (`last_stamp_ns`) is its
message's header stamp (the record's time where the header has none), and the source offers its
record times as its timeline (`next_offset_s`), so the robot plays the bag at the recorded rate
unless `--fps` is given. The bag ends the run (`EndOfStream`).

Bad input: a path that is not a bag (`NotABag`), a topic the bag lacks, a topic of another type,
or several image topics and none named (`BagTopicError`) are one-line errors at start, listing
the bag's topics. A record that does not decode (truncated, another type, an unknown encoding) is
a throttled one-line warning, counted by error code (`rejected_frames`: the run summary's
"frames rejected") and skipped: the frames around it are served. A bag whose
reading fails midway (a storage file cut short) ends there with a one-line error; the frames
read until then have been served.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from common.ros2_messages import FRAME_TYPES, NS_PER_S, MessageType, Ros2MessageError, decode_frame
from common.source_spec import SourceError
from common.throttled_log import ThrottledLog
from robotd.sources.frame_sources import EndOfStream, FrameSource

log = logging.getLogger("robotd")

_FRAME_TYPE_NAMES = frozenset(t.value for t in FRAME_TYPES)
# What the reader reads: a rosbag2 folder, or one storage file.
BAG_FORMS = "a rosbag2 folder (with metadata.yaml), a .mcap file or a .db3 file"


class NotABag(SourceError):
    """A path that rosbags cannot read as a rosbag2 recording."""


class BagTopicError(SourceError):
    """A bag without the topic asked for, a topic that holds no images, or a choice to make."""


class BagSource(FrameSource):
    """The frames of one image topic of a rosbag2 recording (see the module docstring)."""

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        self.path = Path(path)
        self.rejected: Counter[str] = Counter()  # records refused, by error code
        self.frames_read = 0
        self._throttled = ThrottledLog(log, label=lambda: f"bag {self.path}")
        self._reader = _open_reader(self.path)
        try:
            self.topic, self._connections = _pick_topic(self.path, self._reader, topic)
            self._records: Iterator[tuple[Any, int, bytes]] = self._reader.messages(
                connections=self._connections
            )
        except BaseException:
            self._reader.close()
            raise
        count = sum(c.msgcount for c in self._connections)
        self.description = f"bag {self.path} topic {self.topic} ({count} records)"
        # The next frame, decoded ahead so that its record time paces it: (frame, stamp, time).
        self._ahead: tuple[np.ndarray, int, int] | None = None
        self._ended = False
        self._first_time_ns: int | None = None

    def next_offset_s(self) -> float | None:
        """Seconds from the bag's first frame to the next one, by record time; None at the end."""
        ahead = self._peek()
        if ahead is None:
            return None
        if self._first_time_ns is None:
            self._first_time_ns = ahead[2]
        return (ahead[2] - self._first_time_ns) / NS_PER_S

    def read(self) -> np.ndarray:
        ahead = self._peek()
        if ahead is None:
            raise EndOfStream(f"bag {self.path}: end of topic {self.topic}")
        self._ahead = None
        frame, self.last_stamp_ns, _ = ahead
        self.frames_read += 1
        return frame

    @property
    def refused(self) -> int:
        """Records refused so far (not decodable)."""
        return sum(self.rejected.values())

    def rejected_frames(self) -> dict[str, int]:
        return dict(self.rejected)

    def close(self) -> None:
        if self.refused:
            log.warning(
                "bag %s: %d records of %s refused (not decodable), %d frames read",
                self.path,
                self.refused,
                self.topic,
                self.frames_read,
            )
        self._reader.close()

    def _peek(self) -> tuple[np.ndarray, int, int] | None:
        """The next decodable record as (frame, stamp, record time), skipping the others."""
        while self._ahead is None and not self._ended:
            try:
                connection, time_ns, raw = next(self._records)
            except StopIteration:
                self._ended = True
                break
            except Exception as exc:  # whatever the storage's reader raises on a damaged file
                self._ended = True
                log.error(
                    "bag %s: reading %s failed after %d frames (%s: %s); the bag ends here",
                    self.path,
                    self.topic,
                    self.frames_read,
                    type(exc).__name__,
                    " ".join(str(exc).split()),
                )
                break
            try:
                decoded = decode_frame(MessageType(connection.msgtype), raw)
            except Ros2MessageError as exc:
                self.rejected[exc.code.value] += 1
                self._throttled.warning(
                    "bag %s: record at %d ns on %s refused: %s: %s",
                    self.path,
                    time_ns,
                    self.topic,
                    type(exc).__name__,
                    exc,
                )
                continue
            # A header without a stamp (0): the record's time is the best capture time known.
            stamp_ns = decoded.stamp_ns if decoded.stamp_ns > 0 else time_ns
            self._ahead = (decoded.image, stamp_ns, time_ns)
        return self._ahead


def _open_reader(path: Path) -> Any:
    """rosbags' rosbag2 reader, open; NotABag naming the path otherwise."""
    from rosbags.rosbag2 import Reader

    if not path.exists():
        raise NotABag(f"bag not found: {path}")
    try:
        reader = Reader(path)
    except Exception as exc:  # ReaderError, FileNotFoundError (a folder without metadata.yaml)
        raise NotABag(
            f"{path} is not a rosbag2 bag ({_one_line(exc)}); expected {BAG_FORMS}"
        ) from None
    try:
        reader.open()
    except Exception as exc:  # ReaderError, and what a damaged file makes its parser raise
        raise NotABag(
            f"{path} is not a readable rosbag2 bag ({_one_line(exc)}); expected {BAG_FORMS}"
        ) from None
    return reader


def _pick_topic(path: Path, reader: Any, topic: str | None) -> tuple[str, list[Any]]:
    """The topic to read and its connections; BagTopicError listing the bag's topics."""
    by_topic: dict[str, list[Any]] = {}
    for connection in reader.connections:
        by_topic.setdefault(connection.topic, []).append(connection)
    images = sorted(t for t, cs in by_topic.items() if _frames_of(cs))
    listed = ", ".join(f"{t} ({_types(cs)})" for t, cs in sorted(by_topic.items())) or "none"
    if topic is None:
        if len(images) == 1:
            return images[0], _frames_of(by_topic[images[0]])
        if not images:
            raise BagTopicError(
                f"bag {path} has no image topic (sensor_msgs/msg/Image or CompressedImage); "
                f"its topics: {listed}"
            )
        raise BagTopicError(
            f"bag {path} has {len(images)} image topics ({', '.join(images)}); name one: "
            f"bag:{path}:TOPIC"
        )
    if topic not in by_topic:
        raise BagTopicError(f"bag {path} has no topic {topic}; its topics: {listed}")
    frames = _frames_of(by_topic[topic])
    if not frames:
        raise BagTopicError(
            f"bag {path}: topic {topic} holds {_types(by_topic[topic])}, not "
            f"sensor_msgs/msg/Image or CompressedImage; image topics: {', '.join(images) or 'none'}"
        )
    return topic, frames


def _frames_of(connections: list[Any]) -> list[Any]:
    return [c for c in connections if c.msgtype in _FRAME_TYPE_NAMES]


def _types(connections: list[Any]) -> str:
    return ", ".join(sorted({c.msgtype for c in connections}))


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
