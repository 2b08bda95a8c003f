"""The `ros2:` source on real Zenoh sessions: the newest frame wins and the ones it replaced are
counted (dropped_stale), each bad message is counted by its error code (rejected_frames) and
the source goes on to the next good frame, stamped with its header."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zenoh

from common import rmw_zenoh
from common.config import load_fleet
from common.ros2_messages import typestore
from common.source_spec import parse_ros2_source
from deploy.local_fleet import write_local_fleet
from deploy.readiness import wait_until
from robotd.sources.frame_sources import SourceSession
from robotd.sources.ros2 import Ros2Source

WAIT_S = 10.0
TOPIC = "/camera/image_raw"


def _image(stamp_ns: int, value: int = 0) -> bytes:
    types = typestore().types
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    msg = types["sensor_msgs/msg/Image"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="cam"
        ),
        height=4,
        width=6,
        encoding="mono8",
        is_bigendian=0,
        step=6,
        data=np.full(24, value, np.uint8),
    )
    return bytes(typestore().serialize_cdr(msg, "sensor_msgs/msg/Image"))


def test_newest_wins_bad_messages_counted_by_code(
    open_peer: Callable[..., zenoh.Session], tmp_path: Path
) -> None:
    cfg = load_fleet(write_local_fleet(tmp_path, fleet="ros2src", model="zoo:vgg"))
    robot, camera = open_peer(), open_peer()
    stop = threading.Event()
    source = Ros2Source(
        parse_ros2_source(f"ros2:{TOPIC}"), SourceSession(robot, cfg, "r", stop), height=4, width=6
    )
    key = rmw_zenoh.topic_key(0, TOPIC, rmw_zenoh.TopicType.of("sensor_msgs/msg/Image"))
    try:
        # Until the subscription is matched, a put may reach nobody.
        wait_until(
            lambda: (camera.put(key, _image(1)), source.wait_ready(0.1))[1] or None,
            timeout_s=WAIT_S,
            what="the first frame at the source",
        )
        source.read()
        frames = source._frames
        # A burst: only the newest is read, the four it replaced are counted.
        before_received, before_dropped = frames.received, frames.dropped_stale
        for n in range(5):
            camera.put(key, _image(100 + n, n))
        wait_until(
            lambda: frames.received >= before_received + 5 or None,
            timeout_s=WAIT_S,
            what="the burst",
        )
        frame = source.read()
        assert source.last_stamp_ns == 104 and int(frame[0, 0, 0]) == 4
        assert source.dropped_stale - before_dropped == 4
        # A wrong type hash (refused on arrival) and truncated CDR (refused when read).
        wrong = key.rsplit("/", 1)[0] + "/RIHS01_" + "1" * 64
        camera.put(wrong, _image(200))
        camera.put(key, _image(201)[:20])
        wait_until(lambda: source.wait_ready(0.1) or None, timeout_s=WAIT_S, what="bad frame")
        got: list[int | None] = []
        reader = threading.Thread(target=lambda: (source.read(), got.append(source.last_stamp_ns)))
        reader.start()
        wait_until(
            lambda: source.rejected_frames() == {"schema_version": 1, "malformed": 1} or None,
            timeout_s=WAIT_S,
            what=f"both refusals counted (now {source.rejected_frames()})",
        )
        camera.put(key, _image(300))
        reader.join(WAIT_S)
        assert got == [300], "the next good frame is read after the bad ones"
    finally:
        stop.set()
        source.close()
