"""The cloud daemon's threads: the workers that run batches, and one timer thread for late actions.

`BatchWorkers`: `workers` threads, each taking the next batch from the daemon's `FairQueue`
(`cloudd.batch_queue`, which admits or refuses requests at once, so a full deployment answers
"busy" immediately instead of letting requests pile up past their deadlines) and running it.
A batch's slots are released when its run ends, whatever happens in it. With a `UsageMeter`
(`cloudd.cpu_lanes`), the batch of a robot that uses far more of the workers than the others runs
on the worker's low-priority sibling thread, so lighter robots' runs take the CPUs first.
Stopping closes the queue: what was admitted is still handed out (the daemon answers it as
stopping), then the threads end; a run stuck past the timeout does not hold the daemon's exit.

`DelayedActions`: runs callables at a later time on one thread. Fault injection uses it to send
delayed replies and to let go of queries it does not answer (dropped or stalled) when their
deadline has passed, without holding a worker or a Zenoh callback thread meanwhile.
"""

from __future__ import annotations

import functools
import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

from cloudd.batch_queue import Batch, FairQueue
from cloudd.cpu_lanes import LowPriorityThread, UsageMeter

log = logging.getLogger(__name__)

T = TypeVar("T")

MAX_PENDING_ACTIONS = 10_000
"""Late actions held at most; past this an action runs at once (a reply is sent undelayed, a held
query is let go), so a flood of requests cannot grow memory without bound."""


class BatchWorkers(Generic[T]):
    """`workers` threads running `run(batch)` on the batches of `queue`."""

    def __init__(
        self,
        queue: FairQueue[T],
        run: Callable[[Batch[T]], None],
        workers: int,
        *,
        name: str = "worker",
        meter: UsageMeter | None = None,
    ) -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.queue = queue
        self.workers = workers
        self.meter = meter
        self._run = run
        self._threads = [
            threading.Thread(target=self._loop, args=(i,), name=f"{name}-{i}", daemon=True)
            for i in range(workers)
        ]
        self._name = name
        self._low: list[LowPriorityThread] = []  # started with the workers, with a meter
        self._low_counts = [0] * workers  # each written by its own worker only
        self._started = False

    @property
    def low_runs(self) -> int:
        """Batches run at low priority so far."""
        return sum(self._low_counts)

    def start(self) -> None:
        """Start the threads (once)."""
        if not self._started:
            self._started = True
            if self.meter is not None:
                self._low = [
                    LowPriorityThread(f"{self._name}-{i}-low") for i in range(self.workers)
                ]
            for thread in self._threads:
                thread.start()

    def _loop(self, index: int) -> None:
        while (batch := self.queue.get()) is not None:
            try:
                if self.meter is None:
                    self._run(batch)
                else:
                    self._run_metered(batch, self.meter, index)
            except Exception:
                # Runs answer their own errors; one escaping here is a bug, but must not leak
                # the batch's slots or end the worker.
                log.exception("running a batch failed")
            finally:
                self.queue.done(batch)

    def _run_metered(self, batch: Batch[T], meter: UsageMeter, index: int) -> None:
        """Run `batch` on worker `index`'s low-priority sibling when its robots are heavy, and
        record the worker time it took (whatever happens in it)."""
        robots = [item.robot for item in batch.items]
        started = time.monotonic()
        try:
            if meter.heavy(robots):
                self._low_counts[index] += 1
                self._low[index].call(functools.partial(self._run, batch))
            else:
                self._run(batch)
        finally:
            meter.record(robots, time.monotonic() - started)

    def shutdown(self, timeout_s: float) -> bool:
        """Close the queue and let the threads finish what was admitted, for up to
        `timeout_s`; True if every thread ended."""
        self.queue.close()
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            if thread.is_alive() and thread is not threading.current_thread():
                thread.join(max(0.0, deadline - time.monotonic()))
        for low in self._low:
            low.stop()
        return not any(t.is_alive() for t in self._threads)


class DelayedActions:
    """Run callables after a delay, in order of due time, on one thread."""

    def __init__(self, *, name: str = "delayed") -> None:
        self._name = name
        self._cond = threading.Condition()
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self._stopped = False
        self._thread: threading.Thread | None = None
        self._overflow_logged = False

    def start(self) -> None:
        """Start the thread (once)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
            self._thread.start()

    @property
    def pending(self) -> int:
        """Actions waiting for their time."""
        with self._cond:
            return len(self._heap)

    def call_later(self, delay_s: float, action: Callable[[], None]) -> None:
        """Run `action` in `delay_s` seconds (at once when stopped or too many are pending)."""
        with self._cond:
            accept = not self._stopped and len(self._heap) < MAX_PENDING_ACTIONS
            if accept:
                due = time.monotonic() + max(0.0, delay_s)
                heapq.heappush(self._heap, (due, next(self._seq), action))
                self._cond.notify()
            elif not self._stopped and not self._overflow_logged:
                self._overflow_logged = True
                log.warning(
                    "%s: %d actions pending; running new ones at once",
                    self._name,
                    MAX_PENDING_ACTIONS,
                )
        if not accept:
            self._call(action)

    def flush_and_stop(self) -> None:
        """Run every pending action now (in due order) and stop the thread."""
        with self._cond:
            self._stopped = True
            pending = [entry[2] for entry in sorted(self._heap)]
            self._heap.clear()
            self._cond.notify_all()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join()
        for action in pending:
            self._call(action)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._stopped:
                    if self._heap:
                        wait_s = self._heap[0][0] - time.monotonic()
                        if wait_s <= 0:
                            break
                        self._cond.wait(wait_s)
                    else:
                        self._cond.wait()
                if self._stopped:
                    return
                _, _, action = heapq.heappop(self._heap)
            self._call(action)

    def _call(self, action: Callable[[], None]) -> None:
        try:
            action()
        except Exception:
            log.exception("%s: delayed action failed", self._name)
