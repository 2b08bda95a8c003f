"""A logger wrapper that lets a burst of lines through per time window and counts the rest.

Daemons log bad input (a malformed request, a garbage publication) and errors in Zenoh callbacks.
Those come from outside and can come at any rate: a flood of garbage must not flood the log (nor
slow the callback threads down with I/O). So at most `burst` lines go out per `window_s`; the
rest are counted, and the count is logged as one line when the next window opens.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

LOG_BURST = 50
LOG_WINDOW_S = 10.0


class ThrottledLog:
    """`ThrottledLog(log, label=lambda: "cloud edge-1").warning("bad request: %s", why)`.

    `label` names the owner in the summary line; a callable, so it can be read late (a daemon
    names itself after its base class is set up). `clock` is for tests.
    """

    def __init__(
        self,
        logger: logging.Logger,
        *,
        label: Callable[[], str] = lambda: "",
        burst: int = LOG_BURST,
        window_s: float = LOG_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger = logger
        self.burst = burst
        self.window_s = window_s
        self._label = label
        self._clock = clock
        self._lock = threading.Lock()
        self._window_start = -float("inf")
        self._count = 0
        self._suppressed = 0

    def warning(self, message: str, *args: object) -> bool:
        """Log a WARNING line unless this window's burst is spent; True if it was logged."""
        return self._emit(logging.WARNING, message, args, exc_info=False)

    def error(self, message: str, *args: object, exc_info: bool = False) -> bool:
        """Log an ERROR line (with the current traceback if `exc_info`) unless throttled."""
        return self._emit(logging.ERROR, message, args, exc_info=exc_info)

    def log(self, level: int, message: str, *args: object, exc_info: bool = False) -> bool:
        """Log at `level` unless this window's burst is spent; True if it was logged."""
        return self._emit(level, message, args, exc_info=exc_info)

    def _emit(self, level: int, message: str, args: tuple[object, ...], *, exc_info: bool) -> bool:
        now = self._clock()
        with self._lock:
            suppressed = 0
            if now - self._window_start > self.window_s:
                suppressed = self._suppressed
                self._window_start, self._count, self._suppressed = now, 0, 0
            allowed = self._count < self.burst
            if allowed:
                self._count += 1
            else:
                self._suppressed += 1
        if suppressed:
            label = self._label()
            self.logger.warning(
                "%s%d more warnings were not logged in the last %.0f s",
                f"{label}: " if label else "",
                suppressed,
                self.window_s,
            )
        if allowed:
            # stacklevel: the record names the line that called warning/error/log, not this one.
            self.logger.log(level, message, *args, exc_info=exc_info, stacklevel=3)
        return allowed
