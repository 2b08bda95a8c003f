"""The cloud daemon's threads: a bounded worker pool, and one timer thread for late actions.

`WorkerPool`: a ThreadPoolExecutor with `workers` threads behind a slot counter of `workers +
queue`. `try_submit` takes a slot or returns False at once, so a full deployment answers "busy"
immediately (the robot then finishes the frame itself) instead of letting requests pile up past
their deadlines. The slot is released when the job ends, whatever happens in it.

`DelayedActions`: runs callables at a later time on one thread. Fault injection uses it to send
delayed replies and to let go of queries it does not answer (dropped or stalled) when their
deadline has passed, without holding a worker or a Zenoh callback thread meanwhile.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

log = logging.getLogger(__name__)

MAX_PENDING_ACTIONS = 10_000
"""Late actions held at most; past this an action runs at once (a reply is sent undelayed, a held
query is let go), so a flood of requests cannot grow memory without bound."""


class WorkerPool:
    """`workers` threads and `queue` waiting slots; `try_submit` never blocks."""

    def __init__(self, workers: int, queue: int, *, name: str = "worker") -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if queue < 0:
            raise ValueError(f"queue must be >= 0, got {queue}")
        self.workers = workers
        self.capacity = workers + queue
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name)
        self._cond = threading.Condition()
        self._load = 0
        self._closed = False

    @property
    def load(self) -> int:
        """Jobs admitted and not finished (running or waiting for a worker)."""
        with self._cond:
            return self._load

    def try_submit(self, job: Callable[[], None]) -> bool:
        """Run `job` on a worker if a slot is free; False (at once) when full or closed."""
        with self._cond:
            if self._closed or self._load >= self.capacity:
                return False
            self._load += 1
        try:
            self._executor.submit(self._run, job)
        except RuntimeError:  # the executor shut down between the check and the submit
            self._release()
            return False
        return True

    def _run(self, job: Callable[[], None]) -> None:
        try:
            job()
        except Exception:
            # Jobs handle their own errors; one escaping here is a bug, but must not leak a slot.
            log.exception("worker job failed")
        finally:
            self._release()

    def _release(self) -> None:
        with self._cond:
            self._load -= 1
            self._cond.notify_all()

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until no job is admitted; False if some still run after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._load > 0:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def shutdown(self, timeout_s: float) -> bool:
        """Refuse new jobs, let admitted ones finish for up to `timeout_s`; True if all did."""
        with self._cond:
            self._closed = True
        idle = self.wait_idle(timeout_s)
        # Without waiting: a job stuck past the timeout must not hold the daemon's exit here.
        self._executor.shutdown(wait=False, cancel_futures=False)
        return idle


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
