"""The robot's in-flight window (`robotd.frame_path.pipeline`): at most N frames in flight, frames
finished oldest first when ready together, each at its own reply or deadline, stale results dropped
and counted, and with N = 1 the loop without pipelining (each frame finished before the next
starts).

Calls are scripted: the test settles them (from its own thread, or from a timer thread where a
wait must be woken); deadlines are real perf_counter times only where a deadline is what is tested.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import pytest

from robotd.frame_path.pipeline import FramePipeline, InFlight, ResultOrder
from robotd.telemetry import EXTRA_FIELDS, RunSummary, jsonl_object

FAR_S = 60.0
"""A deadline no test reaches: those calls settle by a reply."""
SHORT_DEADLINE_S = 0.05
REPLY_AFTER_S = 0.02
WAIT_S = 5.0


class ScriptedCall:
    """A request in flight that settles when the test says so."""

    def __init__(self, deadline_in_s: float = FAR_S) -> None:
        self.deadline_at = time.perf_counter() + deadline_in_s
        self._settled = threading.Event()
        self._listeners: list[threading.Event] = []
        self.cancelled = False

    @property
    def settled(self) -> bool:
        return self._settled.is_set()

    def settle(self) -> None:
        self._settled.set()
        for event in self._listeners:
            event.set()

    def notify(self, event: threading.Event) -> None:
        self._listeners.append(event)
        if self.settled:
            event.set()

    def cancel(self) -> None:
        self.cancelled = True


@dataclass
class Loop:
    """The frame loop's side: frames finished, and what was applied, in order."""

    max_in_flight: int
    stop: threading.Event = field(default_factory=threading.Event)
    order: ResultOrder = field(default_factory=ResultOrder)
    finished: list[int] = field(default_factory=list)
    applied: list[int] = field(default_factory=list)
    stale: list[int] = field(default_factory=list)
    timed_out: list[int] = field(default_factory=list)
    pipeline: FramePipeline[ScriptedCall] = field(init=False)

    def __post_init__(self) -> None:
        self.pipeline = FramePipeline(self.max_in_flight, self.finish, self.stop)

    def finish(self, item: InFlight[ScriptedCall]) -> None:
        self.finished.append(item.n)
        if not item.work.settled:  # the deadline passed: the robot finishes the frame itself
            self.timed_out.append(item.n)
        (self.applied if self.order.admit(item.n) else self.stale).append(item.n)

    def send(self, n: int, call: ScriptedCall) -> None:
        self.pipeline.submit(InFlight(n, call, call))


def test_result_order_applies_newer_frames_and_counts_the_older_ones() -> None:
    order = ResultOrder()
    assert [order.admit(n) for n in (0, 2, 1, 3, 3, 5)] == [True, True, False, True, False, True]
    assert order.newest == 5 and order.stale_dropped == 2


def test_frames_ready_together_are_finished_oldest_first() -> None:
    """Replies of frames 2, 0, 1 arrive while the loop is busy: all three are applied, in order,
    none is stale."""
    loop = Loop(4)
    calls = [ScriptedCall() for _ in range(3)]
    for n, call in enumerate(calls):
        loop.send(n, call)
    assert len(loop.pipeline) == 3 and loop.finished == []
    for n in (2, 0):
        calls[n].settle()
    calls[1].settle()
    assert loop.pipeline.idle(0.0)
    assert loop.applied == [0, 1, 2] and loop.stale == [] and len(loop.pipeline) == 0


def test_an_older_result_after_a_newer_one_is_dropped_and_counted() -> None:
    """Frame 1's reply is applied before frame 0's arrives: frame 0 is finished (no frame lost)
    but its result is stale, never applied after frame 1's."""
    loop = Loop(3)
    old, new = ScriptedCall(), ScriptedCall()
    loop.send(0, old)
    loop.send(1, new)
    new.settle()
    assert loop.pipeline.idle(0.0)
    assert loop.applied == [1]
    old.settle()
    assert loop.pipeline.idle(0.0)
    assert loop.finished == [1, 0] and loop.applied == [1] and loop.stale == [0]
    assert loop.order.stale_dropped == 1


def test_each_frame_keeps_its_own_deadline() -> None:
    """A call that never settles is finished at its own deadline (the robot's fallback); the
    frames around it are finished at their replies, and none is lost. Frame 2's reply came
    first, so frame 1's fallback result is stale."""
    loop = Loop(4)
    started = time.perf_counter()
    calls = [ScriptedCall(), ScriptedCall(SHORT_DEADLINE_S), ScriptedCall()]
    for n, call in enumerate(calls):
        loop.send(n, call)

    # Frames 0 and 2 answered in that order (two timers of the same delay may fire either way).
    def answer() -> None:
        calls[0].settle()
        calls[2].settle()

    threading.Timer(REPLY_AFTER_S, answer).start()
    loop.pipeline.drain()
    assert time.perf_counter() - started >= SHORT_DEADLINE_S
    assert loop.finished == [0, 2, 1] and loop.timed_out == [1]
    assert loop.applied == [0, 2] and loop.stale == [1]


