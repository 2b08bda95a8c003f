"""The epoch-fenced switch protocol: moves a robot from one deployment to another.

Order of operations (the anycast invariant: each request is computed by exactly one deployment):
1. reserve epoch e+1 in the RIB (persisted first, so a crash never reuses it);
2. new deployment → `service(robot, e+1)`; wait for its acknowledgement (it has declared the robot's
   service key). No ack (timeout, refusal, transport error, a stale ack) → record `ack_failed` with
   the reason and try the next candidate under a fresh epoch;
3. persist the route robot → new deployment under e+1;
4. publish the route change;
5. old deployment → `standby(robot, e+1)`, skipped (recorded as standby) when it is dead;
   candidates that did not ack get `standby` too, so a late `service` cannot leave two deployments
   serving.

Round robin (`dispatch: round_robin`, `registry.pools`): step 2 is followed by `service(robot,
e+1)` to every other member the pool planner names; those that acknowledge form the pool that
step 3 persists and step 4 publishes (the deployment first); a member that does not is left out
and fenced; members of the old pool that are not in the new one get `standby` in step 5.
`repool` rebuilds a pool around the same deployment under a new epoch when a member dies.

Epochs only grow. A deployment refuses a request whose epoch is lower than the one it holds for
the robot and answers with its state and epoch; the same epoch again is idempotent, which is how a
restarted registry re-asserts a restored route (`reassert`). A reply whose epoch, robot,
deployment or state does not match the request is a stale ack and is ignored. A refusal that names
a newer epoch (the RIB was restored from an older file) raises the RIB's epoch past it and retries
that deployment once.

The messages are the wire's (`CtlRequest`, `CtlReply`, `RouteChange` of common/wire/registry.py),
so there is one definition of each; a switcher works for one service (`service`: each service's
plane has its own), named in every request and route change it sends. The transport is abstract
(`SwitchTransport`): the registry daemon plugs Zenoh in (registry/transport.py: queries on
`ef/<fleet>/dep/<id>/ctl`, a publication on `ef/<fleet>/route/<robot>`); tests plug in a fake. One
`Switcher` is driven by one thread (the registry's control loop); the RIB serializes its own writes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

from common.wire.registry import CtlOp, CtlReply, CtlRequest, DeploymentState, RouteChange
from registry.pools import PoolPlanner
from registry.rib import EventKind, Rib
from registry.scheduler import RouteDecision, Scheduler

CTL_TIMEOUT_S = 0.5
DEFAULT_SENDER = "registry"
STANDBY_REASON = "another deployment serves the robot"

# The state a deployment acknowledges for each request it can be sent here.
_ACKED_STATE = {CtlOp.SERVICE: DeploymentState.SERVICE, CtlOp.STANDBY: DeploymentState.STANDBY}


class TransportError(Exception):
    """The transport could not deliver a request or publication (the message says why)."""


class SwitchTransport(Protocol):
    """What the switch protocol needs from the network."""

    def send_ctl(self, deployment: str, request: CtlRequest, timeout_s: float) -> CtlReply | None:
        """Send a state request to a deployment; its reply, or None after `timeout_s` without one.

        Raises `TransportError` when the request cannot be sent or the reply cannot be decoded.
        """
        ...

    def publish_route(self, change: RouteChange) -> None:
        """Publish a route change to the robot (and anyone watching); may raise TransportError."""
        ...


class SwitchOutcome(str, Enum):
    """How one service request ended."""

    ACKED = "acked"
    TIMEOUT = "timeout"
    REFUSED = "refused"
    STALE = "stale_ack"
    ERROR = "transport_error"


@dataclass(frozen=True)
class Attempt:
    """One service request to one candidate."""

    deployment: str
    epoch: int
    outcome: SwitchOutcome
    detail: str = ""


@dataclass(frozen=True)
class SwitchResult:
    """The route after a switch attempt, and the attempts made."""

    robot: str
    previous: str | None
    deployment: str | None
    epoch: int
    changed: bool
    reason: str
    attempts: tuple[Attempt, ...] = ()
    pool: tuple[str, ...] = ()
    """Round robin: the pool the route was set with, `deployment` first (empty otherwise)."""


@dataclass(frozen=True)
class _Answer:
    outcome: SwitchOutcome
    detail: str
    newer_epoch: int | None = None


class Switcher:
    """Runs the switch protocol over a transport, persisting every step in the RIB."""

    def __init__(
        self,
        rib: Rib,
        transport: SwitchTransport,
        *,
        ctl_timeout_s: float = CTL_TIMEOUT_S,
        sender: str = DEFAULT_SENDER,
        clock: Callable[[], float] = time.time,
        pools: PoolPlanner | None = None,
        in_flight: Callable[[str], int | None] | None = None,
        service: str | None = None,
    ) -> None:
        if not ctl_timeout_s > 0:
            raise ValueError(f"ctl_timeout_s must be > 0, got {ctl_timeout_s!r}")
        self.rib = rib
        self.transport = transport
        self.ctl_timeout_s = ctl_timeout_s
        self.sender = sender
        # Wall clock of published route changes (`RouteChange.at`), like the RIB's times.
        self._clock = clock
        # Round-robin fleets: who joins a robot's pool (None: anycast, one deployment each).
        self.pools = pools
        # The frames in flight a robot announced at registration, passed on with service and
        # standby so the deployment admits as many of its requests (None: not known).
        self._in_flight = in_flight
        # The service whose routes these are (None: a one-service peer's, unnamed).
        self.service = service

    def apply(self, decision: RouteDecision) -> SwitchResult:
        """Carry out a scheduler decision; a decision about a route that changed meanwhile is
        dropped unchanged."""
        route = self.rib.route(decision.robot)
        current = route.deployment if route else None
        if current != decision.from_deployment:
            return SwitchResult(
                robot=decision.robot,
                previous=current,
                deployment=current,
                epoch=route.epoch if route else 0,
                changed=False,
                reason=f"stale decision (route is {current or 'local'} now)",
            )
        if decision.to_deployment is None and current is None:
            return self._tell_local(decision.robot, decision.reason.value)
        candidates = decision.candidates or (
            (decision.to_deployment,) if decision.to_deployment is not None else ()
        )
        return self.switch(decision.robot, candidates, reason=decision.reason.value)

    def _tell_local(self, robot: str, reason: str) -> SwitchResult:
        """A robot without a route stays without one, and is told why (e.g. `no_capacity`):
        a route to no deployment under a new epoch. No deployment serves it, none to stand by."""
        epoch = self.rib.reserve_epoch(robot)
        self.rib.set_route(robot, None, epoch, reason)
        self._publish(self._change(robot, None, epoch, reason))
        return SwitchResult(robot, None, None, epoch, True, reason)

    def switch(self, robot: str, candidates: Sequence[str], *, reason: str) -> SwitchResult:
        """Move `robot` to the first candidate that acknowledges `service`.

        With no taker the route stays where it is when the old deployment is alive; otherwise the
        route is dropped (the robot computes locally) under a new epoch.
        """
        route = self.rib.route(robot)
        previous = route.deployment if route else None
        attempts: list[Attempt] = []
        failed: list[str] = []
        tried: set[str] = set()
        for deployment in candidates:
            if deployment == previous or deployment in tried:
                continue
            tried.add(deployment)
            epoch = self.rib.reserve_epoch(robot)
            answer = self._request(deployment, self._ctl(CtlOp.SERVICE, robot, epoch, reason))
            if answer.newer_epoch is not None:
                attempts.append(Attempt(deployment, epoch, answer.outcome, answer.detail))
                epoch = self._epoch_past(robot, deployment, answer.newer_epoch)
                answer = self._request(deployment, self._ctl(CtlOp.SERVICE, robot, epoch, reason))
            attempts.append(Attempt(deployment, epoch, answer.outcome, answer.detail))
            if answer.outcome is SwitchOutcome.ACKED:
                return self._commit(robot, previous, deployment, epoch, reason, failed, attempts)
            failed.append(deployment)
            self._ack_failed(robot, deployment, epoch, reason, answer)
        return self._no_taker(
            robot, route.epoch if route else 0, previous, reason, failed, attempts
        )

    def _epoch_past(self, robot: str, deployment: str, newer: int | None) -> int:
        """A fresh epoch for `robot` past `newer`, the epoch `deployment` says it already holds
        (recorded as an event), so the next service request cannot be refused as stale."""
        epoch = self.rib.reserve_epoch(robot, at_least=newer + 1 if newer is not None else 0)
        if newer is not None:
            self.rib.record_event(
                EventKind.EPOCH_RAISED,
                robot=robot,
                deployment=deployment,
                epoch=epoch,
                reason=f"{deployment} knows epoch {newer}",
            )
        return epoch

    def reassert(self, robot: str, *, reason: str = "restore") -> SwitchResult:
        """Re-send `service` at the route's own epoch to the deployment the RIB routes `robot` to.

        A restarted registry confirms its restored routes this way, and a cloud daemon restarted
        while the registry was away (it starts in standby) declares the service key again; a
        deployment already serving at that epoch just acknowledges. A refusal (the deployment
        holds that epoch or a newer one in another state, e.g. the RIB file is older than its
        memory) moves the route to a fresh epoch past it on the same deployment, persisted and
        published. `changed` is true only then; the last attempt's outcome tells whether the
        route is confirmed.
        """
        route = self.rib.route(robot)
        if route is None or route.deployment is None:
            epoch = route.epoch if route else 0
            return SwitchResult(robot, None, None, epoch, False, "no route to restore")
        deployment, epoch = route.deployment, route.epoch
        answer = self._request(deployment, self._ctl(CtlOp.SERVICE, robot, epoch, reason))
        attempts = [Attempt(deployment, epoch, answer.outcome, answer.detail)]
        if answer.outcome is SwitchOutcome.REFUSED:
            epoch = self._epoch_past(robot, deployment, answer.newer_epoch)
            answer = self._request(deployment, self._ctl(CtlOp.SERVICE, robot, epoch, reason))
            attempts.append(Attempt(deployment, epoch, answer.outcome, answer.detail))
            if answer.outcome is SwitchOutcome.ACKED:
                self.rib.set_route(robot, deployment, epoch, reason)
                self._publish(self._change(robot, deployment, epoch, reason))
                return SwitchResult(
                    robot, deployment, deployment, epoch, True, reason, tuple(attempts)
                )
        if answer.outcome is SwitchOutcome.ACKED:
            return SwitchResult(
                robot, deployment, deployment, epoch, False, reason, tuple(attempts)
            )
        self._ack_failed(robot, deployment, epoch, reason, answer)
        return SwitchResult(
            robot, deployment, deployment, route.epoch, False, reason, tuple(attempts)
        )

    def fence(self, robot: str, deployment: str, *, at_least: int = 0) -> None:
        """Put `deployment` in standby for `robot` at the highest epoch issued (or `at_least`,
        the epoch the deployment says it holds): repairs a deployment found serving a robot the
        RIB routes elsewhere (e.g. one that missed its standby while unreachable)."""
        self._standby(robot, deployment, max(self.rib.issued_epoch(robot), at_least))

    # -- steps ---------------------------------------------------------------------------------
    def _commit(
        self,
        robot: str,
        previous: str | None,
        deployment: str,
        epoch: int,
        reason: str,
        failed: list[str],
        attempts: list[Attempt],
    ) -> SwitchResult:
        old_pool = self._pool_of(robot)
        pool = self._enlist(robot, deployment, epoch, reason, attempts)
        self.rib.set_route(robot, deployment, epoch, reason, pool=pool)
        self._publish(self._change(robot, deployment, epoch, reason, pool))
        for old in dict.fromkeys([previous, *failed, *old_pool]):
            if old is not None and old != deployment and old not in pool:
                self._standby(robot, old, epoch)
        return SwitchResult(robot, previous, deployment, epoch, True, reason, tuple(attempts), pool)

    def repool(self, robot: str, *, reason: str = "pool") -> SwitchResult:
        """Round robin: rebuild `robot`'s pool around its deployment under a new epoch (a member
        died or a usable deployment is outside a short pool). The deployment is asked first; if
        it does not acknowledge, nothing changes (moving the robot is the scheduler's part)."""
        route = self.rib.route(robot)
        if self.pools is None or route is None or route.deployment is None:
            epoch = route.epoch if route else 0
            current = route.deployment if route else None
            return SwitchResult(robot, current, current, epoch, False, "no pool to rebuild")
        deployment = route.deployment
        epoch = self.rib.reserve_epoch(robot)
        answer = self._request(deployment, self._ctl(CtlOp.SERVICE, robot, epoch, reason))
        attempts = [Attempt(deployment, epoch, answer.outcome, answer.detail)]
        if answer.outcome is not SwitchOutcome.ACKED:
            self._ack_failed(robot, deployment, epoch, reason, answer)
            return SwitchResult(
                robot, deployment, deployment, route.epoch, False, reason, tuple(attempts)
            )
        return self._commit(robot, deployment, deployment, epoch, reason, [], attempts)

    def _enlist(
        self, robot: str, deployment: str, epoch: int, reason: str, attempts: list[Attempt]
    ) -> tuple[str, ...]:
        """Round robin: put the planner's other members in service at `epoch` beside
        `deployment`; the pool of those that acknowledged (`deployment` first), or () in an
        anycast fleet. A member that does not acknowledge is left out (and fenced)."""
        if self.pools is None:
            return ()
        pool = [deployment]
        for member in self.pools.members(robot, deployment)[1:]:
            answer = self._request(member, self._ctl(CtlOp.SERVICE, robot, epoch, reason))
            attempts.append(Attempt(member, epoch, answer.outcome, answer.detail))
            if answer.outcome is SwitchOutcome.ACKED:
                pool.append(member)
                continue
            self._ack_failed(robot, member, epoch, f"{reason} (pool member)", answer)
            self._standby(robot, member, epoch)
        return tuple(pool)

    def _pool_of(self, robot: str) -> tuple[str, ...]:
        route = self.rib.route(robot)
        return route.pool if route is not None else ()

    def _no_taker(
        self,
        robot: str,
        route_epoch: int,
        previous: str | None,
        reason: str,
        failed: list[str],
        attempts: list[Attempt],
    ) -> SwitchResult:
        old = self.rib.deployment(previous) if previous is not None else None
        if previous is not None and (old is None or not old.alive):
            # The old deployment is gone and nobody took over: the robot computes locally.
            epoch = self.rib.reserve_epoch(robot)
            why = f"{reason}: no deployment acknowledged" if attempts else reason
            old_pool = self._pool_of(robot)
            self.rib.set_route(robot, None, epoch, why)
            self._publish(self._change(robot, None, epoch, why))
            for dep in dict.fromkeys([previous, *failed, *old_pool]):
                self._standby(robot, dep, epoch)
            return SwitchResult(robot, previous, None, epoch, True, why, tuple(attempts))
        if attempts:
            self.rib.record_event(
                EventKind.SWITCH_FAILED,
                robot=robot,
                deployment=previous,
                epoch=route_epoch,
                reason=f"{reason}: no candidate acknowledged; route kept",
            )
        # Fence the candidates that may still act on a late `service`.
        fence = self.rib.issued_epoch(robot)
        for dep in failed:
            self._standby(robot, dep, fence)
        return SwitchResult(robot, previous, previous, route_epoch, False, reason, tuple(attempts))

    def _ack_failed(
        self, robot: str, deployment: str, epoch: int, why: str, answer: _Answer
    ) -> None:
        self.rib.record_event(
            EventKind.ACK_FAILED,
            robot=robot,
            deployment=deployment,
            epoch=epoch,
            reason=f"{why}: {answer.outcome.value}: {answer.detail}",
        )

    def _standby(self, robot: str, deployment: str, epoch: int) -> None:
        row = self.rib.deployment(deployment)
        if row is None or not row.alive:
            # Nothing to tell a dead deployment; a restarted one starts with every robot in standby.
            self.rib.set_deployment_state(deployment, robot, DeploymentState.STANDBY, epoch)
            return
        answer = self._request(deployment, self._ctl(CtlOp.STANDBY, robot, epoch, STANDBY_REASON))
        if answer.outcome is SwitchOutcome.ACKED:
            self.rib.set_deployment_state(deployment, robot, DeploymentState.STANDBY, epoch)
        else:
            self.rib.record_event(
                EventKind.STANDBY_FAILED,
                robot=robot,
                deployment=deployment,
                epoch=epoch,
                reason=f"{answer.outcome.value}: {answer.detail}",
            )

    def _publish(self, change: RouteChange) -> None:
        try:
            self.transport.publish_route(change)
        except TransportError as exc:
            # The route is persisted; robots also learn it from the RIB views and their next query.
            self.rib.record_event(
                EventKind.PUBLISH_FAILED,
                robot=change.robot,
                deployment=change.deployment,
                epoch=change.epoch,
                reason=str(exc),
            )

    def _ctl(self, op: CtlOp, robot: str, epoch: int, reason: str) -> CtlRequest:
        in_flight = None if self._in_flight is None else self._in_flight(robot)
        return CtlRequest(
            op=op,
            robot=robot,
            epoch=epoch,
            sender=self.sender,
            reason=reason,
            max_in_flight=in_flight,
            service=self.service,
        )

    def _change(
        self,
        robot: str,
        deployment: str | None,
        epoch: int,
        reason: str,
        pool: tuple[str, ...] = (),
    ) -> RouteChange:
        return RouteChange(
            robot=robot,
            deployment=deployment,
            epoch=epoch,
            reason=reason,
            at=self._clock(),
            pool=pool,
            service=self.service,
        )

    def _request(self, deployment: str, request: CtlRequest) -> _Answer:
        try:
            reply = self.transport.send_ctl(deployment, request, self.ctl_timeout_s)
        except TransportError as exc:
            return _Answer(SwitchOutcome.ERROR, str(exc))
        if reply is None:
            return _Answer(SwitchOutcome.TIMEOUT, f"no reply within {self.ctl_timeout_s:g} s")
        if (reply.deployment, reply.robot) != (deployment, request.robot):
            return _Answer(
                SwitchOutcome.STALE,
                f"reply is for {reply.deployment}/{reply.robot}, not {deployment}/{request.robot}",
            )
        if None not in (reply.service, request.service) and reply.service != request.service:
            return _Answer(
                SwitchOutcome.STALE,
                f"reply is for service {reply.service}, not {request.service}",
            )
        if not reply.ok:
            # A refusal carries the deployment's own state and epoch, whatever was asked.
            if reply.epoch > request.epoch:
                return _Answer(
                    SwitchOutcome.REFUSED,
                    f"refused epoch {request.epoch}: deployment knows epoch {reply.epoch}",
                    newer_epoch=reply.epoch,
                )
            return _Answer(SwitchOutcome.REFUSED, reply.reason or "refused")
        expected = _ACKED_STATE[request.op]
        state = reply.state.value if isinstance(reply.state, Enum) else reply.state
        if state != expected.value:
            return _Answer(SwitchOutcome.STALE, f"ack for state {state}, expected {expected.value}")
        if reply.epoch != request.epoch:
            return _Answer(
                SwitchOutcome.STALE, f"ack for epoch {reply.epoch}, expected {request.epoch}"
            )
        return _Answer(SwitchOutcome.ACKED, "")


def carry_out(scheduler: Scheduler, switcher: Switcher, decision: RouteDecision) -> SwitchResult:
    """Apply a decision and tell the scheduler how it went (the daemon's glue, in one place)."""
    result = switcher.apply(decision)
    if result.changed:
        scheduler.record_switch(decision.robot, result.previous, result.deployment, decision.reason)
    elif result.attempts:
        scheduler.record_failure(decision.robot)
    return result
