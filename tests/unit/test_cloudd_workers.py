"""The cloud daemon's worker pool (bounded, busy at once) and its timer thread; fault settings."""

from __future__ import annotations

import threading
import time

import pytest

from cloudd.faults import FaultInjector, describe
from cloudd.workers import DelayedActions, WorkerPool
from common.wire.registry import FaultSpec

WAIT_S = 5.0


def test_pool_refuses_at_once_when_every_slot_is_taken() -> None:
    pool = WorkerPool(workers=1, queue=1)
    release = threading.Event()
    started = threading.Event()
    ran: list[int] = []

    def job(n: int) -> None:
        started.set()
        release.wait(WAIT_S)
        ran.append(n)

    try:
        assert pool.try_submit(lambda: job(1))
        assert started.wait(WAIT_S)
        assert pool.try_submit(lambda: job(2)), "the queue slot"
        t0 = time.monotonic()
        assert not pool.try_submit(lambda: job(3)), "full: refused"
        assert time.monotonic() - t0 < 0.1, "refusal does not wait"
        assert (pool.load, pool.capacity) == (2, 2)
        release.set()
        assert pool.wait_idle(WAIT_S)
        assert sorted(ran) == [1, 2] and pool.load == 0
        assert pool.try_submit(lambda: None), "slots come back"
    finally:
        release.set()
        pool.shutdown(WAIT_S)


def test_a_failing_job_releases_its_slot() -> None:
    pool = WorkerPool(workers=1, queue=0)

    def boom() -> None:
        raise RuntimeError("job bug")

    try:
        assert pool.try_submit(boom)
        assert pool.wait_idle(WAIT_S)
        assert pool.load == 0
    finally:
        pool.shutdown(WAIT_S)


def test_shutdown_lets_admitted_jobs_finish_then_refuses() -> None:
    pool = WorkerPool(workers=1, queue=2)
    done: list[int] = []
    for n in range(3):
        assert pool.try_submit(lambda n=n: done.append(n))  # type: ignore[misc]
    assert pool.shutdown(WAIT_S)
    assert sorted(done) == [0, 1, 2]
    assert not pool.try_submit(lambda: None)


def test_shutdown_gives_up_on_a_stuck_job_after_its_timeout() -> None:
    pool = WorkerPool(workers=1, queue=0)
    release = threading.Event()
    assert pool.try_submit(lambda: release.wait(WAIT_S) and None)
    t0 = time.monotonic()
    assert not pool.shutdown(0.1)
    assert time.monotonic() - t0 < 1.0
    release.set()


@pytest.mark.parametrize(("workers", "queue"), [(0, 1), (1, -1)])
def test_pool_sizes_are_checked(workers: int, queue: int) -> None:
    with pytest.raises(ValueError):
        WorkerPool(workers=workers, queue=queue)


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
