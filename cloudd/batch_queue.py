"""A cloud daemon's admitted requests: one queue per robot, served round robin, formed into batches.

Why per-robot queues: with one FIFO queue, a robot that sends as fast as it can fills it, and
every other robot waits behind its requests or is answered 'busy'. Here each robot has a queue
of its own and at most as many requests admitted at once (queued or running) as it keeps frames
in flight (announced at registration, passed on by the registry with `service`, plus one: a
request the robot gave up on may still be here), capped by `max_in_flight_per_robot` (a robot
that announced nothing gets the cap); past that, or when every slot of the deployment is taken,
`offer` refuses at once and the daemon answers 'busy' (the robot finishes the frame itself).
Workers serve the robots in turn: the robot served least recently goes first (a robot that was
never served, or not for a while, goes before one just served), so a robot waits for at most
one batch per robot ahead of it, never for another robot's backlog.

Batches (after Triton's dynamic batcher). A worker starts from the head request of the robot
whose turn it is; its group (the cut: requests of one cut can share one model run) decides who
joins: each other robot's queued requests of that group, round robin, one per robot per pass
(a robot's own requests stay in order), up to the largest preferred size. The batch leaves at
once when it reaches a preferred size; when no other robot could join now (every robot heard
from lately is in the batch or already has a request admitted, so a robot alone never waits);
when its oldest request has waited `max_queue_delay_s`; or at once when one of its requests
could not afford that wait: the delay and the run of a batch one larger (`BatchCosts`, learned
from the runs) must leave a quarter of its deadline budget. Otherwise the worker waits for more
requests, at most until the delay is over. With batching off the largest batch is 1: the
queues, the turn and the limits stay.

Deadlines: a request carries its budget from arrival (`InferRequest.deadline_s`). One whose
deadline has passed when a worker looks, or that would miss it even if it ran alone now (by
the fastest of the last runs, while a run is recent: `BatchCosts.fastest_alone`), is handed
back as expired instead of being computed: the robot has
finished that frame itself, or will sooner for the early refusal. A batch is cut short to the
requests whose deadlines its estimated run keeps; the others wait for the next one.

No I/O and no Zenoh here: items carry an opaque payload; `poll(now)` makes every decision and
can be driven by any clock (the unit tests); `get()` blocks a worker on it.
"""

from __future__ import annotations

import enum
import itertools
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from common.config import BatchingConfig

T = TypeVar("T")

DEADLINE_RESERVE_SHARE = 0.25
"""A request waits for a batch only if the wait and the run leave this share of its budget (the
reply still has to reach the robot, and run times are estimates)."""

MIN_WAIT_S = 1e-4
"""A batch that could wait less than this leaves now (not worth a wake-up)."""

ACTIVE_WINDOW_S = 1.0
"""A robot heard from within this long may send again soon: a batch waits for it (up to the
delay), not for robots that went quiet."""

COST_EWMA_WEIGHT = 0.2
"""Weight of the newest run in a batch size's running cost."""

COST_RECENT_RUNS = 8
"""Runs of a group whose fastest decides whether a request is doomed (`BatchCosts`)."""

COST_FRESH_S = 1.0
"""A group's costs may refuse a request as doomed only this long (seconds) after its last run."""

# A robot with N frames in flight is admitted N + this many requests: one it stopped waiting for
# (its deadline passed, it finished the frame itself) may still be queued or running here.
IN_FLIGHT_SLACK = 1


@dataclass(eq=False)
class Pending(Generic[T]):
    """One admitted request: its robot, its batch group, when it arrived and must be done by
    (seconds of the queue's clock), and what the daemon needs to answer it."""

    robot: str
    group: int
    arrived: float
    deadline_at: float
    payload: T
    seq: int = field(default=0, init=False)
    """Order of admission (set by the queue): ties of the turn order go to the older."""
    released: bool = field(default=False, init=False)
    """Its slot is free again (`FairQueue.release`)."""


@dataclass
class Batch(Generic[T]):
    """What a worker takes: `items` to run together (all of `group`), and `expired` requests
    to answer without computing (their deadline passed, or would before a run could end).
    Either list may be empty, not both."""

    group: int
    items: list[Pending[T]]
    expired: list[Pending[T]] = field(default_factory=list)
    taken_at: float = 0.0


class Refusal(enum.Enum):
    """Why `offer` did not admit a request (the daemon answers 'busy', or 'stopping')."""

    FULL = "every slot of this deployment is taken"
    ROBOT_LIMIT = "the robot's in-flight limit is reached"
    CLOSED = "the deployment is stopping"


