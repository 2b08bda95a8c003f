"""Small rosbag2 recordings for the tests, written with rosbags' own writer from real photographs
(skimage's, through `common.photos`: nothing downloads), in either storage (sqlite3, MCAP)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common import ros2_messages as rm
from common.photos import PHOTOS, photo_bgr

STORAGES = ("sqlite3", "mcap")
# The first record's time (and header stamp): 2024-11-19, well inside int32 seconds.
START_NS = 1_732_000_000_000_000_000


@dataclass(frozen=True)
class Record:
    """One record of a bag: its topic, message type, record time and CDR payload."""

    topic: str
    msgtype: str
    time_ns: int
    payload: bytes


def photo_frames(count: int, height: int = 48, width: int = 64) -> list[np.ndarray]:
    """`count` BGR frames, each a different photograph (in turn) shrunk to `height`×`width`."""
    names = list(PHOTOS)
    return [
        cv2.resize(photo_bgr(names[i % len(names)]), (width, height), interpolation=cv2.INTER_AREA)
        for i in range(count)
    ]


def header(stamp_ns: int, frame_id: str = "camera") -> object:
    types = rm.typestore().types
    sec, nanosec = divmod(stamp_ns, rm.NS_PER_S)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def image_payload(frame: np.ndarray, stamp_ns: int, encoding: str = "rgb8") -> bytes:
    """A sensor_msgs/msg/Image of a BGR frame in CDR (rgb8 or bgr8)."""
    pixels = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB) if encoding == "rgb8" else frame
    h, w = frame.shape[:2]
    msg = rm.typestore().types["sensor_msgs/msg/Image"](
        header=header(stamp_ns),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * 3,
        data=np.ascontiguousarray(pixels).reshape(-1),
    )
    return bytes(rm.typestore().serialize_cdr(msg, rm.MessageType.IMAGE.value))


def png_payload(frame: np.ndarray, stamp_ns: int) -> bytes:
    """A sensor_msgs/msg/CompressedImage (PNG: lossless, so frames compare exactly) in CDR."""
    _, png = cv2.imencode(".png", frame)
    msg = rm.typestore().types["sensor_msgs/msg/CompressedImage"](
        header=header(stamp_ns), format="png", data=png.reshape(-1)
    )
    return bytes(rm.typestore().serialize_cdr(msg, rm.MessageType.COMPRESSED_IMAGE.value))


def camera_records(
    frames: Sequence[np.ndarray],
    *,
    topic: str = "/camera/image_raw",
    compressed: bool = False,
    period_ns: int = 50_000_000,
    stamp_lag_ns: int = 3_000_000,
) -> list[Record]:
    """One record per frame, `period_ns` apart; each header is stamped `stamp_lag_ns` before its
    record time (a camera stamps at exposure, the recorder at arrival)."""
    msgtype = (rm.MessageType.COMPRESSED_IMAGE if compressed else rm.MessageType.IMAGE).value
    make = png_payload if compressed else image_payload
    return [
        Record(
            topic,
            msgtype,
            START_NS + i * period_ns,
            make(f, START_NS + i * period_ns - stamp_lag_ns),
        )
        for i, f in enumerate(frames)
    ]


def write_bag(path: Path, records: Sequence[Record], storage: str = "mcap") -> Path:
    """A rosbag2 folder at `path` holding `records` (one connection per topic); returns `path`."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin)
    writer.open()
    try:
        connections = {}
        for record in records:
            if record.topic not in connections:
                connections[record.topic] = writer.add_connection(
                    record.topic, record.msgtype, typestore=rm.typestore()
                )
            writer.write(connections[record.topic], record.time_ns, record.payload)
    finally:
        writer.close()
    return path


def storage_file(bag: Path) -> Path:
    """The one storage file of a bag folder (`.mcap` or `.db3`)."""
    (found,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    return found
