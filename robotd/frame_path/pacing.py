"""Pacing in the application: the emulated uplink (`--uplink-mbit`) and the frame rate (`--fps`).

`--uplink-mbit X` is an *emulation* for a single host, where every process talks over loopback
at gigabytes per second: before a request is handed to Zenoh, the robot reserves its bytes in a
token bucket filled at X Mbit/s and holds the request until the bucket has let them through.
A request of n bytes thus leaves n·8/(X·10⁶) seconds after the previous one finished, like on a
link of that rate with a small buffer (`UPLINK_BURST_BYTES` pass at once). The bucket may go
into debt: requests queue behind each other in order, as on a real link. Only requests are
paced (replies and probes are not); on real networks (or the namespace testbed with `tc`) leave
it off and let the network do the shaping. `set_rate` changes the rate while the robot runs
(the phases of `robotd.emulation`, which also use a burst of one Ethernet frame).

`FramePacer` starts frames on a fixed schedule (`--fps`) without drift, and does not try to catch
up in a burst when a slow frame made it late.
`TimelinePacer` starts frames at a recording's own times (a bag's record times, a video file's
frame rate: `FrameSource.next_offset_s`), with the same rule for late frames.

Both take an injectable clock so their arithmetic is tested without waiting.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

BITS_PER_BYTE = 8
BITS_PER_MBIT = 1_000_000
UPLINK_BURST_BYTES = 16 * 1024

Clock = Callable[[], float]


class TokenBucket:
    """A token bucket of `burst_bytes` filled at `rate_bytes_per_s`, allowed to go into debt.

    `reserve(n)` takes n bytes now and returns how long to wait before they have all gone
    through (0 when the bucket held them). Thread-safe.
    """

    def __init__(
        self, rate_bytes_per_s: float, burst_bytes: float, *, clock: Clock = time.monotonic
    ) -> None:
        if not (math.isfinite(rate_bytes_per_s) and rate_bytes_per_s > 0):
            raise ValueError(f"rate must be a positive number of bytes/s, got {rate_bytes_per_s}")
        if not (math.isfinite(burst_bytes) and burst_bytes >= 0):
            raise ValueError(f"burst must be a number of bytes >= 0, got {burst_bytes}")
        self.rate_bytes_per_s = float(rate_bytes_per_s)
        self.burst_bytes = float(burst_bytes)
        self._clock = clock
        self._tokens = float(burst_bytes)
        self._last = clock()
        self._lock = threading.Lock()

    @classmethod
    def from_mbit(
        cls,
        mbit_per_s: float,
        burst_bytes: float = UPLINK_BURST_BYTES,
        *,
        clock: Clock = time.monotonic,
    ) -> TokenBucket:
        """A bucket for a link of `mbit_per_s` megabits (10⁶ bits) per second."""
        if not (math.isfinite(mbit_per_s) and mbit_per_s > 0):
            raise ValueError(f"uplink rate must be a positive number of Mbit/s, got {mbit_per_s}")
        return cls(mbit_per_s * BITS_PER_MBIT / BITS_PER_BYTE, burst_bytes, clock=clock)

    def set_rate(self, rate_bytes_per_s: float) -> None:
        """Change the fill rate from now on (an emulated link that got faster or slower): what
        the bucket held or owed until now is counted at the old rate."""
        if not (math.isfinite(rate_bytes_per_s) and rate_bytes_per_s > 0):
            raise ValueError(f"rate must be a positive number of bytes/s, got {rate_bytes_per_s}")
        with self._lock:
            self._refill()
            self.rate_bytes_per_s = float(rate_bytes_per_s)

    def _refill(self) -> None:
        now = self._clock()
        elapsed = max(0.0, now - self._last)
        self._last = now
        self._tokens = min(self.burst_bytes, self._tokens + elapsed * self.rate_bytes_per_s)

    @property
    def tokens(self) -> float:
        """Bytes that would pass at once now (negative: the debt still queued)."""
        with self._lock:
            self._refill()
            return self._tokens

    def delay_for(self, nbytes: int) -> float:
        """How long `reserve(nbytes)` would make the caller wait now, without reserving."""
        with self._lock:
            self._refill()
            return max(0.0, (nbytes - self._tokens) / self.rate_bytes_per_s)

    def reserve(self, nbytes: int) -> float:
        """Take `nbytes` now; seconds until they have gone through the bucket."""
        if nbytes < 0:
            raise ValueError(f"cannot reserve a negative number of bytes ({nbytes})")
        with self._lock:
            self._refill()
            self._tokens -= nbytes
            return max(0.0, -self._tokens / self.rate_bytes_per_s)


class FramePacer:
    """Frame start times at `fps` on a fixed grid (no drift); a frame that starts more than one
    period late restarts the grid instead of bursting to catch up."""

    def __init__(self, fps: float | None, *, clock: Clock = time.monotonic) -> None:
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps}")
        self.period_s = 1.0 / fps if fps else 0.0
        self._clock = clock
        self._next: float | None = None

    def delay(self) -> float:
        """Seconds to wait before the next frame starts; call once per frame."""
        now = self._clock()
        if self.period_s <= 0:
            return 0.0
        if self._next is None or now - self._next > self.period_s:
            self._next = now  # first frame, or late by more than a period: restart the grid
        wait = max(0.0, self._next - now)
        self._next += self.period_s
        return wait

    def wait(self, stop: threading.Event) -> bool:
        """Wait for the next frame's start; False when `stop` was set meanwhile."""
        delay = self.delay()
        if delay > 0:
            return not stop.wait(delay)
        return not stop.is_set()


class TimelinePacer:
    """Frame start times on a source's own timeline: the frame at offset t (seconds from the
    first frame, `offset()` asked once per frame) starts t after the first one did. A frame more
    than its gap to the previous one late (a slow frame) moves the timeline to now instead of
    bursting to catch up, as `FramePacer` restarts its grid."""

    def __init__(
        self, offset: Callable[[], float | None], *, clock: Clock = time.monotonic
    ) -> None:
        self._offset = offset
        self._clock = clock
        self._origin: float | None = None  # when, on the clock, offset 0 is
        self._last: float | None = None

    def delay(self) -> float:
        """Seconds to wait before the next frame starts (0 where the source has no next
        frame: its read says so); call once per frame."""
        offset = self._offset()
        now = self._clock()
        if offset is None or not math.isfinite(offset):
            return 0.0
        gap = 0.0 if self._last is None else max(0.0, offset - self._last)
        self._last = offset
        if self._origin is None or now - (self._origin + offset) > gap:
            self._origin = now - offset  # first frame, or late by more than a gap: move
        return max(0.0, self._origin + offset - now)