def test_a_silent_frame_is_finished_at_its_deadline_while_others_wait_for_replies() -> None:
    loop = Loop(3)
    silent = ScriptedCall(SHORT_DEADLINE_S)
    late = ScriptedCall()
    loop.send(0, silent)
    loop.send(1, late)
    started = time.perf_counter()
    # Nothing settles: the wait for the next frame's start finishes frame 0 at its deadline.
    assert loop.pipeline.idle(SHORT_DEADLINE_S * 4)
    assert loop.finished == [0] and loop.timed_out == [0]
    assert time.perf_counter() - started >= SHORT_DEADLINE_S
    late.settle()
    loop.pipeline.drain()
    assert loop.finished == [0, 1] and loop.applied == [0, 1] and loop.timed_out == [0]


def test_a_full_window_waits_for_a_reply_before_the_next_frame() -> None:
    """With N in flight, `submit` returns only once a frame could be finished: never more than
    N at once. The reply comes from another thread and wakes the wait."""
    loop = Loop(2)
    first, second = ScriptedCall(), ScriptedCall()
    loop.send(0, first)
    threading.Timer(REPLY_AFTER_S, first.settle).start()
    loop.send(1, second)  # full: waits for frame 0's reply
    assert loop.finished == [0] and len(loop.pipeline) == 1 and loop.pipeline.peak == 2
    second.settle()
    loop.pipeline.drain()
    assert loop.applied == [0, 1]


def test_one_in_flight_is_the_loop_without_pipelining() -> None:
    """N = 1: each frame is finished inside its own `submit`, before the next frame starts, in
    frame order; nothing is ever stale (today's loop: send, wait, finish, next)."""
    loop = Loop(1)
    for n in range(5):
        call = ScriptedCall(SHORT_DEADLINE_S if n == 2 else FAR_S)
        if n != 2:
            threading.Timer(REPLY_AFTER_S, call.settle).start()
        assert loop.pipeline.idle(0.0)
        loop.send(n, call)
        assert loop.finished == list(range(n + 1)) and len(loop.pipeline) == 0
    assert loop.applied == [0, 1, 2, 3, 4] and loop.timed_out == [2]
    assert loop.pipeline.peak == 1 and loop.order.stale_dropped == 0


def test_stop_finishes_every_frame_in_flight_at_once() -> None:
    """A stop while frames are in flight: the wait returns False and every frame is finished
    (the robot's fallback with reason `stopped`), none lost."""
    loop = Loop(4)
    for n in range(3):
        loop.send(n, ScriptedCall())
    threading.Timer(REPLY_AFTER_S, loop.stop.set).start()
    assert not loop.pipeline.idle(WAIT_S)
    loop.pipeline.drain()
    assert loop.finished == [0, 1, 2]


def test_cancel_lets_go_of_calls_in_flight() -> None:
    loop = Loop(3)
    calls = [ScriptedCall(), ScriptedCall()]
    for n, call in enumerate(calls):
        loop.send(n, call)
    loop.pipeline.cancel()
    assert all(c.cancelled for c in calls) and len(loop.pipeline) == 0 and loop.finished == []


def test_max_in_flight_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_in_flight"):
        FramePipeline[ScriptedCall](0, lambda item: None, threading.Event())


def test_stale_frames_are_counted_in_the_summary_and_the_jsonl() -> None:
    from common.wire.telemetry import TelemetryRecord

    summary = RunSummary("robot-1")
    for n, stale in ((0, False), (2, False), (1, True)):
        record = TelemetryRecord(
            robot="robot-1",
            frame=n,
            action="cut:0",
            bytes_up=10,
            bytes_down=10,
            prefix_s=0.0,
            transfer_s=0.01,
            cloud_s=0.01,
            suffix_local_s=0.0,
            latency_s=0.02,
            robot_cpu_s=0.0,
            energy_j=0.0,
            deployment="edge-1",
            fallback=False,
            reason=None,
            stale=stale,
        )
        summary.add(record, hedged=False, served_by="cloud")
        obj = jsonl_object(record, entropy=0.5, hedged=False, served_by="cloud")
        assert set(EXTRA_FIELDS) <= set(obj) and obj["stale"] is stale
        assert TelemetryRecord.from_wire(record.to_wire()).stale is stale
    assert summary.to_json()["stale_dropped"] == 1 and summary.answered == 3
