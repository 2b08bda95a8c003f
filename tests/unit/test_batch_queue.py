"""The cloud daemon's fair queue (cloudd.batch_queue), driven by a hand-moved clock: round robin
between robots, the per-robot in-flight limit, batches of one cut formed in turn order, the
queue delay, deadlines (never held past one, expired ones handed back) and the learned costs."""

from __future__ import annotations

import threading
import time

import pytest

from cloudd.batch_queue import (
    Batch,
    BatchCosts,
    BatchPolicy,
    FairQueue,
    Pending,
    Refusal,
)
from common.config import BatchingConfig

FAR_S = 60.0
DELAY_S = 0.010
WAIT_S = 5.0


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def make_queue(
    clock: Clock,
    sizes: tuple[int, ...] = (1,),
    *,
    delay_s: float = DELAY_S,
    per_robot: int = 4,
    slots: int = 64,
    batchable: bool = True,
) -> FairQueue[str]:
    return FairQueue(
        BatchPolicy(sizes, delay_s, per_robot),
        slots=slots,
        clock=clock,
        batchable=lambda group: batchable,
    )


def offer(
    queue: FairQueue[str],
    clock: Clock,
    robot: str,
    n: int,
    *,
    cut: int = 0,
    budget_s: float = FAR_S,
) -> Pending[str]:
    item = Pending(
        robot=robot,
        group=cut,
        arrived=clock.now,
        deadline_at=clock.now + budget_s,
        payload=f"{robot}{n}",
    )
    assert queue.offer(item) is None, f"{robot}{n} refused"
    return item


def take(queue: FairQueue[str], clock: Clock) -> Batch[str]:
    batch = queue.poll(clock.now)
    assert isinstance(batch, Batch), f"expected a batch now, got {batch!r}"
    return batch


def names(batch: Batch[str]) -> list[str]:
    return [item.payload for item in batch.items]


def test_without_batching_robots_take_turns_whatever_their_backlog() -> None:
    clock = Clock()
    queue = make_queue(clock)
    for n in range(3):
        offer(queue, clock, "hog", n)
    offer(queue, clock, "b", 0)
    offer(queue, clock, "c", 0)
    order = [names(take(queue, clock)) for _ in range(5)]
    assert order == [["hog0"], ["b0"], ["c0"], ["hog1"], ["hog2"]]
    assert queue.poll(clock.now) is None


def test_a_robot_that_arrives_behind_a_backlog_is_served_next() -> None:
    """Regression guard: one FIFO queue made a robot wait for another robot's whole backlog."""
    clock = Clock()
    queue = make_queue(clock)
    offer(queue, clock, "hog", 0)
    offer(queue, clock, "hog", 1)
    assert names(take(queue, clock)) == ["hog0"]
    offer(queue, clock, "hog", 2)
    offer(queue, clock, "victim", 0)
    assert names(take(queue, clock)) == ["victim0"]


def test_per_robot_in_flight_limit_and_capacity_refuse_at_once() -> None:
    clock = Clock()
    queue = make_queue(clock, per_robot=2, slots=3)
    offer(queue, clock, "a", 0)
    offer(queue, clock, "a", 1)
    extra = Pending("a", 0, clock.now, clock.now + FAR_S, "a2")
    assert queue.offer(extra) is Refusal.ROBOT_LIMIT
    offer(queue, clock, "b", 0)
    assert queue.offer(Pending("c", 0, clock.now, clock.now + FAR_S, "c0")) is Refusal.FULL
    assert (queue.load, queue.in_flight("a"), queue.in_flight("b")) == (3, 2, 1)
    batch = take(queue, clock)
    assert queue.in_flight("a") == 2, "a running request still counts"
    queue.done(batch)
    assert (queue.load, queue.in_flight("a")) == (2, 1)
    assert queue.offer(extra) is None


