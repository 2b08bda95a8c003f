"""Heavy robots' batches at a low OS priority (`cloudd.cpu_lanes`): who counts as heavy, the
low-priority thread, and the workers handing a heavy robot's batch to it."""

from __future__ import annotations

import os
import threading
import time

import pytest

from cloudd.batch_queue import Batch, BatchPolicy, FairQueue, Pending
from cloudd.cpu_lanes import (
    HEAVY_FACTOR,
    LOW_NICE,
    LowPriorityThread,
    UsageMeter,
    lanes_supported,
)
from cloudd.workers import BatchWorkers

WAIT_S = 5.0
FAR_S = 60.0

linux_only = pytest.mark.skipif(not lanes_supported(), reason="per-thread nice is Linux's")


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_robot_alone_or_robots_alike_are_never_heavy() -> None:
    meter = UsageMeter(clock=Clock())
    meter.record(["a"], 5.0)
    assert not meter.heavy(["a"]), "alone: nobody to yield to"
    meter.record(["b"], 5.0)
    assert not meter.heavy(["a"]) and not meter.heavy(["b"])
    assert not meter.heavy([]), "an empty batch"


def test_the_robot_using_far_more_than_the_mean_is_heavy_and_the_light_one_not() -> None:
    meter = UsageMeter(clock=Clock())
    meter.record(["hog"], 0.9)
    meter.record(["light"], 0.1)
    assert meter.heavy(["hog"]) and not meter.heavy(["light"])
    assert not meter.heavy(["hog", "light"]), "a batch with a light robot runs at full priority"
    # Two robots: heavy means more than HEAVY_FACTOR x their mean.
    for a, heavy in ((0.25, False), (0.35, True)):
        meter = UsageMeter(clock=Clock())
        meter.record(["a"], a)
        meter.record(["b"], 0.1)
        assert (a > HEAVY_FACTOR * (a + 0.1) / 2) is heavy
        assert meter.heavy(["a"]) is heavy, a


def test_a_batchs_time_is_split_between_its_robots() -> None:
    meter = UsageMeter(clock=Clock())
    meter.record(["a", "b"], 1.0)
    assert meter.usage() == pytest.approx({"a": 0.5, "b": 0.5})


def test_use_decays_and_a_silent_robot_is_forgotten() -> None:
    clock = Clock()
    meter = UsageMeter(half_life_s=1.0, clock=clock)
    meter.record(["hog"], 1.0)
    meter.record(["light"], 0.05)
    clock.now = 1.0
    assert meter.usage()["hog"] == pytest.approx(0.5)
    assert meter.heavy(["hog"])
    clock.now = 30.0  # the hog stopped long ago; the light robot sends on
    meter.record(["light"], 0.05)
    assert set(meter.usage()) == {"light"}
    meter.record(["hog"], 0.05)
    assert not meter.heavy(["hog"]), "back, it starts from nothing"


def test_the_meter_refuses_settings_that_make_no_sense() -> None:
    with pytest.raises(ValueError, match="half_life_s"):
        UsageMeter(half_life_s=0)
    with pytest.raises(ValueError, match="heavy_factor"):
        UsageMeter(heavy_factor=1.0)


def thread_nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


def thread_policy() -> int:
    return os.sched_getscheduler(threading.get_native_id())


@linux_only
def test_the_low_priority_thread_runs_idle_and_hands_back_results_and_errors() -> None:
    low = LowPriorityThread("test-low")
    try:
        before = (thread_nice(), thread_policy())
        assert low.call(lambda: (thread_nice(), thread_policy())) == (LOW_NICE, os.SCHED_IDLE)
        assert (thread_nice(), thread_policy()) == before, "the caller keeps its priority"

        def fail() -> None:
            raise RuntimeError("run bug")

        with pytest.raises(RuntimeError, match="run bug"):
            low.call(fail)
        assert low.call(lambda: 41 + 1) == 42, "an error does not end the thread"
    finally:
        low.stop()


def pending(robot: str, n: int) -> Pending[int]:
    now = time.monotonic()
    return Pending(robot=robot, group=0, arrived=now, deadline_at=now + FAR_S, payload=n)


@linux_only
def test_workers_run_a_heavy_robots_batch_at_low_priority_and_a_light_ones_at_full() -> None:
    clock = Clock()
    meter = UsageMeter(clock=clock)
    meter.record(["hog"], 0.9)
    meter.record(["light"], 0.1)
    queue: FairQueue[int] = FairQueue(BatchPolicy((1,), 0.0, 4), slots=4)
    policy: dict[int, int] = {}
    done = threading.Event()

    def run(batch: Batch[int]) -> None:
        policy[batch.items[0].payload] = thread_policy()
        if len(policy) == 2:
            done.set()

    workers = BatchWorkers(queue, run, workers=1, meter=meter)
    workers.start()
    try:
        assert queue.offer(pending("hog", 1)) is None
        assert queue.offer(pending("light", 2)) is None
        assert done.wait(WAIT_S)
        assert policy[1] == os.SCHED_IDLE and policy[2] == thread_policy() != os.SCHED_IDLE, policy
        assert workers.low_runs == 1
        assert meter.usage()["hog"] > 0.9, "the run's time is counted"
    finally:
        assert workers.shutdown(WAIT_S)


def test_workers_without_a_meter_run_every_batch_on_their_own_thread() -> None:
    queue: FairQueue[int] = FairQueue(BatchPolicy((1,), 0.0, 4), slots=4)
    threads: list[str] = []
    done = threading.Event()

    def run(batch: Batch[int]) -> None:
        threads.append(threading.current_thread().name)
        done.set()

    workers = BatchWorkers(queue, run, workers=1, name="w")
    workers.start()
    try:
        assert queue.offer(pending("hog", 1)) is None
        assert done.wait(WAIT_S)
        assert threads == ["w-0"] and workers.low_runs == 0
    finally:
        assert workers.shutdown(WAIT_S)
