"""One capture for every service of a robot: the robot's frame source, read once, feeds each
service's frame loop.

`Capture` wraps the robot's one `FrameSource`; `feed(height, width)` gives a service its own
`FrameSource` view of it, at that service's model input size (the capture fitted as the photo
source frames a photograph: `fit_frame`, centre crop of the model's aspect, then scaled). Reading
is pulled by the services' frame loops, each at its own fps: a feed returns the newest capture it
has not had yet, and reads a new one from the source only when it has had them all. So the source
is read at the pace of the fastest service, every capture carries one stamp whichever services
take it, a slower service takes the newest capture when it comes (never a queue of old ones), and
no service is handed the same capture twice. The source's end ends every feed.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from robotd.sources.frame_sources import EndOfStream, FrameSource, fit_frame


@dataclass(frozen=True)
class _Taken:
    """One capture: its number (from 0), its stamp and its image."""

    seq: int
    stamp_ns: int
    image: np.ndarray


class Capture:
    """`Capture(source)`: the robot's source, shared by its services' feeds (thread-safe). It
    does not close the source: whoever opened it does."""

    def __init__(self, source: FrameSource) -> None:
        if source.views is not None:
            raise ValueError("a stereo source feeds one service; several services need one image")
        self.source = source
        self._lock = threading.Lock()
        self._newest: _Taken | None = None
        self._ended = False
        self.captures = 0

    def feed(self, height: int, width: int) -> CaptureFeed:
        """A service's view of the capture, its frames at `height`x`width`."""
        return CaptureFeed(self, height, width)

    def newer_than(self, seq: int) -> _Taken:
        """The newest capture after `seq` (-1: none had yet), reading a new one from the source
        when there is none; EndOfStream once the source has ended."""
        with self._lock:
            if self._newest is not None and self._newest.seq > seq:
                return self._newest
            if self._ended:
                raise EndOfStream
            try:
                image = self.source.read()
            except EndOfStream:
                self._ended = True
                raise
            if not isinstance(image, np.ndarray):
                raise ValueError("a stereo source feeds one service")
            stamp = self.source.last_stamp_ns or time.time_ns()
            self._newest = _Taken(self.captures, stamp, image)
            self.captures += 1
            return self._newest

    def has_unseen(self, seq: int) -> bool:
        with self._lock:
            return self._newest is not None and self._newest.seq > seq


class CaptureFeed(FrameSource):
    """One service's frames from the robot's `Capture` (see the module docstring)."""

    def __init__(self, capture: Capture, height: int, width: int) -> None:
        super().__init__()
        self.capture = capture
        self.height, self.width = height, width
        self.description = f"{capture.source.description} (shared capture, {width}x{height})"
        self._seen = -1

    def read(self) -> np.ndarray:
        taken = self.capture.newer_than(self._seen)
        self._seen = taken.seq
        self.last_stamp_ns = taken.stamp_ns
        self.dropped_stale = self.capture.source.dropped_stale
        return fit_frame(taken.image, self.height, self.width)

    def wait_ready(self, timeout_s: float) -> bool:
        if self.capture.has_unseen(self._seen):
            return True
        return self.capture.source.wait_ready(timeout_s)

    def rejected_frames(self) -> dict[str, int]:
        return self.capture.source.rejected_frames()
