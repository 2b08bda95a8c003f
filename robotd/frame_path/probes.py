"""The robot's low-rate probes of every deployment, standbys included.

Every `PROBE_INTERVAL_S` the prober sends one `ProbeRequest` to the probe wildcard
(`dep/*/probe`) with `QueryTarget.ALL` and no consolidation, so every live deployment answers,
whatever its state. The request carries padding and asks for a reply-sized echo; each reply's
arrival time gives that deployment's round trip for a frame-like transfer.

The padding must not crowd out frames on a slow uplink (64 KiB every 2 s is half of 0.5 Mbit/s),
and the robot does not know its uplink's rate. So the padding adapts to what the probes
themselves measure (`next_padding_bytes`): it starts at `PROBE_MIN_PADDING_BYTES` and doubles
while the fastest reply's round trip stays under half of `PROBE_UPLINK_SHARE` × the interval,
and shrinks in proportion when the round trip exceeds that budget (halves when nothing answers).
Its ceiling is a typical cut (the median of the model's cut sizes, at most
`PROBE_MAX_PADDING_BYTES`). The round trip bounds the padding's time on the uplink, so probing
takes at most about that share of the link. On a link whose bare round trip exceeds the budget,
probes carry the minimum padding and measure latency alone.

For each reply the robot publishes a `ProbeReport` on
`tele/<robot>/probe` (the registry builds its probe profiles from them), and a report with
`ok=false` for every deployment whose liveliness token is up but which did not answer in time.

`expected_latency_s` in a report is the remote part of a frame through that deployment as the
robot can tell it: the probe's round trip plus the cloud time (queue + compute) the robot's
recent answered frames reported, the same quantity as a frame's `transfer_s + cloud_s`.
Probes are not paced by `--uplink-mbit` (the emulation paces frames only).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence

import zenoh

from common import keys
from common.keys import KeyKind, parse_key
from common.wire import ErrorReply, WireError, decode
from common.wire.registry import ProbeReply, ProbeRequest
from common.wire.telemetry import ProbeReport

log = logging.getLogger(__name__)

PROBE_INTERVAL_S = 2.0
PROBE_TIMEOUT_S = 0.5
PROBE_MAX_PADDING_BYTES = 64 * 1024
PROBE_MIN_PADDING_BYTES = 1024
# The share of the uplink's time the probes' padding may take.
PROBE_UPLINK_SHARE = 0.02
# The echo asked for: about the size of a classifier's reply.
PROBE_ECHO_BYTES = 4096
# Weight of a new answered frame in the moving average of the cloud's queue + compute time.
CLOUD_TIME_EWMA = 0.2


def probe_padding_bytes(cut_bytes: Sequence[int], cap: int = PROBE_MAX_PADDING_BYTES) -> int:
    """Padding sized like a typical cut: the median of the cut sizes, at most `cap`."""
    if not cut_bytes:
        return 0
    ordered = sorted(int(b) for b in cut_bytes)
    return min(cap, ordered[len(ordered) // 2])


def next_padding_bytes(
    current: int,
    fastest_rtt_s: float | None,
    *,
    interval_s: float,
    ceiling: int,
    share: float = PROBE_UPLINK_SHARE,
    floor: int = PROBE_MIN_PADDING_BYTES,
) -> int:
    """The next round's padding after a round with `current` bytes whose fastest answer took
    `fastest_rtt_s` (None: nobody answered). See the module docstring."""
    floor = min(floor, ceiling)
    budget_s = share * interval_s
    if fastest_rtt_s is None:
        wanted = current // 2
    elif fastest_rtt_s > budget_s:
        wanted = int(current * budget_s / fastest_rtt_s)
    elif fastest_rtt_s < budget_s / 2:
        wanted = 2 * current
    else:
        wanted = current
    return max(floor, min(ceiling, wanted))


class CloudTime:
    """Moving average of the cloud's queue + compute time over answered frames (thread-safe)."""

    def __init__(self) -> None:
        self._value: float | None = None
        self._lock = threading.Lock()

    def observe(self, seconds: float) -> None:
        with self._lock:
            if self._value is None:
                self._value = seconds
            else:
                self._value += CLOUD_TIME_EWMA * (seconds - self._value)

    @property
    def value(self) -> float | None:
        with self._lock:
            return self._value


