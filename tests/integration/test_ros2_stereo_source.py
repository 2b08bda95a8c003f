"""A stereo camera's two ROS 2 topics on real Zenoh sessions, through a ROS 2 session of the
robot's own (`ros2.endpoint`): the node's tokens come from that session, not the fleet's; left and
right images are paired by header stamp into one stereo frame; the geometry comes from the two
CameraInfos, and a camera that is not the one the model was built for is one warning with the
fleet file's `nav: camera:` lines; an image stamped out of order, an unpaired one and a right
CameraInfo with a positive P[3] are each named and counted, and the next pair is served; closing
the source closes the ROS 2 session."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zenoh

from common import rmw_zenoh
from common import ros2_messages as rm
from common.config import load_fleet
from common.source_spec import parse_ros2_source
from deploy.local_fleet import write_local_fleet
from deploy.readiness import wait_until
from robotd.ros2_node import input_frame, ros2_session_open
from robotd.sources.frame_sources import SourceSession
from robotd.sources.ros2_stereo import Ros2StereoSource
from robotd.sources.stereo_frame import StereoFrame
from robotd.sources.stereo_geometry import ModelCamera

WAIT_S = 10.0
LEFT, RIGHT = "/stereo/left/image_raw", "/stereo/right/image_raw"
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
FX, BASELINE_M = 80.0, 0.06
# zoo:stereo's default camera at the model's 80x60 view: 60° (fx = 40/tan 30° = 69.3 px, 15% less
# than the camera's FX), 6 cm, 0.30 m above the floor.
BUILT_FOR = ModelCamera(40 * 3**0.5, 0.06, 39.5, 29.5, 0.30, 0.10)


def _image(stamp_ns: int, value: int, frame_id: str) -> bytes:
    types = rm.typestore().types
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    msg = types["sensor_msgs/msg/Image"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
            frame_id=frame_id,
        ),
        height=60,
        width=80,
        encoding="mono8",
        is_bigendian=0,
        step=80,
        data=np.full(60 * 80, value, np.uint8),
    )
    return bytes(rm.typestore().serialize_cdr(msg, "sensor_msgs/msg/Image"))


def _info(p3: float) -> bytes:
    k = (FX, 0.0, 39.5, 0.0, FX, 29.5, 0.0, 0.0, 1.0)
    p = (FX, 0.0, 39.5, p3, 0.0, FX, 29.5, 0.0, 0.0, 0.0, 1.0, 0.0)
    return rm.encode_camera_info(rm.CameraInfo(rm.Header(T0, "stereo"), 60, 80, k=k, p=p))


def _key(topic: str, kind: rm.MessageType) -> str:
    return rmw_zenoh.topic_key(0, topic, rmw_zenoh.TopicType.of(kind.value, rm.typestore()))


def test_two_topics_paired_on_a_ros2_session_of_its_own(
    open_peer: Callable[..., zenoh.Session],
    zenoh_router: object,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="robotd.ros2")
    endpoint = zenoh_router.endpoint  # type: ignore[attr-defined]
    cfg = load_fleet(
        write_local_fleet(
            tmp_path, fleet="stereo", model="zoo:vgg", changes={"ros2": {"endpoint": endpoint}}
        )
    )
    # The fleet session: another router's peer in a real robot; here it must simply stay unused.
    fleet, camera = open_peer(), open_peer()
    stop = threading.Event()
    spec = parse_ros2_source(f"ros2:{LEFT},right={RIGHT},slop_ms=5")
    source = Ros2StereoSource(
        spec, SourceSession(fleet, cfg, "r", stop), height=60, width=80, built_for=BUILT_FOR
    )
    image = rm.MessageType.IMAGE
    try:
        assert ros2_session_open(endpoint)
        # The node and its subscriptions are announced by the ROS 2 session, not the fleet's.
        fleet_zid = str(fleet.info.zid())

        def tokens() -> list[str]:
            replies = camera.liveliness().get("@ros2_lv/0/**", timeout=1.0)
            keys = [str(r.ok.key_expr) for r in replies if r.ok is not None]
            return [k for k in keys if "elasticfog_r" in k]

        # The node, two image and two CameraInfo subscriptions.
        wait_until(lambda: len(tokens()) == 5 or None, timeout_s=WAIT_S, what="5 tokens")
        assert all(t.split("/")[2] != fleet_zid for t in tokens())
        for topic, p3 in ((LEFT, 0.0), (RIGHT, -FX * BASELINE_M)):
            camera.put(
                _key(rmw_zenoh.camera_info_topic(topic), rm.MessageType.CAMERA_INFO), _info(p3)
            )

        def put_pair(stamp_ns: int, value: int, skew_ns: int = 3 * MS) -> None:
            camera.put(_key(LEFT, image), _image(stamp_ns, value, "left_optical"))
            camera.put(_key(RIGHT, image), _image(stamp_ns + skew_ns, value + 1, "right_optical"))

        stamp = T0
        while not source.wait_ready(0.1):  # bounded: until the subscriptions are matched
            stamp += 33 * MS
            put_pair(stamp, 10)
            assert stamp < T0 + 300 * 33 * MS, "no pair at the source"
        frame = source.read()
        assert isinstance(frame, StereoFrame) and set(frame.views) == {"left", "right"}
        assert int(frame.views["left"][0, 0, 0]) == 10 and int(frame.views["right"][0, 0, 0]) == 11
        assert source.last_stamp_ns is not None
        remembered = input_frame(source.last_stamp_ns)
        assert remembered is not None and remembered.header.frame_id == "left_optical"
        geometry = source.geometry()
        assert geometry is not None and geometry.baseline_m == pytest.approx(BASELINE_M)
        assert geometry.fx_px == pytest.approx(FX)
        # Bad input: an image older than its side's last, an unpaired one, a right CameraInfo
        # with a positive P[3].
        before = source.unpaired
        camera.put(_key(LEFT, image), _image(T0, 50, "left_optical"))
        stamp += 33 * MS
        camera.put(_key(LEFT, image), _image(stamp, 60, "left_optical"))  # its right one is lost
        camera.put(_key(rmw_zenoh.camera_info_topic(RIGHT), rm.MessageType.CAMERA_INFO), _info(9.0))
        wait_until(
            lambda: source.refused.get("StampOutOfOrder") == 1 or None,
            timeout_s=WAIT_S,
            what=f"the out-of-order image named (now {source.refused})",
        )
        wait_until(
            lambda: source.cameras["right"].received >= 2 or None,
            timeout_s=WAIT_S,
            what="the second right CameraInfo",
        )
        stamp += 33 * MS
        put_pair(stamp, 20)
        frame = source.read()
        assert int(frame.views["left"][0, 0, 0]) == 20 and source.last_stamp_ns == stamp
        assert source.unpaired > before
        assert source.refused.get("BadCameraInfo") == 1
        kept = source.geometry()
        assert kept is not None and kept.baseline_m == pytest.approx(BASELINE_M)
        assert source.rejected_frames() == {"bad_value": 2}
        # The camera is not the model's (fx 80 px, not 69.3): one warning however often the
        # geometry is read, with the lines that build the model for it (hfov from fx: 53.13°).
        warnings = [r.message for r in caplog.records if "model was built for" in r.message]
        assert len(warnings) == 1, warnings
        assert warnings[0].startswith(f"{source.description}: the camera's CameraInfo geometry")
        assert warnings[0].endswith(
            "nav:\n  camera:\n    baseline_m: 0.06\n    hfov_deg: 53.13\n    height_m: 0.3"
        )
    finally:
        stop.set()
        source.close()
    assert not ros2_session_open(endpoint), "the ROS 2 session closes with its last node"
