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
from dataclasses import dataclass

import numpy as np
import onnxruntime as ort
import zenoh

from common.wire import ErrorCode, ErrorReply, Message, WireError, decode
from common.wire.cloud_to_robot import INFER_REPLIES, BusyReply, InferReply
from common.wire.telemetry import FallbackReason, ResendReason

log = logging.getLogger("robotd")

# Nice value of the speculative local run's thread: Linux's lowest priority (weight 15 against
# 1024 for the offload's threads at nice 0).
SPECULATIVE_NICE = 19
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
    ) -> None:
        self._session = session
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
        return len(self._payload)

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
        try:
            self._session.get(
                self._key,
                zenoh.handlers.Callback(self._on_reply, self._on_final),
                payload=self._payload,
                target=zenoh.QueryTarget.ALL if resend else zenoh.QueryTarget.BEST_MATCHING,
                consolidation=zenoh.ConsolidationMode.NONE if resend else None,
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
            if reply.ok is not None:
                payload = reply.ok.payload.to_bytes()
                small = None
                if self._served is not None:
                    small = _decode_small(payload, self._max_reply_bytes)
                if isinstance(small, ErrorReply) and small.error_code is ErrorCode.NOT_SERVING:
                    self._not_serving = payload  # settled (or resent) when the query finishes
                    return
                self.replied_at = now
                self._ok, self._decoded = payload, small
            else:
                self.replied_at = now
                self._err = reply.err.payload.to_bytes() if reply.err is not None else b""
        self._set_settled()

    def _on_final(self) -> None:
        """Zenoh finished the query. Without a reply (or with only NOT_SERVING) and with time
        left, it found no serving deployment (a move under way, or a stale route): resend it
        from a thread of its own (this is Zenoh's callback thread), see the module docstring."""
        with self._lock:
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