class RobotProber:
    """Probes every deployment from its own thread; `start()`, then `stop()` (joins)."""

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        robot: str,
        *,
        max_padding_bytes: int,
        publish: Callable[[ProbeReport], None],
        alive_deployments: Callable[[], set[str]],
        cloud_time: CloudTime,
        interval_s: float = PROBE_INTERVAL_S,
        timeout_s: float = PROBE_TIMEOUT_S,
        max_reply_bytes: int,
        service: str | None = None,
    ) -> None:
        self._session = session
        self._service = service
        self._fleet = fleet
        self._robot = robot
        self.max_padding_bytes = max_padding_bytes
        self.padding_bytes = min(PROBE_MIN_PADDING_BYTES, max_padding_bytes)
        self._publish = publish
        self._alive_clouds = alive_deployments
        self._cloud_time = cloud_time
        self.interval_s = interval_s
        self.timeout_s = timeout_s
        self._max_reply_bytes = max_reply_bytes
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.rounds = 0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"probe-{self._robot}", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 1.5) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _run(self) -> None:
        # Bounded by the stop flag; each round is bounded by the probe timeout.
        while not self._stop.wait(self.interval_s):
            try:
                self.probe_once()
            except zenoh.ZError as exc:
                if self._stop.is_set():
                    return
                log.warning("probe round failed: %s", exc)

    def probe_once(self) -> list[ProbeReport]:
        """One round: query every deployment, publish and return the reports."""
        request = ProbeRequest(
            sender=self._robot,
            service=self._service,
            sent_at=time.time(),
            echo_bytes=PROBE_ECHO_BYTES,
            padding=bytes(self.padding_bytes),
        )
        payload = request.to_wire()
        started = time.perf_counter()
        replies = self._session.get(
            keys.dep_probe_all(self._fleet),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            payload=payload,
            timeout=self.timeout_s,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        reports: dict[str, ProbeReport] = {}
        fastest_s: float | None = None
        # The channel ends when every deployment answered or the timeout passed.
        for reply in replies:
            arrived = time.perf_counter()
            report = self._report(reply, arrived - started, len(payload))
            if report is not None and report.deployment not in reports:
                reports[report.deployment] = report
                if report.ok and (fastest_s is None or arrived - started < fastest_s):
                    fastest_s = arrived - started
        if fastest_s is not None or self._alive_clouds():
            self.padding_bytes = next_padding_bytes(
                self.padding_bytes,
                fastest_s,
                interval_s=self.interval_s,
                ceiling=self.max_padding_bytes,
            )
        for deployment in sorted(self._alive_clouds() - set(reports)):
            reports[deployment] = ProbeReport(
                service=self._service,
                robot=self._robot,
                deployment=deployment,
                ok=False,
                at=time.time(),
                up_bytes=len(payload),
                reason=f"no probe reply within {self.timeout_s:g} s",
            )
        for report in reports.values():
            self._publish(report)
        self.rounds += 1
        return list(reports.values())

    def _report(self, reply: zenoh.Reply, rtt_s: float, up_bytes: int) -> ProbeReport | None:
        if reply.ok is None:
            return None  # a Zenoh-level error (e.g. the timeout) names no deployment
        parts = parse_key(str(reply.ok.key_expr))
        deployment = parts.id if parts is not None and parts.kind is KeyKind.DEP_PROBE else None
        data = reply.ok.payload.to_bytes()
        try:
            message = decode(data, expect=(ProbeReply, ErrorReply), max_bytes=self._max_reply_bytes)
        except WireError as exc:
            if deployment is None:
                return None
            return self._failed(deployment, rtt_s, up_bytes, len(data), f"bad probe reply: {exc}")
        if isinstance(message, ErrorReply):
            if deployment is None:
                return None
            reason = f"probe refused: {message.code}: {message.reason}"
            return self._failed(deployment, rtt_s, up_bytes, len(data), reason)
        assert isinstance(message, ProbeReply)
        cloud = self._cloud_time.value
        return ProbeReport(
            service=self._service,
            robot=self._robot,
            deployment=message.deployment,
            ok=True,
            at=time.time(),
            rtt_s=rtt_s,
            up_bytes=up_bytes,
            down_bytes=len(data),
            load=message.load,
            capacity=message.capacity,
            expected_latency_s=rtt_s + (cloud or 0.0),
        )

    def _failed(
        self, deployment: str, rtt_s: float, up_bytes: int, down_bytes: int, reason: str
    ) -> ProbeReport:
        return ProbeReport(
            service=self._service,
            robot=self._robot,
            deployment=deployment,
            ok=False,
            at=time.time(),
            rtt_s=rtt_s,
            up_bytes=up_bytes,
            down_bytes=down_bytes,
            reason=reason,
        )
