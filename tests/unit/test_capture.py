"""One capture for a robot's services (`robotd.sources.capture`): the source is read at the
pace of the fastest service, a slower one takes the newest capture (never one twice, never a
queue of old ones), every service sees a capture with its one stamp at its own size, and the
source's end ends every feed."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.services import service_recording
from robotd.sources.capture import Capture
from robotd.sources.frame_sources import EndOfStream, FrameSource

H, W = 48, 64


class Numbered(FrameSource):
    """Frames whose every pixel is their number, stamped 1000 + number; `count` of them."""

    description = "numbered"

    def __init__(self, count: int) -> None:
        self.count = count
        self.reads = 0

    def read(self) -> np.ndarray:
        if self.reads == self.count:
            raise EndOfStream
        self.last_stamp_ns = 1000 + self.reads
        frame = np.full((H, W, 3), self.reads, dtype=np.uint8)
        self.reads += 1
        return frame


def test_the_fastest_service_paces_the_source_and_a_slower_one_takes_the_newest() -> None:
    source = Numbered(10)
    capture = Capture(source)
    fast, slow = capture.feed(H, W), capture.feed(H // 2, W // 2)
    assert [int(fast.read()[0, 0, 0]) for _ in range(3)] == [0, 1, 2]
    assert source.reads == 3
    got = slow.read()
    assert got.shape == (H // 2, W // 2, 3)  # fitted to its own input size
    assert int(got[0, 0, 0]) == 2 and slow.last_stamp_ns == 1002  # the newest, its one stamp
    assert int(slow.read()[0, 0, 0]) == 3  # nothing new: it reads the next capture itself
    assert int(fast.read()[0, 0, 0]) == 3  # ... which the fast one has not had yet
    assert source.reads == 4


def test_the_sources_end_ends_every_feed() -> None:
    capture = Capture(Numbered(1))
    a, b = capture.feed(H, W), capture.feed(H, W)
    a.read()
    b.read()
    for feed in (a, b):
        with pytest.raises(EndOfStream):
            feed.read()


def test_a_service_recording_sits_beside_the_robots() -> None:
    from pathlib import Path

    assert service_recording(Path("/r/run.mcap"), "tags") == Path("/r/run.tags.mcap")
    assert service_recording(Path("/r/run"), "tags") == Path("/r/run.tags")
