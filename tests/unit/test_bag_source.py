"""`bag:PATH[:TOPIC]`: frames from rosbag2 recordings written here with rosbags' writer (sqlite3
and MCAP storage, folders and single files) from real photographs: every frame comes back with its
header stamp and its record time as the timeline; the bag ends the stream; topics are picked or
refused with the bag's topics listed; a path that is not a bag and damaged records are named
errors, and no decodable record is lost around a bad one."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from common import ros2_messages as rm
from common.source_spec import BagSpec, SourceError, parse_source
from robotd.sources.bag import BagSource, BagTopicError, NotABag
from robotd.sources.frame_sources import EndOfStream, FrameSource
from robotd.sources.opening import open_source
from tests.unit.bag_support import (
    START_NS,
    STORAGES,
    Record,
    camera_records,
    photo_frames,
    storage_file,
    write_bag,
)

FRAMES = 6
PERIOD_NS = 50_000_000
LAG_NS = 3_000_000


def read_all(source: FrameSource) -> tuple[list[np.ndarray], list[int], list[float | None]]:
    """Every frame, stamp and offset (asked before each read, as the robot's pacer does)."""
    frames: list[np.ndarray] = []
    stamps: list[int] = []
    offsets: list[float | None] = []
    for _ in range(1000):  # far more than any bag here
        offsets.append(source.next_offset_s())
        try:
            frames.append(np.asarray(source.read()))
        except EndOfStream:
            return frames, stamps, offsets
        assert source.last_stamp_ns is not None
        stamps.append(source.last_stamp_ns)
    raise AssertionError("the bag did not end")


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("compressed", [False, True])
@pytest.mark.parametrize("single_file", [False, True])
def test_every_frame_comes_back_with_its_header_stamp_and_record_time(
    tmp_path: Path, storage: str, compressed: bool, single_file: bool
) -> None:
    frames = photo_frames(FRAMES)
    records = camera_records(
        frames, compressed=compressed, period_ns=PERIOD_NS, stamp_lag_ns=LAG_NS
    )
    bag = write_bag(tmp_path / "run", records, storage)
    path = storage_file(bag) if single_file else bag
    with open_source(f"bag:{path}", height=1, width=1) as source:
        assert isinstance(source, BagSource)
        assert source.topic == "/camera/image_raw"
        got, stamps, offsets = read_all(source)
    assert len(got) == FRAMES
    for frame, expected in zip(got, frames, strict=True):
        np.testing.assert_array_equal(frame, expected)  # rgb8 and PNG are lossless
    assert stamps == [START_NS + i * PERIOD_NS - LAG_NS for i in range(FRAMES)]
    assert offsets == pytest.approx([i * PERIOD_NS / 1e9 for i in range(FRAMES)] + [None])


def test_a_named_topic_is_read_among_several(tmp_path: Path) -> None:
    frames = photo_frames(4)
    left = camera_records(frames[:2], topic="/left/image")
    right = camera_records(frames[2:], topic="/right/image", compressed=True)
    bag = write_bag(tmp_path / "pair", left + right, "sqlite3")
    for topic, expected in (("/right/image", frames[2:]), ("right/image", frames[2:])):
        with open_source(f"bag:{bag}:{topic}", height=1, width=1) as source:
            got, _, _ = read_all(source)
        assert [f.tobytes() for f in got] == [f.tobytes() for f in expected]


def test_several_image_topics_and_none_named_is_an_error_listing_them(tmp_path: Path) -> None:
    frames = photo_frames(2)
    records = camera_records(frames, topic="/left/image") + camera_records(frames, topic="/front")
    bag = write_bag(tmp_path / "pair", records)
    with pytest.raises(BagTopicError, match=r"2 image topics \(/front, /left/image\); name one"):
        BagSource(bag)


def test_a_missing_topic_or_one_without_images_is_an_error_listing_the_topics(
    tmp_path: Path,
) -> None:
    twist = rm.encode_twist(rm.Twist(linear=(0.2, 0.0, 0.0)))
    records = [
        *camera_records(photo_frames(1)),
        Record("/cmd_vel", rm.MessageType.TWIST.value, START_NS, twist),
    ]
    bag = write_bag(tmp_path / "run", records)
    with pytest.raises(BagTopicError, match=r"has no topic /depth; its topics: /camera/image_raw"):
        BagSource(bag, "/depth")
    with pytest.raises(
        BagTopicError,
        match=r"topic /cmd_vel holds geometry_msgs/msg/Twist, not sensor_msgs/msg/Image or "
        r"CompressedImage; image topics: /camera/image_raw",
    ):
        BagSource(bag, "/cmd_vel")
    only_twists = write_bag(tmp_path / "twists", records[1:])
    with pytest.raises(
        BagTopicError, match=r"no image topic .*its topics: /cmd_vel \(geometry_msgs/msg/Twist\)"
    ):
        BagSource(only_twists)


def test_a_path_that_is_not_a_bag_is_a_named_one_line_error(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "run", camera_records(photo_frames(3)), "mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(storage_file(bag).read_bytes()[:500])
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording")
    db = tmp_path / "notes.db3"
    db.write_text("not a database" * 100)
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    video = tmp_path / "clip.avi"
    video.write_bytes(b"RIFF")
    for path in (cut, text, db, empty_dir, video, tmp_path / "nope"):
        with pytest.raises(NotABag) as caught:
            BagSource(path)
        message = str(caught.value)
        assert str(path) in message and "\n" not in message
    with pytest.raises(NotABag, match="expected a rosbag2 folder"):
        BagSource(video)


@pytest.mark.parametrize("storage", STORAGES)
def test_bad_records_are_refused_by_name_and_the_others_served(
    tmp_path: Path, storage: str, caplog: pytest.LogCaptureFixture
) -> None:
    frames = photo_frames(5)
    records = camera_records(frames)
    good = records[1].payload
    bad = [
        Record(r.topic, r.msgtype, r.time_ns, payload)
        for r, payload in zip(
            records[1:4],
            [good[: len(good) // 2], rm.encode_twist(rm.Twist()), b""],
            strict=True,
        )
    ]
    bag = write_bag(tmp_path / "run", [records[0], *bad, records[4]], storage)
    source = BagSource(bag)
    with caplog.at_level(logging.WARNING, logger="robotd"), source:
        got, _, _ = read_all(source)
        assert source.refused == 3
    np.testing.assert_array_equal(got[0], frames[0])
    np.testing.assert_array_equal(got[1], frames[4])
    assert len(got) == 2
    refusals = [r.getMessage() for r in caplog.records if "refused: " in r.getMessage()]
    assert len(refusals) == 3 and all("MalformedMessage" in m for m in refusals)
    assert any("3 records of /camera/image_raw refused" in r.getMessage() for r in caplog.records)


def test_an_unknown_encoding_in_a_record_is_refused_naming_it(tmp_path: Path) -> None:
    frames = photo_frames(2)
    yuv = camera_records(frames[:1])[0]
    types = rm.typestore()
    msg = types.deserialize_cdr(yuv.payload, rm.MessageType.IMAGE.value)
    msg.encoding = "yuv422"
    odd = Record(yuv.topic, yuv.msgtype, yuv.time_ns, bytes(types.serialize_cdr(msg, yuv.msgtype)))
    later = camera_records(frames, period_ns=1)[1]
    source = BagSource(write_bag(tmp_path / "run", [odd, later]))
    with source:
        got, _, _ = read_all(source)
        assert source.refused == 1 and len(got) == 1


def test_a_header_without_a_stamp_takes_the_record_time(tmp_path: Path) -> None:
    frame = photo_frames(1)[0]
    from tests.unit.bag_support import image_payload

    record = Record("/cam", rm.MessageType.IMAGE.value, START_NS + 7, image_payload(frame, 0))
    with BagSource(write_bag(tmp_path / "run", [record])) as source:
        source.read()
        assert source.last_stamp_ns == START_NS + 7


def test_bag_specs_parse_into_a_path_and_a_topic() -> None:
    assert parse_source("bag:runs/a") == BagSpec("bag:runs/a", path=Path("runs/a"))
    spec = parse_source("bag:runs/a.mcap:/camera/image_raw")
    assert spec == BagSpec(
        "bag:runs/a.mcap:/camera/image_raw", path=Path("runs/a.mcap"), topic="/camera/image_raw"
    )
    assert parse_source("bag:runs/a:cam").topic == "/cam"  # type: ignore[attr-defined]
    # A `:` that no topic name follows is the path's.
    assert parse_source("bag:/data/run:0").path == Path("/data/run:0")  # type: ignore[attr-defined]
    moved = spec.resolved(lambda p: f"/fleet/{p}")
    assert str(moved) == "bag:/fleet/runs/a.mcap:/camera/image_raw"
    for bad in ("bag:", "bag: ", "bag:run:/9cam"):
        with pytest.raises(SourceError):
            parse_source(bad)