@dataclass(frozen=True)
class BatchPolicy:
    """How batches form and how much one robot may hold (`BatchingConfig`, resolved)."""

    preferred_sizes: tuple[int, ...] = (1,)
    max_queue_delay_s: float = 0.0
    max_in_flight_per_robot: int = 2

    def __post_init__(self) -> None:
        if not self.preferred_sizes or min(self.preferred_sizes) < 1:
            raise ValueError(f"preferred sizes must be >= 1, got {self.preferred_sizes}")
        if self.max_queue_delay_s < 0:
            raise ValueError(f"max_queue_delay_s must be >= 0, got {self.max_queue_delay_s}")
        if self.max_in_flight_per_robot < 1:
            raise ValueError(
                f"max_in_flight_per_robot must be >= 1, got {self.max_in_flight_per_robot}"
            )
        object.__setattr__(self, "preferred_sizes", tuple(sorted(set(self.preferred_sizes))))

    @property
    def max_batch(self) -> int:
        return self.preferred_sizes[-1]

    @classmethod
    def from_config(cls, cfg: BatchingConfig) -> BatchPolicy:
        """The policy of a machine's `batching` section (batching off: batches of one)."""
        if not cfg.enabled:
            return cls((1,), 0.0, cfg.max_in_flight_per_robot)
        return cls(
            tuple(cfg.preferred_batch_sizes),
            cfg.max_queue_delay_ms / 1000.0,
            cfg.max_in_flight_per_robot,
        )