def test_a_batch_gathers_one_cut_round_robin_in_each_robots_order() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,))
    for n in range(3):
        offer(queue, clock, "a", n)
    offer(queue, clock, "b", 0)
    offer(queue, clock, "c", 0, cut=3)  # another cut: another batch
    offer(queue, clock, "d", 0)
    clock.now += DELAY_S
    first = take(queue, clock)
    assert first.group == 0
    assert names(first) == ["a0", "b0", "d0", "a1", "a2"]
    second = take(queue, clock)
    assert (second.group, names(second)) == (3, ["c0"])


def test_a_robot_whose_head_is_another_cut_keeps_its_order() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,))
    offer(queue, clock, "a", 0, cut=0)
    offer(queue, clock, "b", 0, cut=2)
    offer(queue, clock, "b", 1, cut=0)  # behind b's cut-2 request: not taken before it
    clock.now += DELAY_S
    assert names(take(queue, clock)) == ["a0"]
    assert names(take(queue, clock)) == ["b0"]
    assert names(take(queue, clock)) == ["b1"]


def test_the_largest_batch_leaves_at_once_and_the_rest_waits_for_whom_may_come() -> None:
    clock = Clock()
    queue = make_queue(clock, (2,))
    for robot in "abc":
        offer(queue, clock, robot, 0)
    first = take(queue, clock)
    assert names(first) == ["a0", "b0"], "a preferred size leaves without waiting"
    assert names(take(queue, clock)) == ["c0"], "a and b cannot send more: c goes alone"
    offer(queue, clock, "c", 1)
    queue.done(first)
    # Now a and b were heard from and have nothing admitted: c waits for them.
    wait = queue.poll(clock.now)
    assert isinstance(wait, float) and 0 < wait <= DELAY_S + 1e-9


def test_a_preferred_size_leaves_without_waiting_for_the_largest() -> None:
    clock = Clock()
    queue = make_queue(clock, (2, 8))
    for robot in "abcde":
        offer(queue, clock, robot, 0)
    assert names(take(queue, clock)) == ["a0", "b0"]
    assert names(take(queue, clock)) == ["c0", "d0"]


def test_a_robot_alone_never_waits_for_a_batch() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,))
    offer(queue, clock, "a", 0)
    assert names(take(queue, clock)) == ["a0"]


def test_a_batch_waits_for_robots_heard_from_lately_at_most_the_queue_delay() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,))
    for robot in "abc":
        offer(queue, clock, robot, 0)
    while queue.load:  # all three answered: each is expected to send again
        batch = queue.poll(clock.now)
        if isinstance(batch, Batch):
            queue.done(batch)
        clock.now += DELAY_S
    clock.now += 0.5
    offer(queue, clock, "a", 1)
    wait = queue.poll(clock.now)
    assert wait == pytest.approx(DELAY_S), "b and c may come"
    clock.now += DELAY_S / 2
    offer(queue, clock, "b", 1)
    wait = queue.poll(clock.now)
    assert wait == pytest.approx(DELAY_S / 2), "the oldest request's delay counts"
    clock.now += DELAY_S / 2
    assert names(take(queue, clock)) == ["a1", "b1"]
    clock.now += 2.0  # c went quiet: nobody is waited for any more
    offer(queue, clock, "a", 2)
    assert names(take(queue, clock)) == ["a2"]


def test_a_request_that_cannot_afford_the_delay_is_not_held() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,), delay_s=0.050)
    offer(queue, clock, "b", 0)
    queue.done(take(queue, clock))  # b was heard from: a batch would wait for it
    queue.costs.record(0, 1, 0.004)
    # 50 ms of delay + 8 ms for a batch of 2 fit a 100 ms budget with a quarter left over...
    offer(queue, clock, "a", 0, budget_s=0.100)
    assert queue.poll(clock.now) == pytest.approx(0.050)
    clock.now += 0.050
    assert names(take(queue, clock)) == ["a0"]
    # ...not a 70 ms one (58 ms > 75% of 70): it runs at once instead of waiting part way.
    offer(queue, clock, "a", 1, budget_s=0.070)
    assert names(take(queue, clock)) == ["a1"]


