"""The cloud daemon's workers (over its fair queue: refused at once when full, slots released
whatever a run does, admitted work finished at shutdown) and its timer thread; fault settings."""

from __future__ import annotations

import threading
import time

import pytest

from cloudd.batch_queue import Batch, BatchPolicy, FairQueue, Pending, Refusal
from cloudd.faults import FaultInjector, describe
from cloudd.workers import BatchWorkers, DelayedActions
from common.wire.registry import FaultSpec

WAIT_S = 5.0
FAR_S = 60.0


def pending(robot: str, n: int) -> Pending[int]:
    now = time.monotonic()
    return Pending(robot=robot, group=0, arrived=now, deadline_at=now + FAR_S, payload=n)


def unbatched(slots: int, per_robot: int = 8) -> FairQueue[int]:
    return FairQueue(BatchPolicy((1,), 0.0, per_robot), slots=slots)


def test_a_full_queue_refuses_at_once_and_slots_come_back() -> None:
    queue = unbatched(slots=2)
    release = threading.Event()
    started = threading.Event()
    ran: list[int] = []

    def run(batch: Batch[int]) -> None:
        started.set()
        release.wait(WAIT_S)
        ran.extend(item.payload for item in batch.items)

    workers = BatchWorkers(queue, run, workers=1)
    workers.start()
    try:
        assert queue.offer(pending("a", 1)) is None
        assert started.wait(WAIT_S)
        assert queue.offer(pending("b", 2)) is None, "the waiting slot"
        t0 = time.monotonic()
        assert queue.offer(pending("c", 3)) is Refusal.FULL
        assert time.monotonic() - t0 < 0.1, "refusal does not wait"
        assert (queue.load, queue.capacity) == (2, 2)
        release.set()
        assert workers.shutdown(WAIT_S)
        assert sorted(ran) == [1, 2] and queue.load == 0
        assert queue.offer(pending("a", 4)) is Refusal.CLOSED
    finally:
        release.set()
        workers.shutdown(WAIT_S)


def test_a_failing_run_releases_its_slots_and_the_worker_goes_on() -> None:
    queue = unbatched(slots=1)
    ran = threading.Event()
    calls: list[int] = []

    def run(batch: Batch[int]) -> None:
        calls.append(batch.items[0].payload)
        if len(calls) == 1:
            raise RuntimeError("run bug")
        ran.set()

    workers = BatchWorkers(queue, run, workers=1)
    workers.start()
    try:
        assert queue.offer(pending("a", 1)) is None
        deadline = time.monotonic() + WAIT_S
        while queue.offer(pending("a", 2)) is not None:  # admitted once the first slot is free
            assert time.monotonic() < deadline, "the failed run's slot never came back"
        assert ran.wait(WAIT_S) and calls == [1, 2]
    finally:
        workers.shutdown(WAIT_S)


def test_shutdown_finishes_admitted_requests_then_refuses() -> None:
    queue = unbatched(slots=3)
    done: list[int] = []
    workers = BatchWorkers(queue, lambda b: done.extend(i.payload for i in b.items), workers=1)
    for n in range(3):
        assert queue.offer(pending(f"r{n}", n)) is None
    workers.start()
    assert workers.shutdown(WAIT_S)
    assert sorted(done) == [0, 1, 2]
    assert queue.offer(pending("r0", 9)) is Refusal.CLOSED


def test_shutdown_gives_up_on_a_stuck_run_after_its_timeout() -> None:
    queue = unbatched(slots=1)
    release = threading.Event()
    workers = BatchWorkers(queue, lambda b: release.wait(WAIT_S) and None, workers=1)
    workers.start()
    assert queue.offer(pending("a", 1)) is None
    t0 = time.monotonic()
    assert not workers.shutdown(0.1)
    assert time.monotonic() - t0 < 1.0
    release.set()


def test_worker_count_is_checked() -> None:
    with pytest.raises(ValueError):
        BatchWorkers(unbatched(slots=1), lambda b: None, workers=0)


def test_delayed_actions_run_in_due_order_after_their_delay() -> None:
    timer = DelayedActions()
    timer.start()
    seen: list[tuple[str, float]] = []
    done = threading.Event()
    t0 = time.monotonic()

    def mark(name: str) -> None:
        seen.append((name, time.monotonic() - t0))
        if len(seen) == 2:
            done.set()

    try:
        timer.call_later(0.15, lambda: mark("late"))
        timer.call_later(0.05, lambda: mark("early"))
        assert done.wait(WAIT_S)
        assert [name for name, _ in seen] == ["early", "late"]
        assert seen[0][1] >= 0.05 and seen[1][1] >= 0.15
    finally:
        timer.flush_and_stop()


def test_flush_runs_pending_actions_now_and_later_ones_at_once() -> None:
    timer = DelayedActions()
    timer.start()
    ran: list[str] = []
    timer.call_later(60.0, lambda: ran.append("pending"))
    assert timer.pending == 1
    t0 = time.monotonic()
    timer.flush_and_stop()
    assert ran == ["pending"] and time.monotonic() - t0 < 1.0
    timer.call_later(60.0, lambda: ran.append("after stop"))
    assert ran == ["pending", "after stop"]


def test_fault_injector_drops_with_its_probability() -> None:
    faults = FaultInjector(FaultSpec(drop=0.25), seed=1)
    drops = sum(faults.drop_now() for _ in range(4000))
    assert 800 <= drops <= 1200
    faults.set(FaultSpec())
    assert not any(faults.drop_now() for _ in range(100))
    assert FaultInjector(FaultSpec(drop=1.0)).drop_now()


def test_fault_descriptions() -> None:
    assert describe(FaultSpec()) == "none"
    assert (
        describe(FaultSpec(delay_ms=250, drop=0.1, stall=True)) == "delay 250 ms, drop 0.1, stall"
    )
