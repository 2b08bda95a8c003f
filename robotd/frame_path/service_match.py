"""Whether a deployment serves the robot's anycast service key now.

The robot daemon declares a querier on its service key only for this (frames use `session.get`,
each with its own timeout): Zenoh's matching status of that querier says whether a queryable
serves the key, and its matching listener follows the changes. Startup waits on it, bounded and
cut short by a signal, so that the first frames are not finished on the robot only because the
session was still meeting its peers; a frame whose query found no serving deployment (a move)
waits on it briefly before it is resent (`wait_served`, `robotd.frame_path.offload.CloudCall`).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import zenoh

from common.daemon import Daemon
from robotd.frame_path.registry_link import WAIT_SLICE_S


class ServiceMatch:
    """Set while a deployment serves the key, once `declare` has made its querier."""

    def __init__(self) -> None:
        self._served = threading.Event()

    def declare(self, owner: Daemon, session: zenoh.Session, key: str) -> None:
        """Declare the querier on `key` and its matching listener, both held by `owner`'s
        lifecycle, and start from the querier's current status."""
        querier = owner.hold(session.declare_querier(key), "service querier")
        owner.hold(
            querier.declare_matching_listener(
                owner.guarded(self._on_matching, what="a matching status")
            ),
            "service matching listener",
        )
        status: Any = querier.matching_status  # a MatchingStatus (the stub says bool)
        if bool(getattr(status, "matching", status)):
            self._served.set()

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._served.set()
        else:
            self._served.clear()

    def wait_served(self, timeout_s: float) -> bool:
        """Wait at most `timeout_s` for a deployment serving the key (a frame's resend after a
        move, `robotd.frame_path.offload.CloudCall`); True if one serves it."""
        return self._served.wait(timeout_s)

    def wait(self, timeout_s: float, interrupt: threading.Event) -> bool:
        """Wait at most `timeout_s` for a deployment serving the key, cut short once `interrupt`
        is set (a signal handler can only set the daemon's stop flag, so the wait looks at it
        every `WAIT_SLICE_S`); True if one serves it."""
        end = time.monotonic() + timeout_s
        while not interrupt.is_set():
            left = min(WAIT_SLICE_S, end - time.monotonic())
            if left <= 0:
                break
            if self._served.wait(left):
                return True
        return self._served.is_set()
