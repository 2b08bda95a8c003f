"""The robot's link to the registry: registration, the route it holds, reroute requests, and the
watcher that says when the registry cannot be reached.

Reachability: the robot daemon's membership view (`common.membership`) reports the registry's
liveliness token to `registry_changed`. The link keeps that one boolean, its stop flag and the
route under one condition variable, so its watcher thread waits for "registry up", "registry
gone" or "stop" in a single wait, without polling, and `stop()` wakes it at once.

Watcher: while no registry is up it logs `registry at <endpoint> not reachable...; retrying`,
again with a doubling interval (`REGISTRY_RETRY_INITIAL_S` up to `REGISTRY_RETRY_MAX_S`) while
Zenoh keeps reconnecting; frames are finished on the robot meanwhile unless a deployment still
serves it. When a registry appears the robot registers (`reg/register`: protocol version,
capabilities, service, model digest) and takes the route from the reply. When it goes the robot
keeps its route: frames go peer to peer as before.

Route: `route/<robot>` messages, registration replies and reroute replies all go through
`apply_route`, which ignores another robot's route and any epoch older than the one held (epochs
only grow, so a late message cannot undo a newer switch).

Reroute: the frame loop asks for a new route after consecutive timeouts or missing routes;
`request_reroute` sends at most one `RerouteRequest` per `REROUTE_MIN_INTERVAL_S`, only while a
registry is up, and never waits for the answer (it comes on a guarded callback).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from typing import Protocol

import zenoh

from common import keys
from common.config import FleetConfig
from common.keys import Role
from common.throttled_log import ThrottledLog
from common.wire import WireError, decode
from common.wire.registry import (
    CAP_LOCAL_FALLBACK,
    CAP_PROBE_REPORTS,
    CAP_TELEMETRY,
    NO_CAPACITY_REASON,
    PROTOCOL_VERSION,
    RegisterReply,
    RegisterRequest,
    RerouteRequest,
    RouteChange,
)
from common.wire.telemetry import FallbackReason

# The robot's log lines come from one logger, whichever of its modules writes them.
log = logging.getLogger("robotd")

# "Registry unreachable" is repeated with this backoff while frames are computed locally.
REGISTRY_RETRY_INITIAL_S = 1.0
REGISTRY_RETRY_MAX_S = 30.0
REGISTER_TIMEOUT_S = 1.0
# At most one reroute request per this interval (the registry also sees failures in telemetry).
REROUTE_MIN_INTERVAL_S = 1.0
REROUTE_TIMEOUT_S = 1.0
# How long stopping waits for the watcher (it may be inside a registration of REGISTER_TIMEOUT_S).
THREAD_JOIN_S = 1.0
# A wait that only a signal can cut short looks at the daemon's stop flag this often: a signal
# handler sets that flag, it cannot notify the link's condition.
WAIT_SLICE_S = 0.1
ROBOT_CAPABILITIES = (CAP_LOCAL_FALLBACK, CAP_TELEMETRY, CAP_PROBE_REPORTS)

ReplyCallback = Callable[[zenoh.Reply], None]


class Guard(Protocol):
    """Wraps a Zenoh callback so that it never raises (`common.daemon.Daemon.guarded`)."""

    def __call__(self, callback: ReplyCallback, *, what: str | None = None) -> ReplyCallback: ...


@dataclass(frozen=True)
class Route:
    """The deployment the registry last said serves the robot (None: compute locally) and its
    epoch; `known` is False until the registry said anything."""

    deployment: str | None = None
    epoch: int = 0
    known: bool = False
    # Held without a deployment because every deployment is full (the registry's admission).
    no_capacity: bool = False
    # Round robin: every deployment serving the robot at this epoch (empty: anycast).
    pool: tuple[str, ...] = ()


class RegistryLink:
    """`RegistryLink(session, config, "robot-1", model_digest=..., throttled=..., guard=...)`.

    No I/O until used: `registry_changed` is fed by the daemon's membership view, `on_route` is
    its subscriber on `route/<robot>`, `start()` / `stop()` run the watcher thread.
    `throttled` takes the lines about bad input (garbage on the route key, a bad reply), so a
    flood of it cannot flood the log; `guard` wraps the reroute reply callback.
    """

    def __init__(
        self,
        session: zenoh.Session,
        config: FleetConfig,
        robot: str,
        *,
        model_digest: str,
        throttled: ThrottledLog,
        guard: Guard,
        max_in_flight: int = 1,
    ) -> None:
        self._session = session
        # Announced at registration: the deployments serving this robot admit as many.
        self._max_in_flight = max_in_flight
        self._fleet = config.fleet
        self._service = config.service_name
        self.endpoint = config.registry.endpoint
        self.robot = robot
        self._model_digest = model_digest
        self._throttled = throttled
        self._guard = guard
        # One lock and condition for the registry's reachability, the stop flag and the route.
        self._changed = threading.Condition()
        self._up = False
        self._stopping = False
        self._route = Route()
        self._last_reroute = -float("inf")
        self._watcher: threading.Thread | None = None

    # -- route -----------------------------------------------------------------------------
    @property
    def route(self) -> tuple[str | None, int]:
        """The deployment the registry last said serves this robot, and its epoch."""
        with self._changed:
            return self._route.deployment, self._route.epoch

    @property
    def epoch(self) -> int:
        """The epoch of the route held (0 before any)."""
        with self._changed:
            return self._route.epoch

    @property
    def held(self) -> Route:
        """The whole route held (deployment, epoch and pool read together)."""
        with self._changed:
            return self._route

    def on_route(self, sample: zenoh.Sample) -> None:
        """Subscriber callback on `route/<robot>`."""
        try:
            change = decode(sample.payload.to_bytes(), expect=RouteChange)
        except WireError as exc:
            self._throttled.warning("%s: ignoring a bad route message: %s", self.robot, exc)
            return
        self.apply_route(change)

    def apply_route(self, change: RouteChange) -> bool:
        """Take `change` unless it is another robot's or another service's (None: a registry of
        a one-service fleet) or older than the route held; True if it was taken."""
        if change.robot != self.robot or change.service not in (None, self._service):
            return False
        with self._changed:
            held = self._route
            if held.known and change.epoch < held.epoch:
                return False  # older than what we hold: epochs only grow
            moved = not held.known or change.deployment != held.deployment
            pooled = change.pool != held.pool and len(change.pool) > 1
            no_capacity = change.deployment is None and change.reason == NO_CAPACITY_REASON
            refused = no_capacity and not held.no_capacity
            self._route = Route(change.deployment, change.epoch, True, no_capacity, change.pool)
            self._changed.notify_all()
        if refused:
            # Logged once per change, not for every repetition of the same refusal (a restarted
            # registry tells it again): frames are finished on the robot, none is lost.
            log.info(
                "%s: no deployment has room: computing locally (epoch %d, %s)",
                self.robot,
                change.epoch,
                change.reason,
            )
        elif moved or pooled:
            log.info(
                "%s: route -> %s (epoch %d, %s)",
                self.robot,
                f"pool {', '.join(change.pool)}"
                if len(change.pool) > 1
                else change.deployment or "local (no deployment)",
                change.epoch,
                change.reason,
            )
        return True

    def wait_for_epoch(self, epoch: int, timeout_s: float) -> bool:
        """Block until a route of at least `epoch` is held (True) or `timeout_s` passed."""
        with self._changed:
            return self._changed.wait_for(
                lambda: self._route.known and self._route.epoch >= epoch, timeout_s
            )

    # -- reachability ----------------------------------------------------------------------
    def registry_changed(self, up: bool) -> None:
        """Whether any registry's token is alive now (from the membership view)."""
        with self._changed:
            self._up = up
            self._changed.notify_all()

    @property
    def reachable(self) -> bool:
        with self._changed:
            return self._up

    def wait_reachable(self, timeout_s: float, interrupt: threading.Event) -> bool:
        """Block until a registry is up (True), `timeout_s` passed or `interrupt` is set.

        For the daemon's main thread: a signal only sets the daemon's stop flag (`interrupt`),
        so the wait looks at it every `WAIT_SLICE_S`."""
        end = time.monotonic() + timeout_s
        with self._changed:
            while not self._up and not interrupt.is_set():
                left = end - time.monotonic()
                if left <= 0:
                    break
                self._changed.wait(min(left, WAIT_SLICE_S))
            return self._up

    def report_unreachable(self, still: str, next_s: float) -> None:
        log.warning(
            "%s: registry at %s not reachable%s; frames are finished on the robot unless a "
            "deployment still serves it; retrying (next report in %.0f s)",
            self.robot,
            self.endpoint,
            still,
            next_s,
        )

    # -- watcher ---------------------------------------------------------------------------
    def start(self, *, reported: bool) -> None:
        """Start the watcher thread. `reported`: the caller already said the registry is
        unreachable (the next report then comes after the first backoff)."""
        self._watcher = threading.Thread(
            target=self._watch, args=(reported,), name=f"registry-watch-{self.robot}", daemon=True
        )
        self._watcher.start()

    def stop(self, timeout_s: float = THREAD_JOIN_S) -> None:
        """Wake the watcher and wait (bounded) for it to end; later waits return at once."""
        with self._changed:
            self._stopping = True
            self._changed.notify_all()
        if self._watcher is not None:
            self._watcher.join(timeout_s)

    def _watch(self, reported: bool) -> None:
        """Report the registry's reachability and register when it appears; until `stop()`."""
        backoff = REGISTRY_RETRY_INITIAL_S
        if reported:
            self._wait_registry(up=True, timeout_s=backoff)
            backoff *= 2
        still = " yet" if reported else ""
        while not self._stopped():
            if not self.reachable:
                self.report_unreachable(still, backoff)
                self._wait_registry(up=True, timeout_s=backoff)
                backoff, still = min(backoff * 2, REGISTRY_RETRY_MAX_S), " yet"
                continue
            log.info("%s: registry reachable at %s", self.robot, self.endpoint)
            backoff, still = REGISTRY_RETRY_INITIAL_S, ""
            self.register()
            self._wait_registry(up=False, timeout_s=None)
            if self._stopped():
                return
            deployment, epoch = self.route
            log.warning(
                "%s: registry gone; keeping the route to %s (epoch %d), frames go peer to peer; "
                "retrying",
                self.robot,
                deployment or "(none known)",
                epoch,
            )
            # That was the first report: the next one comes after the backoff.
            self._wait_registry(up=True, timeout_s=backoff)
            backoff, still = backoff * 2, " yet"

    def _wait_registry(self, *, up: bool, timeout_s: float | None) -> None:
        """Until the registry is `up` (or gone), `timeout_s` (None: no limit) or `stop()`."""
        with self._changed:
            self._changed.wait_for(lambda: self._stopping or self._up == up, timeout_s)

    def _stopped(self) -> bool:
        with self._changed:
            return self._stopping

    # -- requests --------------------------------------------------------------------------
    def register(self) -> None:
        """Register on `reg/register` and take the route from the reply (waits at most
        `REGISTER_TIMEOUT_S`)."""
        request = RegisterRequest(
            role=Role.ROBOT,
            id=self.robot,
            protocol_version=PROTOCOL_VERSION,
            capabilities=ROBOT_CAPABILITIES,
            service=self._service,
            model_digest=self._model_digest,
            software=_software_version(),
            max_in_flight=self._max_in_flight,
        )
        try:
            replies = self._session.get(
                keys.reg_register(self._fleet),
                payload=request.to_wire(),
                timeout=REGISTER_TIMEOUT_S,
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    answer = decode(reply.ok.payload.to_bytes(), expect=RegisterReply)
                except WireError as exc:
                    self._throttled.warning("%s: bad registration reply: %s", self.robot, exc)
                    continue
                if not answer.accepted:
                    log.error(
                        "%s: the registry refused this robot: %s; frames are finished on the robot",
                        self.robot,
                        answer.reason,
                    )
                elif answer.route is not None:
                    self.apply_route(answer.route)
                return
        except zenoh.ZError as exc:
            log.debug("%s: registration not sent: %s", self.robot, exc)

    def request_reroute(self, reason: FallbackReason, consecutive: int) -> bool:
        """Ask the registry for another deployment after `consecutive` frames failed with
        `reason`; the answer is applied when it comes. False when not sent (no registry up,
        or the last request was less than `REROUTE_MIN_INTERVAL_S` ago)."""
        now = time.monotonic()
        with self._changed:
            if not self._up or now - self._last_reroute < REROUTE_MIN_INTERVAL_S:
                return False
            self._last_reroute = now
            held = self._route
        request = RerouteRequest(
            robot=self.robot,
            service=self._service,
            deployment=held.deployment,
            epoch=held.epoch,
            reason=reason,
            consecutive_timeouts=consecutive,
        )
        try:
            self._session.get(
                keys.reg_reroute(self._fleet),
                self._guard(self._on_reroute_reply, what="a reroute reply"),
                payload=request.to_wire(),
                timeout=REROUTE_TIMEOUT_S,
            )
        except zenoh.ZError as exc:
            log.debug("%s: reroute request not sent: %s", self.robot, exc)
            return False
        log.info(
            "%s: asked the registry for a new route after %d frame(s) of %s",
            self.robot,
            consecutive,
            reason,
        )
        return True

    def _on_reroute_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is None:
            return
        try:
            change = decode(reply.ok.payload.to_bytes(), expect=RouteChange)
        except WireError:
            return  # an ErrorReply: the registry could not move us; telemetry tells it more
        self.apply_route(change)


def _software_version() -> str:
    try:
        return metadata.version("elasticfog")
    except metadata.PackageNotFoundError:
        return ""
