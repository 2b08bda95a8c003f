"""The `ros2:` source spec, the results-topic collision check and the newest-frame slot: parsed
into typed values with named errors, before any model loads or Zenoh session opens."""

from __future__ import annotations

import threading

import pytest

from common.errors import UserError
from common.source_spec import (
    Ros2FrameType,
    Ros2Spec,
    check_results_topics,
    parse_ros2_source,
)
from robotd.sources.newest_frame import NewestFrame


def test_topic_type_and_domain() -> None:
    spec = parse_ros2_source("ros2:/camera/image_raw")
    assert (spec.topic, spec.type, spec.domain) == ("/camera/image_raw", Ros2FrameType.IMAGE, None)
    spec = parse_ros2_source(" ros2:camera/image , type=compressed, domain=3 ")
    assert (spec.topic, spec.type, spec.domain) == ("/camera/image", Ros2FrameType.COMPRESSED, 3)
    assert isinstance(spec, Ros2Spec)


@pytest.mark.parametrize(
    ("spec", "named"),
    [
        ("ros2:", "not a ROS 2 topic name"),
        ("ros2:/cam//x", "not a ROS 2 topic name"),
        ("ros2:/cam,type=depth", "type='depth' is not one of image, compressed"),
        ("ros2:/cam,domain=x", "not an integer"),
        ("ros2:/cam,domain=500", "0..232"),
        ("ros2:/cam,fps=3", "unknown option 'fps'"),
        ("ros2:/cam,type", "expected name=value"),
        ("ros2", "not a ROS 2 topic name"),
        ("ros3:/cam", "unknown frame source"),
        ("ros2:/l,slop_ms=5", "slop_ms pairs a stereo camera's images: give right="),
        ("ros2:/l,right=/l", "left and right are both /l"),
        ("ros2:/l,right=/r,slop_ms=0", "slop_ms must be a positive number"),
        ("ros2:/l,right=/r,slop_ms=x", "slop_ms='x' is not a number"),
        ("ros2:/l,right=r//x", "right='r//x'"),
    ],
)
def test_bad_specs_are_named(spec: str, named: str) -> None:
    with pytest.raises(UserError, match=named.replace(".", r"\.").replace("(", r"\(")):
        parse_ros2_source(spec)


def test_a_stereo_camera_from_two_topics() -> None:
    spec = parse_ros2_source("ros2:/left/image_raw,right=right/image_raw")
    assert (spec.topic, spec.right, spec.slop_ms) == ("/left/image_raw", "/right/image_raw", 10.0)
    assert spec.topics == ("/left/image_raw", "/right/image_raw")
    spec = parse_ros2_source("ros2:/l,right=/r,slop_ms=2.5,type=compressed,domain=1")
    assert (spec.slop_ms, spec.type, spec.domain) == (2.5, Ros2FrameType.COMPRESSED, 1)
    assert parse_ros2_source("ros2:/cam").topics == ("/cam",)


def test_results_topics_colliding_with_the_input_are_refused() -> None:
    with pytest.raises(UserError, match="collides with the input topic /ef/out/x"):
        check_results_topics("ros2:/ef/out/x", "/ef/out", 0)
    with pytest.raises(UserError, match="collides"):
        check_results_topics("ros2:/ef/out", "/ef/out", 0)
    # Another domain, another prefix, another kind of source: no collision.
    check_results_topics("ros2:/ef/out/x,domain=4", "/ef/out", 0)
    check_results_topics("ros2:/ef/outside", "/ef/out", 0)
    check_results_topics("photo", "/ef/out", 0)
    check_results_topics("ros2:/ef/out/x", None, 0)
    # Either image of a stereo pair.
    with pytest.raises(UserError, match="collides with the input topic /ef/out/right"):
        check_results_topics("ros2:/left,right=/ef/out/right", "/ef/out", 0)


def test_newest_frame_wins_and_the_dropped_are_counted() -> None:
    slot = NewestFrame[int]()
    for n in range(5):
        slot.put(n)
    assert slot.take() == 4
    assert (slot.received, slot.dropped_stale) == (5, 4)
    slot.put(5)
    assert slot.take() == 5 and slot.dropped_stale == 4


def test_a_wait_for_the_next_frame_ends_at_stop_or_close() -> None:
    stop = threading.Event()
    stop.set()
    assert NewestFrame[int]().take(stop) is None
    slot = NewestFrame[int]()
    threading.Timer(0.05, slot.close).start()
    assert slot.take() is None


def test_wait_ready_says_whether_a_frame_waits() -> None:
    slot = NewestFrame[int]()
    assert not slot.wait_ready(0.01)
    slot.put(1)
    assert slot.wait_ready(0.0)
    stop = threading.Event()
    stop.set()
    assert NewestFrame[int]().wait_ready(5.0, stop)
