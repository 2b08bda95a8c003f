"""Frames in flight on the robot: up to `max_in_flight` offloaded frames whose cloud calls are
under way at once, and the order in which frames' results are applied.

With one frame in flight (the default) the robot sends a frame and waits for its result before it
grabs the next one: while the cloud computes and the reply travels back, the uplink is idle. With
N > 1 the frame loop sends frame k while frames k-1, k-2... are still in flight, up to N at once
(the navigation paper's pipelining: the transmission of frame k overlaps the processing of k-1).

Each frame keeps its own deadline and its local finish: a call that fails or is not answered in
time is finished on the robot, as without pipelining, so no frame is lost. Results are *applied*
(a frame's outputs handed on) in frame order: a result older than the newest one already applied
would take its consumer back in time, so `ResultOrder` drops it and counts it (`stale`), and the
frame keeps its telemetry record and still feeds the policy.

`FramePipeline` is what the loop asks: `idle(delay_s)` waits for the next frame's start while
finishing frames whose calls settle meanwhile; `submit` adds an offloaded frame and, with N in
flight, waits until one can be finished; `drain` finishes the rest. Frames ready at the same
moment are finished oldest first. With N = 1 `submit` returns once its frame is finished: the
loop without pipelining.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

from robotd.frame_path.offload import FINISH_GRACE_S, STOP_POLL_S

W = TypeVar("W")
Clock = Callable[[], float]


class Call(Protocol):
    """What the window needs of a request in flight (`robotd.frame_path.offload.CloudCall` is
    one)."""

    @property
    def settled(self) -> bool: ...

    @property
    def deadline_at(self) -> float: ...

    def notify(self, event: threading.Event) -> None: ...

    def cancel(self) -> None: ...


@dataclass(frozen=True)
class InFlight(Generic[W]):
    """Frame `n`, its cloud call, and what the loop needs to finish it (`work`)."""

    n: int
    call: Call
    work: W


class ResultOrder:
    """Results are applied in frame order. `admit(n)`: True when frame `n` is newer than every
    frame applied so far (it becomes the newest), False when it is stale (`stale_dropped`)."""

    def __init__(self) -> None:
        self.newest: int | None = None
        self.stale_dropped = 0

    def admit(self, n: int) -> bool:
        if self.newest is not None and n <= self.newest:
            self.stale_dropped += 1
            return False
        self.newest = n
        return True


class FramePipeline(Generic[W]):
    """Up to `max_in_flight` frames in flight; `finish(item)` is called once per frame, in the
    caller's thread, when its call has settled, its deadline (plus `grace_s`) has passed or `stop`
    is set. Every wait is bounded by the calls' deadlines, and cut short by `stop`."""

    def __init__(
        self,
        max_in_flight: int,
        finish: Callable[[InFlight[W]], None],
        stop: threading.Event,
        *,
        grace_s: float = FINISH_GRACE_S,
        clock: Clock = time.perf_counter,
    ) -> None:
        if max_in_flight < 1:
            raise ValueError(f"max_in_flight must be at least 1, got {max_in_flight}")
        self.max_in_flight = max_in_flight
        self._finish = finish
        self._stop = stop
        self._grace_s = grace_s
        self._clock = clock
        self._items: list[InFlight[W]] = []
        # Set by every call in the window when it settles: one event to wait for the first.
        self._wake = threading.Event()
        self.peak = 0  # the most frames that were in flight at once

    def __len__(self) -> int:
        return len(self._items)

    @property
    def full(self) -> bool:
        return len(self._items) >= self.max_in_flight

    def idle(self, delay_s: float) -> bool:
        """Wait `delay_s` (until the next frame starts), finishing the frames that become ready
        meanwhile; False when `stop` is set."""
        until = self._clock() + delay_s
        while True:  # bounded by `until` (or the stop flag)
            self._finish_ready()
            if self._stop.is_set():
                return False
            if self._clock() >= until:
                return True
            self._wait(until)

    def submit(self, item: InFlight[W]) -> None:
        """Add a frame whose call is under way; with the window full, wait until a frame can be
        finished (so at most `max_in_flight` are ever in flight)."""
        self._items.append(item)
        item.call.notify(self._wake)
        self.peak = max(self.peak, len(self._items))
        while self.full:  # bounded: every call is ready by its deadline
            self._wait(math.inf)
            self._finish_ready()

    def drain(self) -> None:
        """Finish every frame still in flight (at their replies or deadlines)."""
        while self._items:  # bounded: every call is ready by its deadline
            self._wait(math.inf)
            self._finish_ready()

    def cancel(self) -> None:
        """Let go of the calls still in flight (shutdown after a failed loop); not finished."""
        for item in self._items:
            item.call.cancel()
        self._items.clear()

    def _ready(self, item: InFlight[W]) -> bool:
        call = item.call
        return (
            call.settled or self._stop.is_set() or self._clock() >= call.deadline_at + self._grace_s
        )

    def _finish_ready(self) -> None:
        for item in sorted((i for i in self._items if self._ready(i)), key=lambda i: i.n):
            self._items.remove(item)
            self._finish(item)

    def _wait(self, until: float) -> None:
        """Until a frame is ready, the perf_counter time `until`, or `stop`."""
        while True:  # bounded by the earliest deadline (or the stop flag)
            self._wake.clear()
            if self._stop.is_set() or any(self._ready(i) for i in self._items):
                return
            limit = min([until, *(i.call.deadline_at + self._grace_s for i in self._items)])
            left = limit - self._clock()
            if left <= 0:
                return
            self._wake.wait(min(left, STOP_POLL_S))