class BatchCosts:
    """Seconds one run of `n` requests of a group takes, learned from the runs (thread-safe).

    An unseen size is estimated from the nearest smaller one measured (per request), so the
    first batch of a new size is not held longer than the runs so far justify; nothing measured
    yet: 0 (then only the queue delay bounds the wait).

    `fastest_alone` is what refuses a request as doomed, so it must not lock a group out: it is
    the fastest of a single request's last COST_RECENT_RUNS runs (a few slow runs, e.g. while the
    host was busy starting robots, do not condemn every later request), and only while a run of
    the group was recorded within COST_FRESH_S (`clock`): a group whose requests were all
    refused would otherwise never run again, and its cost never be measured again."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self._seconds: dict[int, dict[int, float]] = {}
        self._alone: dict[int, deque[float]] = {}
        self._last_run_at: dict[int, float] = {}

    def record(self, group: int, n: int, seconds: float) -> None:
        with self._lock:
            sizes = self._seconds.setdefault(group, {})
            old = sizes.get(n)
            sizes[n] = seconds if old is None else old + COST_EWMA_WEIGHT * (seconds - old)
            # A batch's run per request is at most one request's own run: doomed errs towards
            # computing.
            per_request = seconds / n
            self._alone.setdefault(group, deque(maxlen=COST_RECENT_RUNS)).append(per_request)
            self._last_run_at[group] = self._clock()

    def estimate(self, group: int, n: int) -> float:
        with self._lock:
            sizes = self._seconds.get(group)
            if not sizes:
                return 0.0
            if n in sizes:
                return sizes[n]
            below = [m for m in sizes if m < n]
            m = max(below) if below else min(sizes)
            return sizes[m] / m * n

    def fastest_alone(self, group: int, now: float) -> float:
        """The shortest run of one request of `group` lately; 0 (nothing can be called doomed)
        when no run of it was recorded within COST_FRESH_S of `now`."""
        with self._lock:
            last = self._last_run_at.get(group)
            if last is None or now - last > COST_FRESH_S:
                return 0.0
            return min(self._alone[group])


class FairQueue(Generic[T]):
    """Per-robot queues, round robin, in-flight limits and batch forming (module docstring).

    `capacity` is the number of requests admitted at once: `slots` (workers x largest batch +
    waiting slots, decided by the daemon). `batchable(group)` tells whether a group may run in
    batches at all (a suffix that cannot take a batch axis runs one request at a time).
    """

    def __init__(
        self,
        policy: BatchPolicy,
        *,
        slots: int,
        costs: BatchCosts | None = None,
        batchable: Callable[[int], bool] = lambda group: True,
        clock: Callable[[], float] = time.monotonic,
        active_window_s: float = ACTIVE_WINDOW_S,
    ) -> None:
        if slots < 1:
            raise ValueError(f"slots must be >= 1, got {slots}")
        self.policy = policy
        self.capacity = slots
        self.costs = costs if costs is not None else BatchCosts(clock)
        self._batchable = batchable
        self._clock = clock
        self._active_window_s = active_window_s
        self._cond = threading.Condition()
        self._queues: dict[str, deque[Pending[T]]] = {}  # robots with queued requests
        self._served_turn: dict[str, int] = {}  # robot -> the turn it was last served in
        self._turn = 0
        self._seq = itertools.count()
        self._in_flight: dict[str, int] = {}
        # Per robot: its requests admitted at once, from the frames in flight it announced
        # (`set_in_flight`); a robot that announced none gets the cap.
        self._limits: dict[str, int] = {}
        self._last_seen: dict[str, float] = {}
        self._load = 0
        self._closed = False

    # -- facts ---------------------------------------------------------------------------------
    @property
    def load(self) -> int:
        """Requests admitted and not yet done (queued or running)."""
        with self._cond:
            return self._load

    @property
    def queued(self) -> int:
        """Requests waiting for a worker."""
        with self._cond:
            return sum(len(q) for q in self._queues.values())

    def in_flight(self, robot: str) -> int:
        with self._cond:
            return self._in_flight.get(robot, 0)

    def limit(self, robot: str) -> int:
        """Requests of `robot` admitted at once (`set_in_flight`, else the cap)."""
        with self._cond:
            return self._limits.get(robot, self.policy.max_in_flight_per_robot)

    def set_in_flight(self, robot: str, announced: int) -> int:
        """`robot` keeps `announced` frames in flight: admit that many of its requests at once,
        plus `IN_FLIGHT_SLACK`, at most the cap (`max_in_flight_per_robot`); the limit now in
        force for it."""
        if announced < 1:
            raise ValueError(f"announced frames in flight must be >= 1, got {announced}")
        limit = min(announced + IN_FLIGHT_SLACK, self.policy.max_in_flight_per_robot)
        with self._cond:
            self._limits[robot] = limit
        return limit

    @property
    def closed(self) -> bool:
        with self._cond:
            return self._closed

    # -- producers -----------------------------------------------------------------------------
    def offer(self, item: Pending[T]) -> Refusal | None:
        """Admit `item` (None) or say at once why not."""
        with self._cond:
            self._last_seen[item.robot] = item.arrived
            if self._closed:
                return Refusal.CLOSED
            limit = self._limits.get(item.robot, self.policy.max_in_flight_per_robot)
            if self._in_flight.get(item.robot, 0) >= limit:
                return Refusal.ROBOT_LIMIT
            if self._load >= self.capacity:
                return Refusal.FULL
            self._load += 1
            self._in_flight[item.robot] = self._in_flight.get(item.robot, 0) + 1
            item.seq = next(self._seq)
            self._queues.setdefault(item.robot, deque()).append(item)
            self._cond.notify_all()
            return None

    def close(self) -> None:
        """Admit nothing more; queued requests are still handed out (at once, unbatched by
        waiting), then `get` returns None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # -- consumers -----------------------------------------------------------------------------
    def get(self, timeout_s: float | None = None) -> Batch[T] | None:
        """Block until a batch is ready and take it; None once closed and empty (or after
        `timeout_s` without a batch)."""
        deadline = None if timeout_s is None else self._clock() + timeout_s
        with self._cond:
            while True:
                now = self._clock()
                decision = self._poll(now)
                if isinstance(decision, Batch):
                    return decision
                if decision is None and self._closed:
                    return None
                wait = decision
                if deadline is not None:
                    left = deadline - now
                    if left <= 0:
                        return None
                    wait = left if wait is None else min(wait, left)
                self._cond.wait(wait)

    def poll(self, now: float | None = None) -> Batch[T] | float | None:
        """Take a batch if one is ready at `now`; else the seconds to wait before asking again
        (a batch is forming), or None (nothing queued)."""
        with self._cond:
            return self._poll(self._clock() if now is None else now)

    def release(self, item: Pending[T]) -> None:
        """Free `item`'s slot (once; again is harmless). Call it just before its reply goes
        out: a robot that sends its next frame as soon as the reply is in must find its slot
        free, or it would be refused for its own finished request."""
        with self._cond:
            if item.released:
                return
            item.released = True
            self._load -= 1
            left = self._in_flight.get(item.robot, 0) - 1
            if left > 0:
                self._in_flight[item.robot] = left
            else:
                self._in_flight.pop(item.robot, None)

    def done(self, batch: Batch[T]) -> None:
        """The batch is over: the slots of its requests not released yet are free."""
        for item in (*batch.items, *batch.expired):
            self.release(item)

    # -- decisions (under the lock) ------------------------------------------------------------
    def _poll(self, now: float) -> Batch[T] | float | None:
        expired = self._take_expired(now)
        if expired:
            return Batch(group=expired[0].group, items=[], expired=expired, taken_at=now)
        if not self._queues:
            return None
        order = self._turn_order()
        head = self._queues[order[0]][0]
        largest = self.policy.max_batch if self._batchable(head.group) else 1
        candidates = self._gather(order, head.group, largest)
        size = self._ready_size(candidates, largest, now)
        if size is None:
            return self._wait_s(candidates, now)
        items = candidates[:size]
        doomed = self._doomed(items, now)
        if doomed:
            self._remove(doomed)
            return Batch(group=head.group, items=[], expired=doomed, taken_at=now)
        return self._take(head.group, self._fitting(items, now), now)

    def _doomed(self, items: list[Pending[T]], now: float) -> list[Pending[T]]:
        """Requests that would miss their deadline even run alone now (by the runs measured so
        far): computing them helps nobody, and refusing them at once lets the robot finish the
        frame itself sooner."""
        alone_s = self.costs.fastest_alone(items[0].group, now)
        if alone_s <= 0:
            return []
        return [item for item in items if now + alone_s > item.deadline_at]

    def _fitting(self, items: list[Pending[T]], now: float) -> list[Pending[T]]:
        """The longest leading part of `items` whose run, as estimated, ends before every one
        of their deadlines (a bigger batch runs longer); the rest wait for the next batch."""
        group = items[0].group
        while len(items) > 1:
            ends_at = now + self.costs.estimate(group, len(items))
            if ends_at <= min(item.deadline_at for item in items):
                break
            items = items[:-1]
        return items

    def _ready_size(self, candidates: list[Pending[T]], largest: int, now: float) -> int | None:
        """How many of `candidates` leave now, or None to wait for more."""
        n = len(candidates)
        if n >= largest:
            return largest
        formable = [s for s in self.policy.preferred_sizes if s <= n]
        if formable:
            return formable[-1]
        if self._closed or not self._others_expected(candidates, now):
            return n
        if not self._deadlines_allow_waiting(candidates):
            return n
        if self._wait_s(candidates, now) < MIN_WAIT_S:
            return n
        return None

    def _wait_s(self, candidates: list[Pending[T]], now: float) -> float:
        """How long the batch may still wait: the queue delay of its oldest request."""
        return min(c.arrived for c in candidates) + self.policy.max_queue_delay_s - now

    def _deadlines_allow_waiting(self, candidates: list[Pending[T]]) -> bool:
        """Whether every request can afford the whole queue delay and the run of a batch one
        larger, and keep a share of its budget for the reply's way back and for misestimates.
        One that cannot is not held at all: it runs at once with what is there."""
        group = candidates[0].group
        start = min(c.arrived for c in candidates) + self.policy.max_queue_delay_s
        done_at = start + self.costs.estimate(group, len(candidates) + 1)
        return all(
            done_at <= c.deadline_at - DEADLINE_RESERVE_SHARE * (c.deadline_at - c.arrived)
            for c in candidates
        )

    def _others_expected(self, candidates: list[Pending[T]], now: float) -> bool:
        """Whether a robot outside the batch may send a request soon: heard from lately and
        nothing admitted now (a robot waits for its reply before sending its next frame)."""
        inside = {c.robot for c in candidates}
        since = now - self._active_window_s
        return any(
            robot not in inside and seen >= since and self._in_flight.get(robot, 0) == 0
            for robot, seen in self._last_seen.items()
        )

    def _turn_order(self) -> list[str]:
        """Robots with queued requests, least recently served first, then by their oldest
        request."""
        return sorted(
            self._queues,
            key=lambda robot: (self._served_turn.get(robot, -1), self._queues[robot][0].seq),
        )

    def _gather(self, order: list[str], group: int, largest: int) -> list[Pending[T]]:
        """Requests of `group` in turn order: one per robot per pass, each robot's in its own
        order (only its leading requests of that group), at most `largest`."""
        runs: list[list[Pending[T]]] = []
        for robot in order:
            queue = self._queues[robot]
            run: list[Pending[T]] = []
            for item in queue:
                if item.group != group or len(run) == largest:
                    break
                run.append(item)
            if run:
                runs.append(run)
        out: list[Pending[T]] = []
        depth = 0
        while len(out) < largest and any(len(run) > depth for run in runs):
            for run in runs:
                if len(run) > depth and len(out) < largest:
                    out.append(run[depth])
            depth += 1
        return out

    def _remove(self, items: list[Pending[T]]) -> None:
        for item in items:
            queue = self._queues[item.robot]
            queue.remove(item)  # a leading item of its queue: cheap
            if not queue:
                del self._queues[item.robot]

    def _take(self, group: int, items: list[Pending[T]], now: float) -> Batch[T]:
        self._remove(items)
        # Served robots go behind every other one, in the order they were served.
        for robot in dict.fromkeys(item.robot for item in items):
            self._turn += 1
            self._served_turn[robot] = self._turn
        return Batch(group=group, items=items, taken_at=now)

    def _take_expired(self, now: float) -> list[Pending[T]]:
        expired: list[Pending[T]] = []
        for robot in list(self._queues):
            queue = self._queues[robot]
            if all(item.deadline_at > now for item in queue):
                continue
            expired += [item for item in queue if item.deadline_at <= now]
            kept = deque(item for item in queue if item.deadline_at > now)
            if kept:
                self._queues[robot] = kept
            else:
                del self._queues[robot]
        return expired