def test_expired_requests_are_handed_back_not_run() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,))
    offer(queue, clock, "a", 0, budget_s=0.005)
    offer(queue, clock, "b", 0)
    offer(queue, clock, "b", 1, budget_s=0.005)
    clock.now += 0.006
    first = take(queue, clock)
    assert first.items == [] and sorted(i.payload for i in first.expired) == ["a0", "b1"]
    queue.done(first)
    assert queue.in_flight("a") == 0 and queue.load == 1
    clock.now += DELAY_S  # b0 waits for a (heard from, nothing admitted), then goes
    assert names(take(queue, clock)) == ["b0"]


def test_an_unbatchable_cut_runs_one_request_at_a_time() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,), batchable=False)
    for robot in "abc":
        offer(queue, clock, robot, 0)
    assert [names(take(queue, clock)) for _ in range(3)] == [["a0"], ["b0"], ["c0"]]


def test_closing_hands_out_what_was_admitted_without_waiting() -> None:
    clock = Clock()
    queue = make_queue(clock, (8,))
    offer(queue, clock, "b", 0)
    queue.done(take(queue, clock))
    offer(queue, clock, "a", 0)
    assert isinstance(queue.poll(clock.now), float), "would wait for b"
    queue.close()
    assert names(take(queue, clock)) == ["a0"]
    assert queue.get(timeout_s=0) is None
    assert queue.offer(Pending("a", 0, clock.now, clock.now + 1, "a1")) is Refusal.CLOSED


def test_get_wakes_up_when_a_batch_fills() -> None:
    queue: FairQueue[str] = FairQueue(BatchPolicy((2,), FAR_S, 4), slots=8)
    now = time.monotonic()
    for robot in "ab":
        queue.offer(Pending(robot, 0, now, now + 10 * FAR_S, f"{robot}0"))
    first = queue.get(timeout_s=WAIT_S)
    assert first is not None and names(first) == ["a0", "b0"]
    queue.done(first)  # both heard from, nothing admitted: a1 waits for b (a long delay)
    got: list[Batch[str] | None] = []
    taker = threading.Thread(target=lambda: got.append(queue.get(timeout_s=WAIT_S)))
    now = time.monotonic()
    queue.offer(Pending("a", 0, now, now + 10 * FAR_S, "a1"))
    taker.start()
    queue.offer(Pending("b", 0, now, now + 10 * FAR_S, "b1"))
    taker.join(WAIT_S)
    assert got and got[0] is not None and names(got[0]) == ["a1", "b1"]


def test_costs_are_learned_per_batch_size_and_extrapolated() -> None:
    costs = BatchCosts()
    assert costs.estimate(0, 4) == 0.0
    costs.record(0, 1, 0.010)
    assert costs.estimate(0, 4) == pytest.approx(0.040)
    costs.record(0, 4, 0.020)
    assert costs.estimate(0, 4) == pytest.approx(0.020)
    assert costs.estimate(0, 8) == pytest.approx(0.040)
    costs.record(0, 4, 0.030)
    assert 0.020 < costs.estimate(0, 4) < 0.030, "a running average, not the last run"
    assert costs.estimate(1, 4) == 0.0, "per group"


def test_policy_from_config() -> None:
    default = BatchingConfig()
    assert (default.enabled, default.max_batch, default.max_in_flight_per_robot) == (False, 1, 8)
    assert default.preferred_batch_sizes == [8] and default.max_queue_delay_ms == 5.0
    off = BatchPolicy.from_config(BatchingConfig(max_in_flight_per_robot=3))
    assert (off.max_batch, off.max_queue_delay_s, off.max_in_flight_per_robot) == (1, 0.0, 3)
    on = BatchingConfig(enabled=True, preferred_batch_sizes=[8, 4, 4], max_queue_delay_ms=2.5)
    policy = BatchPolicy.from_config(on)
    assert policy.preferred_sizes == (4, 8) and policy.max_batch == 8
    assert policy.max_queue_delay_s == pytest.approx(0.0025)
    with pytest.raises(ValueError):
        BatchPolicy((0,), 0.0, 1)


