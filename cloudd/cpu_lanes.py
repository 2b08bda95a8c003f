"""Which batches yield the CPU: a heavy robot's runs go at the lowest CPU priority.

Why: the per-robot queues and in-flight limit (`cloudd.batch_queue`) keep a robot that sends as
fast as it can from taking every worker, but not from taking the cores. Its run on one worker
competes with a light robot's run, and with the threads that receive and answer the light
robot's requests, for the host's CPUs; the light robot's p95 rises with it. The kernel settles
that when the heavy robot's runs are `SCHED_IDLE` (Linux): any other thread that wakes takes the
CPU from such a run at once, and the run still uses every CPU nobody else wants, so the
deployment serves as many frames as before. Where the policy cannot be set, nice 19 instead.

Heavy is relative ("least attained service" with two levels): a robot whose worker-seconds over
the last seconds (decayed, `USAGE_HALF_LIFE_S`; a batch's time split evenly between its robots)
exceed `HEAVY_FACTOR` times the mean of the robots served lately. A robot alone, or robots
alike, are never heavy; a batch runs low only when every robot in it is heavy.

The low priority is a thread of its own per worker (`LowPriorityThread`): lowering a thread's
priority needs no privilege, raising it back does, so each worker hands a heavy batch to its
low-priority sibling and waits for it. Linux only (priorities are per thread there; elsewhere
`setpriority` would lower the whole process), off elsewhere.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from typing import TypeVar

log = logging.getLogger(__name__)

R = TypeVar("R")

HEAVY_FACTOR = 1.5
"""A robot is heavy above this multiple of the mean use of the robots served lately (so with two
robots, one using three times the other's share or more)."""

USAGE_HALF_LIFE_S = 1.0
"""Half-life of a robot's worker-seconds: use of a second ago counts half."""

FORGET_BELOW_S = 1e-4
"""A robot whose decayed use is below this (about 13 half-lives of silence after a 1 s run) is
forgotten: it no longer counts in the mean."""

LOW_NICE = 19
"""Nice value of the low-priority threads, set before their policy (what is left where
`SCHED_IDLE` is refused)."""


def lanes_supported() -> bool:
    """Per-thread priorities: Linux (elsewhere `setpriority` on a thread id is the process)."""
    return sys.platform.startswith("linux")


class UsageMeter:
    """Decayed worker-seconds per robot, and which robots use far more than the others.

    Thread-safe: workers record and ask concurrently. `now` is injectable for tests.
    """

    def __init__(
        self,
        *,
        half_life_s: float = USAGE_HALF_LIFE_S,
        heavy_factor: float = HEAVY_FACTOR,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if half_life_s <= 0 or heavy_factor <= 1:
            raise ValueError("half_life_s must be > 0 and heavy_factor > 1")
        self._rate = math.log(2) / half_life_s
        self._factor = heavy_factor
        self._clock = clock
        self._lock = threading.Lock()
        self._use: dict[str, float] = {}
        self._at = clock()

    def record(self, robots: Iterable[str], seconds: float) -> None:
        """A batch of `robots` held a worker for `seconds`."""
        names = list(robots)
        if not names or seconds <= 0:
            return
        share = seconds / len(names)
        with self._lock:
            self._decay()
            for robot in names:
                self._use[robot] = self._use.get(robot, 0.0) + share

    def heavy(self, robots: Iterable[str]) -> bool:
        """Every robot of `robots` uses more than `heavy_factor` x the mean of those served
        lately (False for an empty batch, or with fewer than two robots served lately)."""
        names = set(robots)
        with self._lock:
            self._decay()
            if not names or len(self._use) < 2:
                return False
            bar = self._factor * sum(self._use.values()) / len(self._use)
            return all(self._use.get(robot, 0.0) > bar for robot in names)

    def usage(self) -> dict[str, float]:
        """Decayed worker-seconds per robot served lately (a copy)."""
        with self._lock:
            self._decay()
            return dict(self._use)

    def _decay(self) -> None:
        now = self._clock()
        keep = math.exp(-self._rate * max(0.0, now - self._at))
        self._at = now
        if keep < 1.0:
            self._use = {r: u * keep for r, u in self._use.items() if u * keep >= FORGET_BELOW_S}


class LowPriorityThread:
    """One thread at `SCHED_IDLE` (else nice `LOW_NICE`) that runs what it is given, one call
    at a time."""

    def __init__(self, name: str) -> None:
        self._calls: queue.SimpleQueue[tuple[Callable[[], object], Future[object]] | None] = (
            queue.SimpleQueue()
        )
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def call(self, fn: Callable[[], R]) -> R:
        """Run `fn` on the low-priority thread and return its result (or raise its error)."""
        future: Future[object] = Future()
        self._calls.put((fn, future))
        return future.result()  # type: ignore[return-value]

    def stop(self) -> None:
        """End the thread after what it runs now (it is a daemon thread: a stuck run does not
        hold the process)."""
        self._calls.put(None)

    def _loop(self) -> None:
        tid = threading.get_native_id()
        try:
            os.setpriority(os.PRIO_PROCESS, tid, LOW_NICE)
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        except OSError as exc:  # still runs the calls, at what could be set
            log.warning("could not lower %s's priority fully: %s", self._thread.name, exc)
        while (entry := self._calls.get()) is not None:
            fn, future = entry
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller, which decides
                future.set_exception(exc)
