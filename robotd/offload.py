"""One offloaded frame: the query on the anycast service key with a deadline, and what came of it.

`CloudCall` hands an encoded `InferRequest` to Zenoh (after the emulated uplink's delay, if any)
with a `get` on the robot's service key, BEST_MATCHING target: exactly one deployment (the one in
service, which declared the key complete) computes it. The reply is caught by a callback, which
records its arrival time, so the frame loop can compute the local suffix meanwhile (hedging) and
still know which path finished first. `result()` decodes the reply in the caller's thread and
classifies every way the cloud can fail the frame:

| reason         | what happened                                                          |
| -------------- | ---------------------------------------------------------------------- |
| `no_route`     | no deployment serves the key (Zenoh finished the query at once)        |
| `timeout`      | no reply within the deadline (or the emulated uplink needed longer)   |
| `busy`         | the deployment's queue is full (`BusyReply`)                           |
| `error`        | an error reply (`ErrorReply`, or a Zenoh error other than a timeout)  |
| `decode_error` | a reply that is not a valid message, or not for this frame             |
| `stopped`      | the daemon was asked to stop while waiting                             |

The robot then finishes the frame itself: no frame is ever lost.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from common.wire import ErrorCode, ErrorReply, WireError, decode
from common.wire.cloud_to_robot import INFER_REPLIES, BusyReply, InferReply

REASON_NO_ROUTE = "no_route"
REASON_TIMEOUT = "timeout"
REASON_BUSY = "busy"
REASON_ERROR = "error"
REASON_DECODE_ERROR = "decode_error"
REASON_STOPPED = "stopped"
REASONS = (
    REASON_NO_ROUTE,
    REASON_TIMEOUT,
    REASON_BUSY,
    REASON_ERROR,
    REASON_DECODE_ERROR,
    REASON_STOPPED,
)

# Zenoh's error reply when a get's timeout expires.
ZENOH_TIMEOUT_TEXT = "Timeout"
# Extra wait past the deadline for Zenoh to finish the query itself before the robot gives up.
FINISH_GRACE_S = 0.05
# How often a waiting frame looks at the stop flag.
STOP_POLL_S = 0.05

Clock = Callable[[], float]


@dataclass(frozen=True)
class CallResult:
    """What the cloud did with one request.

    `reply` is set when the frame was answered (`reason` None). Times are the caller's clock:
    `handed_at` when the request entered the (emulated) uplink, `sent_at` when Zenoh got it
    (None if it never did), `replied_at` when the first reply arrived, `finished_at` when the
    result was settled. `bytes_down` is the reply's size.
    """

    reply: InferReply | None
    reason: str | None
    detail: str
    handed_at: float
    sent_at: float | None
    replied_at: float | None
    finished_at: float
    bytes_down: int
    deployment: str | None

    @property
    def answered(self) -> bool:
        return self.reply is not None

    @property
    def round_trip_s(self) -> float:
        """From handing the request to the uplink to its reply (or to giving up)."""
        end = self.replied_at if self.replied_at is not None else self.finished_at
        return max(0.0, end - self.handed_at)


class CloudCall:
    """One request in flight. `start()` sends it (now, or after `delay_s` of emulated uplink);
    `wait()` blocks until it is settled; `result()` decodes and classifies it."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        payload: bytes,
        *,
        frame: int,
        budget_s: float,
        delay_s: float = 0.0,
        max_reply_bytes: int,
        clock: Clock = time.perf_counter,
    ) -> None:
        self._session = session
        self._key = key
        self._payload = payload
        self.frame = frame
        self.budget_s = budget_s
        self.delay_s = delay_s
        self._max_reply_bytes = max_reply_bytes
        self._clock = clock
        self._lock = threading.Lock()
        self._settled = threading.Event()
        self._timer: threading.Timer | None = None
        self.handed_at = clock()
        self.deadline_at = self.handed_at + budget_s
        self.sent_at: float | None = None
        self.replied_at: float | None = None
        self._finished_at: float | None = None
        self._ok: bytes | None = None
        self._err: bytes | None = None
        self._send_error: str | None = None
        self._result: CallResult | None = None

    @property
    def bytes_up(self) -> int:
        return len(self._payload)

    # -- sending ---------------------------------------------------------------------------
    def start(self) -> None:
        """Send now, or after the uplink delay. A delay past the budget never sends (the
        deployment could not have received the request in time) but still settles at the
        deadline, as a real link would keep the robot waiting."""
        if self.delay_s >= self.budget_s:
            self._timer = threading.Timer(self.budget_s, self._finish)
            self._timer.daemon = True
            self._timer.start()
        elif self.delay_s > 0:
            self._timer = threading.Timer(self.delay_s, self._send)
            self._timer.daemon = True
            self._timer.start()
        else:
            self._send()

    def _send(self) -> None:
        remaining = self.deadline_at - self._clock()
        if remaining <= 0 or self._settled.is_set():
            self._finish()
            return
        self.sent_at = self._clock()
        try:
            self._session.get(
                self._key,
                zenoh.handlers.Callback(self._on_reply, self._finish),
                payload=self._payload,
                timeout=remaining,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        except zenoh.ZError as exc:  # e.g. the session was closed under us
            self._send_error = str(exc)
            self._finish()

    def _on_reply(self, reply: zenoh.Reply) -> None:
        now = self._clock()
        with self._lock:
            if self.replied_at is not None or self._finished_at is not None:
                return  # only the first reply counts (anycast: there is only one)
            self.replied_at = now
            if reply.ok is not None:
                self._ok = reply.ok.payload.to_bytes()
            else:
                self._err = reply.err.payload.to_bytes() if reply.err is not None else b""
        self._settled.set()

    def _finish(self) -> None:
        with self._lock:
            if self._finished_at is None:
                self._finished_at = self._clock()
        self._settled.set()

    # -- waiting ---------------------------------------------------------------------------
    @property
    def settled(self) -> bool:
        """True once a reply came, or the query ended without one."""
        return self._settled.is_set()

    def wait(self, stop: threading.Event | None = None) -> bool:
        """Block until settled or the deadline (plus a little grace) passed; False when `stop`
        was set first. Bounded by the deadline whatever Zenoh does."""
        limit = self.deadline_at + FINISH_GRACE_S
        while not self._settled.is_set():
            remaining = limit - self._clock()
            if remaining <= 0:
                return True
            if stop is not None and stop.is_set():
                return False
            self._settled.wait(min(remaining, STOP_POLL_S) if stop is not None else remaining)
        return True

    def cancel(self) -> None:
        """Stop a request still waiting for the emulated uplink."""
        if self._timer is not None:
            self._timer.cancel()
        self._finish()

    # -- result ----------------------------------------------------------------------------
    def result(self, *, stopped: bool = False) -> CallResult:
        """Decode and classify (once; later calls return the same result)."""
        if self._result is None:
            self._result = self._classify(stopped)
        return self._result

    def _classify(self, stopped: bool) -> CallResult:
        with self._lock:
            ok, err, replied_at = self._ok, self._err, self.replied_at
            finished_at = self._finished_at
            if finished_at is None and replied_at is None:
                finished_at = self._finished_at = self._clock()
        end = replied_at if replied_at is not None else finished_at
        assert end is not None

        def fail(reason: str, detail: str, deployment: str | None = None) -> CallResult:
            return CallResult(
                reply=None,
                reason=reason,
                detail=detail,
                handed_at=self.handed_at,
                sent_at=self.sent_at,
                replied_at=replied_at,
                finished_at=end,
                bytes_down=len(ok or err or b""),
                deployment=deployment,
            )

        if ok is None and err is None:
            if stopped and end < self.deadline_at:
                return fail(REASON_STOPPED, "stopped while waiting for the cloud")
            if self._send_error is not None:
                return fail(REASON_ERROR, f"could not send: {self._send_error}")
            if self.sent_at is None:
                return fail(
                    REASON_TIMEOUT,
                    f"the emulated uplink needs {self.delay_s:.3f} s for "
                    f"{len(self._payload)} bytes, past the {self.budget_s:.3f} s deadline",
                )
            if end < self.deadline_at:
                return fail(REASON_NO_ROUTE, "no deployment serves this robot's service key")
            return fail(REASON_TIMEOUT, f"no reply within {self.budget_s:.3f} s")
        if err is not None:
            return self._classify_error(err, fail)
        assert ok is not None
        try:
            message = decode(ok, expect=INFER_REPLIES, max_bytes=self._max_reply_bytes)
        except WireError as exc:
            return fail(REASON_DECODE_ERROR, f"bad reply: {exc}")
        if isinstance(message, BusyReply):
            return fail(
                REASON_BUSY,
                f"{message.deployment} busy ({message.queued} queued, capacity {message.capacity})",
                message.deployment,
            )
        if isinstance(message, ErrorReply):
            reason = (
                REASON_TIMEOUT if message.error_code is ErrorCode.DEADLINE_EXPIRED else REASON_ERROR
            )
            return fail(reason, f"{message.code}: {message.reason}")
        assert isinstance(message, InferReply)
        if message.frame != self.frame:
            return fail(
                REASON_DECODE_ERROR,
                f"reply for frame {message.frame}, expected {self.frame}",
                message.deployment,
            )
        return CallResult(
            reply=message,
            reason=None,
            detail="",
            handed_at=self.handed_at,
            sent_at=self.sent_at,
            replied_at=replied_at,
            finished_at=end,
            bytes_down=len(ok),
            deployment=message.deployment,
        )

    def _classify_error(self, err: bytes, fail: Callable[..., CallResult]) -> CallResult:
        """A Zenoh error reply: its timeout, or a replier's `reply_err`."""
        try:
            text = err.decode("utf-8")
        except UnicodeDecodeError:
            text = ""
        if text.strip() == ZENOH_TIMEOUT_TEXT:
            return fail(REASON_TIMEOUT, f"no reply within {self.budget_s:.3f} s")
        try:
            message = decode(err, expect=ErrorReply, max_bytes=self._max_reply_bytes)
        except WireError:
            shown = text.strip()[:200] if text.strip().isprintable() else f"{len(err)} bytes"
            return fail(REASON_ERROR, f"error reply: {shown}")
        return fail(REASON_ERROR, f"{message.code}: {message.reason}")
