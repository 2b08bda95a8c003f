"""Camera semantics for frames that arrive on their own: the robot always works on the newest.

A source fed over the network (a ROS 2 topic, `ef/<fleet>/in/<robot>`) gets frames whenever the
publisher sends them, faster or slower than the robot serves them. `NewestFrame` holds one frame
waiting for the frame loop: a frame that arrives while another waits replaces it, and the one
replaced is counted in `dropped_stale` (never lost silently); `take` waits for the next frame,
bounded by a stop flag. Nothing queues, so a slow robot's results never age by a growing backlog.
"""

from __future__ import annotations

import threading
from typing import Generic, TypeVar

T = TypeVar("T")

# How often a wait for the next frame looks at the stop flag, s.
STOP_POLL_S = 0.1


class NewestFrame(Generic[T]):
    """One waiting frame, the newest (see the module docstring). Thread-safe: `put` is called
    from Zenoh's callback threads, `take` from the frame loop."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._closed = False
        self.received = 0
        self.dropped_stale = 0

    def put(self, item: T) -> None:
        """`item` is the newest frame; a frame still waiting is dropped and counted."""
        with self._cond:
            self.received += 1
            if self._item is not None:
                self.dropped_stale += 1
            self._item = item
            self._cond.notify()

    def take(self, stop: threading.Event | None = None) -> T | None:
        """The newest frame, waiting for one; None once closed or `stop` is set."""
        with self._cond:
            while self._item is None:  # bounded by `stop` or close()
                if self._closed or (stop is not None and stop.is_set()):
                    return None
                self._cond.wait(STOP_POLL_S)
            item, self._item = self._item, None
            return item

    def wait_ready(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Whether `take` would return at once (a frame waits, or the slot is closed or
        stopping), after waiting up to `timeout_s` for a frame."""
        with self._cond:
            stopping = self._closed or (stop is not None and stop.is_set())
            if self._item is None and not stopping:
                self._cond.wait(timeout_s)
            return self._item is not None or self._closed or (stop is not None and stop.is_set())

    def close(self) -> None:
        """No more frames: a `take` waiting returns None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
