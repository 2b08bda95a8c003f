"""One offloaded frame: the query on the anycast service key with a deadline, and what came of it.

`CloudCall` hands an encoded `InferRequest` to Zenoh (after the emulated uplink's delay, if any)
with a `get` on the robot's service key, BEST_MATCHING target: exactly one deployment (the one in
service, which declared the key complete) computes it. The reply is caught by a callback, which
records its arrival time, so the frame loop can compute the local suffix meanwhile (hedging) and
still know which path finished first. `result()` decodes the reply in the caller's thread and
classifies every way the cloud can fail the frame (`common.wire.telemetry.FallbackReason`, whose
wire values these are):

| reason         | what happened                                                          |
| -------------- | ---------------------------------------------------------------------- |
| `no_route`     | no deployment serves the key (Zenoh finished the query at once)        |
| `timeout`      | no reply within the deadline (or the emulated uplink needed longer)   |
| `busy`         | the deployment's queue is full (`BusyReply`)                           |
| `error`        | an error reply (`ErrorReply`, or a Zenoh error other than a timeout)  |
| `decode_error` | a reply that is not a valid message, or not for this frame             |
| `stopped`      | the daemon was asked to stop while waiting                             |

The robot then finishes the frame itself: no frame is ever lost.

A query that Zenoh finishes with no reply before its deadline (`no_route`), or whose only reply
is NOT_SERVING (the old deployment, already in standby, had not withdrawn the key yet), is not
given up at once when the call knows the service key's matching status (`served`): it waits for
a matching queryable (at most `MATCH_WAIT_S`; after a NOT_SERVING first `NOT_SERVING_PAUSE_S`,
since the old deployment's declaration still matches) and is sent again, up to
`NO_ROUTE_RESENDS` times within the deadline, with target ALL and no consolidation (Zenoh's
default would keep one reply per key: the old deployment's NOT_SERVING could hide the new one's
answer). This covers the ways a move leaves a robot without a route (docs/registry.md, "A move
and the robot's route"): the old deployment's undeclaration reaching the robot before the new
one's declaration (a few frames), and zenoh 1.10's cached BEST_MATCHING route that still points
at the old deployment after it undeclared the key, when the new deployment's complete queryable
had been declared beside it (the route is not recomputed because the key's "complete" info did
not change; zenoh PR #2660): every frame then finished as `no_route` until the next declaration
change, 24 s once. A query with target ALL is routed afresh and reaches only sessions that still
declare the key; one that finished without a reply, or only with NOT_SERVING, never reached a
serving deployment, so the resend cannot make two deployments compute it; a NOT_SERVING reply to
the resend is passed over while another reply may still come. Each resend is kept with its
reason (`ResendReason`: no reply, or only NOT_SERVING) in `CallResult.resends`, for the frame's
telemetry and the robot's `resends_total` counter.

A video frame (`h264`) that the deployment could not decode is answered NEED_KEYFRAME (its
decoder does not hold the picture the P-frame is predicted from: frames were lost or served
elsewhere, the decoder was freed). Given `rekey`, the call then sends the frame again, once, as a
keyframe (`ResendReason.KEYFRAME`), with the deadline budget left and through the emulated uplink,
and waits for that answer; without time for it, the NEED_KEYFRAME error is the frame's answer and
the robot finishes the frame itself. Each query of the call has its generation: replies to an
earlier one are ignored once the keyframe is sent.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from common.wire import ErrorCode, ErrorReply, Message, WireError, decode
from common.wire.cloud_to_robot import INFER_REPLIES, BusyReply, InferReply
from common.wire.robot_to_cloud import VideoStream
from common.wire.telemetry import FallbackReason, ResendReason

log = logging.getLogger("robotd")

# Zenoh's error reply when a get's timeout expires.
ZENOH_TIMEOUT_TEXT = "Timeout"
# Extra wait past the deadline for Zenoh to finish the query itself before the robot gives up.
FINISH_GRACE_S = 0.05
# How often a waiting frame looks at the stop flag.
STOP_POLL_S = 0.05
# A query that found no serving deployment is sent again at most this many times within its
# deadline (a move: see `CloudCall`'s docstring).
NO_ROUTE_RESENDS = 3
# The longest a resend waits for the service key's matching status to say a deployment serves it
# (it is sent then anyway: in the stale-route case the status never stopped saying so).
MATCH_WAIT_S = 0.05
# A frame answered only NOT_SERVING is resent after this pause: the robot may not have seen the
# new deployment's declaration yet, while the old one's still says the key is served.
NOT_SERVING_PAUSE_S = 0.01
# A resend needs at least this much of the deadline left to be worth it.
MIN_RESEND_BUDGET_S = 0.005
# Replies at most this long are looked at on arrival for NOT_SERVING (an ErrorReply is ~100 B;
# an InferReply carries tensors and is never decoded on Zenoh's thread).
SMALL_REPLY_BYTES = 1024

Clock = Callable[[], float]
# A video frame's keyframe for a resend, given the budget left: (its payload, None when it cannot
# reach the deployment in time; its emulated uplink delay in seconds; its stream position).
Rekey = Callable[[float], tuple[bytes | None, float, VideoStream]]


@dataclass(frozen=True)
class CallResult:
    """What the cloud did with one request.

    `reply` is set when the frame was answered (`reason` None). Times are the caller's clock:
    `handed_at` when the request entered the (emulated) uplink, `sent_at` when Zenoh got it
    (None if it never did), `replied_at` when the first reply arrived, `finished_at` when the
    result was settled. `bytes_down` is the reply's size. `resends`: why each resend of the
    query was made, in order (empty when the first query settled it).
    """

    reply: InferReply | None
    reason: FallbackReason | None
    detail: str
    handed_at: float
    sent_at: float | None
    replied_at: float | None
    finished_at: float
    bytes_down: int
    deployment: str | None
    resends: tuple[ResendReason, ...] = ()

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
        served: Callable[[float], bool] | None = None,
        video: VideoStream | None = None,
        rekey: Rekey | None = None,
    ) -> None:
        self._session = session
        # A video frame: where it stands in its stream (a keyframe resend changes it), and what
        # makes its keyframe when the deployment cannot decode it.
        self.video = video
        self._rekey = rekey
        self._gen = 0  # the query whose replies count (a keyframe resend starts the next)
        self._need_keyframe: bytes | None = None
        self._sent_bytes = len(payload)
        # Waits at most the given seconds for a deployment serving the key (None: no resends).
        self._served = served
        self.resends_left = NO_ROUTE_RESENDS if served is not None else 0
        # Why each resend was made, in order (its length is the number of resends).
        self.resends: list[ResendReason] = []
        # A NOT_SERVING reply held back while the query may still be answered (resends only).
        self._not_serving: bytes | None = None
        # The reply already decoded on arrival (a small one, looked at for NOT_SERVING), so that
        # `result` does not decode it again.
        self._decoded: Message | None = None
        self._pause_s = 0.0
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
        self._listeners: list[threading.Event] = []

    @property
    def bytes_up(self) -> int:
        """Bytes sent for this frame (a keyframe resend included)."""
        return self._sent_bytes

    # -- sending ---------------------------------------------------------------------------
    def start(self, *, background: bool = False) -> None:
        """Send now, or after the uplink delay. A delay past the budget never sends (the
        deployment could not have received the request in time) but still settles at the
        deadline, as a real link would keep the robot waiting.

        `background`: hand the request to Zenoh from a thread of its own, so that the caller
        goes on at once. Zenoh's `get` blocks its caller while the link's queue is full (big
        payloads use `CongestionControl.BLOCK`): a hedged frame must not wait there to start
        its local run."""
        if self.delay_s >= self.budget_s:
            self._timer = threading.Timer(self.budget_s, self._finish)
            self._timer.daemon = True
            self._timer.start()
        elif self.delay_s > 0:
            self._timer = threading.Timer(self.delay_s, self._send)
            self._timer.daemon = True
            self._timer.start()
        elif background:
            sender = threading.Thread(target=self._send, name=f"send-{self.frame}", daemon=True)
            sender.start()
        else:
            self._send()

    def _send(self, resend: bool = False) -> None:
        remaining = self.deadline_at - self._clock()
        if remaining <= 0 or self._settled.is_set():
            self._finish()
            return
        if self.sent_at is None:
            self.sent_at = self._clock()
        gen = self._gen
        try:
            self._session.get(
                self._key,
                zenoh.handlers.Callback(
                    functools.partial(self._on_reply, gen), functools.partial(self._on_final, gen)
                ),
                payload=self._payload,
                target=zenoh.QueryTarget.ALL if resend else zenoh.QueryTarget.BEST_MATCHING,
                consolidation=zenoh.ConsolidationMode.NONE if resend else None,
                timeout=remaining,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        except zenoh.ZError as exc:  # e.g. the session was closed under us
            self._send_error = str(exc)
            self._finish()

    def _on_reply(self, gen: int, reply: zenoh.Reply) -> None:
        now = self._clock()
        with self._lock:
            if gen != self._gen or self.replied_at is not None or self._finished_at is not None:
                return  # only the first reply counts (anycast: there is only one)
            if reply.ok is not None:
                payload = reply.ok.payload.to_bytes()
                small = None
                if self._served is not None or self._rekey is not None:
                    small = _decode_small(payload, self._max_reply_bytes)
                if isinstance(small, ErrorReply) and small.error_code is ErrorCode.NOT_SERVING:
                    self._not_serving = payload  # settled (or resent) when the query finishes
                    return
                if isinstance(small, ErrorReply) and small.error_code is ErrorCode.NEED_KEYFRAME:
                    self._need_keyframe = payload  # the answer if no keyframe can be sent
                    if self._rekey_now():
                        return  # the keyframe's query answers the frame
                self.replied_at = now
                self._ok, self._decoded = payload, small
            else:
                self.replied_at = now
                self._err = reply.err.payload.to_bytes() if reply.err is not None else b""
        self._set_settled()

    def _rekey_now(self) -> bool:
        """NEED_KEYFRAME came (the lock is held): start the keyframe resend, once, if there is
        time for it; True when it was started."""
        if self._rekey is None or self.deadline_at - self._clock() <= MIN_RESEND_BUDGET_S:
            return False
        rekey, self._rekey = self._rekey, None
        self._gen += 1  # the first query's replies and end no longer count
        self.resends.append(ResendReason.KEYFRAME)
        threading.Thread(
            target=self._send_keyframe, args=(rekey,), name=f"keyframe-{self.frame}", daemon=True
        ).start()
        return True

    def _send_keyframe(self, rekey: Rekey) -> None:
        """Send the frame again as a keyframe (its uplink delay first); settle without an
        answer when it cannot reach the deployment before the deadline."""
        payload, delay_s, self.video = rekey(self.deadline_at - self._clock())
        if payload is None:  # no time left for it: NEED_KEYFRAME is the frame's answer
            with self._lock:
                if self.replied_at is None and self._finished_at is None:
                    self.replied_at, self._ok = self._clock(), self._need_keyframe
            self._set_settled()
            return
        self._payload = payload
        self._sent_bytes += len(payload)
        if delay_s > 0:  # the emulated uplink; cut short if the call settles meanwhile
            self._settled.wait(delay_s)
        self._send()

    def _on_final(self, gen: int) -> None:
        """Zenoh finished the query. Without a reply (or with only NOT_SERVING) and with time
        left, it found no serving deployment (a move under way, or a stale route): resend it
        from a thread of its own (this is Zenoh's callback thread), see the module docstring."""
        with self._lock:
            if gen != self._gen:
                return  # a query that a keyframe resend replaced
            resend = (
                self.replied_at is None
                and self._finished_at is None
                and self.resends_left > 0
                and self.deadline_at - self._clock() > MIN_RESEND_BUDGET_S
            )
            if resend:
                self.resends_left -= 1
                not_serving = self._not_serving is not None
                self.resends.append(
                    ResendReason.NOT_SERVING if not_serving else ResendReason.NO_REPLY
                )
                self._pause_s = NOT_SERVING_PAUSE_S if not_serving else 0.0
            elif self.replied_at is None and self._not_serving is not None:
                # Nothing but NOT_SERVING, and no resend left: that is the frame's answer.
                self.replied_at = self._clock()
                self._ok = self._not_serving
            self._not_serving = None
        if not resend:
            self._finish()
            return
        threading.Thread(target=self._resend, name=f"resend-{self.frame}", daemon=True).start()

    def _resend(self) -> None:
        assert self._served is not None  # resends_left is 0 without it
        if self._pause_s > 0:  # cut short if the call settles meanwhile (cancelled)
            self._settled.wait(min(self._pause_s, self.deadline_at - self._clock()))
        wait_s = min(MATCH_WAIT_S, self.deadline_at - self._clock() - MIN_RESEND_BUDGET_S)
        if wait_s > 0:
            self._served(wait_s)
        self._send(resend=True)

    def _finish(self) -> None:
        with self._lock:
            if self._finished_at is None:
                self._finished_at = self._clock()
        self._set_settled()

    def _set_settled(self) -> None:
        self._settled.set()
        for event in self._listeners:
            event.set()

    def notify(self, event: threading.Event) -> None:
        """Set `event` when the call settles (at once if it already has): lets a caller wait
        for the first of several things with one event."""
        self._listeners.append(event)
        if self._settled.is_set():
            event.set()

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
            resends = tuple(self.resends)
            if finished_at is None and replied_at is None:
                finished_at = self._finished_at = self._clock()
        end = replied_at if replied_at is not None else finished_at
        assert end is not None

        def fail(reason: FallbackReason, detail: str, deployment: str | None = None) -> CallResult:
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
                resends=resends,
            )

        if ok is None and err is None:
            if stopped and end < self.deadline_at:
                return fail(FallbackReason.STOPPED, "stopped while waiting for the cloud")
            if self._send_error is not None:
                return fail(FallbackReason.ERROR, f"could not send: {self._send_error}")
            if self.sent_at is None:
                return fail(
                    FallbackReason.TIMEOUT,
                    f"the emulated uplink needs {self.delay_s:.3f} s for "
                    f"{len(self._payload)} bytes, past the {self.budget_s:.3f} s deadline",
                )
            if end < self.deadline_at:
                return fail(
                    FallbackReason.NO_ROUTE, "no deployment serves this robot's service key"
                )
            return fail(FallbackReason.TIMEOUT, f"no reply within {self.budget_s:.3f} s")
        if err is not None:
            return self._classify_error(err, fail)
        assert ok is not None
        message = self._decoded
        if message is None:
            try:
                message = decode(ok, expect=INFER_REPLIES, max_bytes=self._max_reply_bytes)
            except WireError as exc:
                return fail(FallbackReason.DECODE_ERROR, f"bad reply: {exc}")
        if isinstance(message, BusyReply):
            return fail(
                FallbackReason.BUSY,
                f"{message.deployment} busy ({message.queued} queued, capacity {message.capacity})",
                message.deployment,
            )
        if isinstance(message, ErrorReply):
            reason = (
                FallbackReason.TIMEOUT
                if message.error_code is ErrorCode.DEADLINE_EXPIRED
                else FallbackReason.ERROR
            )
            return fail(reason, f"{message.code}: {message.reason}")
        assert isinstance(message, InferReply)
        if message.frame != self.frame:
            return fail(
                FallbackReason.DECODE_ERROR,
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
            resends=resends,
        )

    def _classify_error(self, err: bytes, fail: Callable[..., CallResult]) -> CallResult:
        """A Zenoh error reply: its timeout, or a replier's `reply_err`."""
        try:
            text = err.decode("utf-8")
        except UnicodeDecodeError:
            text = ""
        if text.strip() == ZENOH_TIMEOUT_TEXT:
            return fail(FallbackReason.TIMEOUT, f"no reply within {self.budget_s:.3f} s")
        try:
            message = decode(err, expect=ErrorReply, max_bytes=self._max_reply_bytes)
        except WireError:
            shown = text.strip()[:200] if text.strip().isprintable() else f"{len(err)} bytes"
            return fail(FallbackReason.ERROR, f"error reply: {shown}")
        return fail(FallbackReason.ERROR, f"{message.code}: {message.reason}")


def _decode_small(payload: bytes, max_bytes: int) -> Message | None:
    """A small reply decoded on arrival (on Zenoh's callback thread), to tell a deployment's
    NOT_SERVING (it crossed a switch and did not compute the frame); None for a large reply or
    one that does not decode (`CloudCall.result` decodes it then, and names the problem)."""
    if len(payload) > SMALL_REPLY_BYTES:
        return None
    try:
        return decode(payload, expect=INFER_REPLIES, max_bytes=max_bytes)
    except WireError:
        return None
