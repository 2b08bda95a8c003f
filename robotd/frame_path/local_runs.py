"""Local runs on the robot: the thread that runs hedged frames' speculative local suffixes.

A hedged frame also runs the local suffix, speculatively, on `LocalRunner`'s thread (as do the
next frames' model runs while its reply is still on its way). That thread runs at the lowest CPU
priority: on a robot with a small CPU quota the robot's compute and the offload (Zenoh's threads
serialising and sending the request, receiving the reply) share that quota, and threads of one
CPU cgroup share it by their nice weight, so the offload goes first (measured on the testbed:
docs/experiments.md). Whichever path of a hedged frame loses is stopped: a cloud reply that
comes first cancels the run (onnxruntime's `RunOptions.terminate`).
"""

from __future__ import annotations

import logging
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Mapping

import numpy as np
import onnxruntime as ort

log = logging.getLogger("robotd")

Clock = Callable[[], float]

# Nice value of the speculative local run's thread: Linux's lowest priority (weight 15 against
# 1024 for the offload's threads at nice 0).
SPECULATIVE_NICE = 19


Outputs = dict[str, np.ndarray]


def lower_thread_priority(nice: int = SPECULATIVE_NICE) -> bool:
    """Give the calling thread (only it) the nice value `nice`; False where that is not possible
    (not Linux, or refused). On Linux `setpriority(PRIO_PROCESS, tid)` applies to one thread."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except OSError:
        return False
    return True


class LocalJob:
    """One speculative local run, queued on a `LocalRunner`.

    `fn` gets the run's `onnxruntime.RunOptions` (pass them to `SplitModel.run_*`); `cancel()`
    sets their `terminate` flag, which stops a run in progress at its next node (or skips one
    still queued). When the job is done `outputs` holds the result, or `error` what `fn` raised
    (never set for a cancelled run), and `wake` (if given) is set."""

    def __init__(
        self,
        fn: Callable[[ort.RunOptions], Mapping[str, np.ndarray]],
        wake: threading.Event | None = None,
        clock: Clock = time.perf_counter,
    ) -> None:
        self._fn = fn
        self._wake = wake
        self._clock = clock
        self.run_options = ort.RunOptions()
        self.outputs: Outputs | None = None
        self.error: Exception | None = None
        self.cancelled = False
        self.started_at: float | None = None
        self.finished_at: float | None = None
        self._done = threading.Event()

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def completed(self) -> bool:
        """True when the run finished with outputs (not cancelled, no error)."""
        return self._done.is_set() and self.outputs is not None

    @property
    def elapsed_s(self) -> float | None:
        """Time the run took on its thread (not its wait in the queue), when it completed."""
        if not self.completed or self.started_at is None or self.finished_at is None:
            return None
        return self.finished_at - self.started_at

    def cancel(self) -> None:
        """Stop the run (its result is not wanted any more)."""
        self.cancelled = True
        self.run_options.terminate = True

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until the job is done (at most `timeout_s`); True when it is."""
        return self._done.wait(timeout_s)

    def run(self) -> None:
        """Run `fn` in the calling thread (the runner's)."""
        try:
            if self.cancelled:
                return
            self.started_at = self._clock()
            try:
                self.outputs = dict(self._fn(self.run_options))
            except Exception as exc:
                # A cancelled run raises onnxruntime's "terminate flag" error: not an error here.
                if not self.cancelled:
                    self.error = exc
            self.finished_at = self._clock()
            if self.cancelled:
                self.outputs = None
        finally:
            self._done.set()
            if self._wake is not None:
                self._wake.set()


class LocalRunner:
    """The thread that runs hedged frames' speculative local suffixes, one at a time, at the
    lowest CPU priority (`SPECULATIVE_NICE`). `start()` waits until the thread has lowered its
    priority; `niced` then says whether that worked."""

    def __init__(self, name: str = "local-run", nice: int = SPECULATIVE_NICE) -> None:
        self.name = name
        self.nice = nice
        self.niced = False
        self._queue: queue.SimpleQueue[LocalJob | None] = queue.SimpleQueue()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._current: LocalJob | None = None

    def start(self, timeout_s: float = 1.0) -> None:
        self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise RuntimeError(f"{self.name}: the local-run thread did not start")

    def submit(
        self,
        fn: Callable[[ort.RunOptions], Mapping[str, np.ndarray]],
        wake: threading.Event | None = None,
    ) -> LocalJob:
        """Queue `fn` (see `LocalJob`); it runs after the jobs before it."""
        if self._thread is None or not self._thread.is_alive():
            raise RuntimeError(f"{self.name}: not running")
        job = LocalJob(fn, wake)
        self._queue.put(job)
        return job

    def stop(self, timeout_s: float = 1.0) -> None:
        """Cancel what runs or waits and end the thread (bounded by `timeout_s`)."""
        current = self._current
        if current is not None:
            current.cancel()
        while True:  # bounded: only jobs queued before this call are drained
            try:
                job = self._queue.get_nowait()
            except queue.Empty:
                break
            if job is not None:
                job.cancel()
                job.run()  # marks it done without running anything
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _loop(self) -> None:
        self.niced = lower_thread_priority(self.nice)
        if not self.niced:
            log.debug("%s: could not lower this thread's CPU priority", self.name)
        self._ready.set()
        while True:  # ends on the None that stop() queues
            job = self._queue.get()
            if job is None:
                return
            self._current = job
            job.run()
            self._current = None
