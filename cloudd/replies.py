"""How a cloud daemon answers a query: now, later, or not at all.

Every reply goes through `Replier.send`, which finalizes the query once the reply is out (or
could not go out: the querier or the session is gone, which is logged and otherwise ignored).
Fault injection delays replies on the timer thread (`cloudd.workers.DelayedActions`), so a
delay never holds a worker or a Zenoh callback thread, and it leaves queries unanswered on
purpose (`hold`: drop, stall) until HOLD_UNANSWERED_S has passed. Once the timer is stopped
(shutdown), delayed replies go out and held queries are let go at once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import zenoh

from cloudd.faults import FaultInjector
from cloudd.workers import DelayedActions
from common.throttled_log import ThrottledLog
from common.wire import ErrorCode, ErrorReply, WireError, error_reply

log = logging.getLogger(__name__)

HOLD_UNANSWERED_S = 30.0
"""How long a query left unanswered on purpose (drop, stall) is held before it is let go: longer
than any querier waits, so it sees a timeout, as it would for a lost message or a frozen host."""


def query_payload(query: zenoh.Query) -> bytes:
    """The query's payload (empty when it carries none)."""
    payload = query.payload
    return b"" if payload is None else payload.to_bytes()


class Replier:
    """Sends a deployment's replies, delayed by the injected fault, and holds dropped queries."""

    def __init__(self, deployment: str, faults: FaultInjector, throttled: ThrottledLog) -> None:
        self.deployment = deployment
        self.faults = faults
        self.throttled = throttled
        self._timer: DelayedActions | None = None

    def start(self) -> None:
        """Start the timer thread: from now on delays and holds take effect."""
        self._timer = timer = DelayedActions(name=f"{self.deployment}-timer")
        timer.start()

    def stop(self) -> None:
        """Send the delayed replies now, let the held queries go, stop the timer thread."""
        timer = self._timer
        if timer is not None:
            timer.flush_and_stop()

    def delay_s(self) -> float:
        """The injected delay before a reply now, in seconds."""
        return self.faults.get().delay_ms / 1000.0

    def send(
        self,
        query: zenoh.Query,
        key: str,
        payload: bytes,
        delay_s: float,
        on_sent: Callable[[], None] | None = None,
    ) -> None:
        """Reply to `query` now or after `delay_s` (fault injection), then finalize it."""

        def send() -> None:
            try:
                query.reply(key, payload)
                if on_sent is not None:
                    on_sent()
            except Exception as exc:  # the querier or the session is gone: nothing to do
                self.throttled.warning("%s: reply on %s not sent: %s", self.deployment, key, exc)
            finally:
                try:
                    query.drop()
                except Exception as exc:
                    log.debug("%s: query already finalized: %s", self.deployment, exc)

        timer = self._timer
        if delay_s > 0 and timer is not None:
            timer.call_later(delay_s, send)
        else:
            send()

    def hold(self, query: zenoh.Query) -> None:
        """Leave `query` unanswered (drop, stall): the querier sees a timeout."""
        timer = self._timer
        if timer is not None:
            timer.call_later(HOLD_UNANSWERED_S, query.drop)

    def internal_error(self, key: str, query: zenoh.Query, exc: Exception) -> None:
        """Answer a query on `key` whose callback failed (`Daemon.guarded` has logged why)."""
        if isinstance(exc, WireError):
            payload = error_reply(exc)
        else:
            payload = ErrorReply.make(
                ErrorCode.INTERNAL, "internal error; see the daemon log"
            ).to_wire()
        self.send(query, key, payload, 0.0)