def test_a_slot_is_released_once_before_the_reply_and_again_is_harmless() -> None:
    clock = Clock()
    queue = make_queue(clock, per_robot=1)
    offer(queue, clock, "a", 0)
    batch = take(queue, clock)
    queue.release(batch.items[0])  # the reply is about to go out
    assert (queue.load, queue.in_flight("a")) == (0, 0)
    offer(queue, clock, "a", 1)  # the robot's next frame, sent as soon as the reply came
    queue.done(batch)  # the worker finishes: nothing released twice
    assert (queue.load, queue.in_flight("a")) == (1, 1)


def test_a_request_that_would_miss_its_deadline_is_refused_and_a_batch_cut_to_fit() -> None:
    clock = Clock()
    queue = make_queue(clock, (3,))
    for n, seconds in ((1, 0.010), (2, 0.020), (3, 0.030)):
        queue.costs.record(0, n, seconds)
    offer(queue, clock, "a", 0, budget_s=0.005)  # a run takes 10 ms: cannot make it
    offer(queue, clock, "b", 0, budget_s=0.015)  # alone yes, in a batch of two (20 ms) no
    offer(queue, clock, "c", 0, budget_s=1.0)
    refused = take(queue, clock)
    assert refused.items == [] and [i.payload for i in refused.expired] == ["a0"]
    queue.done(refused)
    assert names(take(queue, clock)) == ["b0"], "cut to what keeps every deadline"
    clock.now += DELAY_S
    assert names(take(queue, clock)) == ["c0"]


def test_slow_runs_while_the_host_was_busy_do_not_refuse_every_later_request() -> None:
    """A few slow runs (a host busy starting robots) must not make every later request doomed:
    the fastest recent run decides, and with no run for a while a request runs again and its
    cost is measured anew (else nothing would ever run again)."""
    clock = Clock()
    queue = make_queue(clock)
    queue.costs.record(0, 1, 0.900)  # the first runs, on a host busy starting robot daemons
    for n in range(2):
        offer(queue, clock, "a", n, budget_s=0.500)
        refused = take(queue, clock)
        assert [i.payload for i in refused.expired] == [f"a{n}"], "0.9 s runs miss 0.5 s"
        queue.done(refused)
        clock.now += 0.5  # the second is refused too: the slow run is recent
    clock.now += 0.5  # no run for more than a second: the cost is measured again
    offer(queue, clock, "a", 2, budget_s=0.500)
    batch = take(queue, clock)
    assert names(batch) == ["a2"]
    queue.done(batch)
    queue.costs.record(0, 1, 0.030)  # the host is quiet again
    offer(queue, clock, "a", 3, budget_s=0.500)
    assert names(take(queue, clock)) == ["a3"], "the fastest recent run decides"


def test_a_robot_is_admitted_the_frames_it_keeps_in_flight_up_to_the_cap() -> None:
    clock = Clock()
    queue = make_queue(clock, per_robot=8)
    assert queue.limit("piped") == 8, "a robot that announced nothing gets the cap"
    assert queue.set_in_flight("piped", 3) == 4, "3 in flight and one it gave up on"
    for n in range(4):
        offer(queue, clock, "piped", n)
    late = Pending("piped", 0, clock.now, clock.now + FAR_S, "piped4")
    assert queue.offer(late) is Refusal.ROBOT_LIMIT
    assert queue.set_in_flight("greedy", 20) == 8, "the cap holds"
    assert queue.set_in_flight("single", 1) == 2
    with pytest.raises(ValueError, match=">= 1"):
        queue.set_in_flight("none", 0)
