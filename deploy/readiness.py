"""Waiting for daemons to be ready, never sleeping for them: a predicate over a reply
(`wait_until`) or liveliness tokens (`TokenWatch`), each with a timeout and a message naming what
did not happen. While waiting the processes are watched too, so a daemon that exits during startup
fails the wait at once with its exit code and the last line of its log instead of a timeout.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, TypeVar

from deploy.procs import WATCH_INTERVAL_S, DaemonError, DaemonProc, ProcessSet

if TYPE_CHECKING:
    import zenoh

T = TypeVar("T")


def wait_until(
    fn: Callable[[], T | None],
    *,
    timeout_s: float,
    what: str,
    procs: ProcessSet | Sequence[DaemonProc] | None = None,
    interval_s: float = 0.1,
    wake: threading.Event | None = None,
) -> T:
    """Call `fn` until it returns something other than None/False, and return that.

    For conditions only a query can tell (a registry view, a probe reply). Between attempts we wait
    on `wake` (set it from a callback to retry at once) for at most `interval_s`, and check that the
    daemons in `procs` are still running. `DaemonError` naming `what` after `timeout_s`.
    """
    deadline = time.monotonic() + timeout_s
    wake = wake or threading.Event()
    last_error: Exception | None = None
    while True:
        check_procs(procs)
        try:
            result = fn()
        except Exception as exc:  # a query that fails now may succeed once the daemon is up
            last_error = exc
            result = None
        if result is not None and result is not False:
            return result
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            detail = f" (last error: {last_error})" if last_error else ""
            raise DaemonError(f"timed out after {timeout_s:.0f} s waiting for {what}{detail}")
        wake.wait(min(interval_s, remaining))
        wake.clear()


def check_procs(procs: ProcessSet | Sequence[DaemonProc] | None) -> None:
    if procs is None:
        return
    if isinstance(procs, ProcessSet):
        procs.check_alive()
        return
    for proc in procs:
        proc.check_alive()


class TokenWatch:
    """The fleet's liveliness tokens for waits that name keys (`keys.alive_*`), with the daemons'
    processes watched meanwhile.

    The tokens are followed by a `common.membership.MembershipView` of every role (seeded, then
    kept up to date by its subscriber, so a wait never misses a token declared just before it
    began); this adds what starting daemons needs: a wait that fails at once when a daemon exits,
    and a `DaemonError` naming the missing tokens on timeout. Close it (or use `with`) before
    the session closes.
    """

    def __init__(self, session: zenoh.Session, fleet: str) -> None:
        # Imported here: the demo's CLI parsing must not pay for importing zenoh.
        from common.membership import MembershipView

        self.fleet = fleet
        self.view = MembershipView(session, fleet).start()

    @property
    def alive(self) -> set[str]:
        """The keys of the tokens alive now."""
        from common import keys

        members = self.view.snapshot()
        return {keys.alive(self.fleet, role, id) for role, ids in members.items() for id in ids}

    def wait_for(
        self,
        keys: Sequence[str],
        *,
        timeout_s: float,
        procs: ProcessSet | Sequence[DaemonProc] | None = None,
        present: bool = True,
    ) -> None:
        """Block until every key is alive (present=False: gone); `DaemonError` on timeout."""
        members = {key: self._member(key) for key in keys}

        def missing(alive: Mapping[str, frozenset[str]]) -> list[str]:
            return [k for k, (role, id) in members.items() if (id in alive[role]) != present]

        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            slice_s = max(0.0, min(WATCH_INTERVAL_S, remaining))
            if self.view.wait_for(lambda alive: not missing(alive), timeout_s=slice_s):
                return
            check_procs(procs)
            if remaining <= 0:
                state = "liveliness token" if present else "disappearance of token"
                raise DaemonError(
                    f"timed out after {timeout_s:.0f} s waiting for {state} "
                    + ", ".join(missing(self.view.snapshot()))
                )

    def _member(self, key: str) -> tuple[str, str]:
        """(role, id) of a liveliness key of this fleet."""
        from common import keys

        parts = keys.parse_key(key)
        if parts is None or parts.role is None or parts.id is None or parts.fleet != self.fleet:
            raise ValueError(f"{key!r} is not a liveliness key of fleet {self.fleet}")
        return parts.role, parts.id

    def close(self) -> None:
        self.view.close()

    def __enter__(self) -> TokenWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
