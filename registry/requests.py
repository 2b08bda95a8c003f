"""The `reg/drain` and `reg/reroute` requests: decoded on the queryable's thread, queued for the
control loop, acted on there and answered with the outcome.

Both move robots, and only the control loop decides and switches, so a callback does no more
than decode the query strictly (`registry.replies.decode_query`), refuse a reroute for a service
the fleet does not serve (`UnknownService`, answered like bad input) and queue a `QueuedRequest`.
A drain is for every service the deployment serves; a reroute for its `service` (None: the
fleet's first).
The control loop hands it to `drain` or `reroute` with the daemon's own evaluation of a robot
(`evaluate`: ask the scheduler, carry out its decision), so what a request does is what a
scheduling round would do. Requests still queued when the registry stops are refused
(`refuse_queued`) rather than left to time out.
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import zenoh

from common import keys
from common.wire import ErrorCode, ErrorReply, Message
from common.wire import registry as msg
from registry.measurements import Measurements
from registry.registration import Registrar
from registry.replies import answer, check_service, decode_query, refusal
from registry.rib import Rib
from registry.switch import SwitchResult

log = logging.getLogger(__name__)

STOPPING_REASON = "the registry is stopping"

# Ask the scheduler about one robot and carry out its decision (None: nothing to do).
Evaluate = Callable[[str], SwitchResult | None]


@dataclass(frozen=True)
class QueuedRequest:
    """A decoded drain or reroute request waiting for the control loop."""

    message: Message
    query: zenoh.Query
    key: str  # the queryable's own key: replies go there (the query's may hold wildcards)


class RequestQueue:
    """The drain and reroute queryables' callbacks: `on_drain(query)`, `on_reroute(query)`
    decode and hand a `QueuedRequest` to `put` (bad input raises `WireError`, which the
    daemon's guard answers). `services`: the fleet's (empty: any)."""

    def __init__(
        self,
        fleet: str,
        put: Callable[[QueuedRequest], None],
        *,
        max_request_bytes: int,
        services: Sequence[str] = (),
    ) -> None:
        self.fleet = fleet
        self.max_request_bytes = max_request_bytes
        self.services = tuple(services)
        self._put = put

    def on_reroute(self, query: zenoh.Query) -> None:
        request = decode_query(query, msg.RerouteRequest, max_bytes=self.max_request_bytes)
        if self.services:
            check_service(request.service, self.services)
        self._put(QueuedRequest(request, query, keys.reg_reroute(self.fleet)))

    def on_drain(self, query: zenoh.Query) -> None:
        request = decode_query(query, msg.DrainRequest, max_bytes=self.max_request_bytes)
        self._put(QueuedRequest(request, query, keys.reg_drain(self.fleet)))


def refuse_queued(events: queue.Queue[object]) -> None:
    """Empty the control loop's queue: requests in it get a refusal instead of a timeout (the
    other events are dropped, nothing acts on them any more)."""
    while True:
        try:
            event = events.get_nowait()
        except queue.Empty:
            return
        if isinstance(event, QueuedRequest):
            answer(event.query, (event.key, refusal(STOPPING_REASON)))


def drain(request: msg.DrainRequest, rib: Rib, registrar: Registrar, evaluate: Evaluate) -> Message:
    """Move every robot of a deployment that stops; the reply lists the robots moved."""
    deployment = request.deployment
    if rib.deployment(deployment) is None and registrar.get(deployment) is None:
        return ErrorReply.make(
            ErrorCode.REFUSED, f"unknown deployment {deployment!r}: it never registered here"
        )
    rib.set_deployment_draining(deployment, request.reason or "drain requested")
    log.info("deployment %s drains: moving its robots", deployment)
    moved: list[str] = []
    stuck: list[str] = []
    for route in rib.routes():
        if route.deployment != deployment:
            continue
        result = evaluate(route.robot)
        if result is not None and result.changed:
            moved.append(route.robot)
        else:
            stuck.append(route.robot)
    reason = ""
    if stuck:
        reason = f"no other deployment took {', '.join(stuck)}; they compute locally once it stops"
        log.warning("drain of %s: %s", deployment, reason)
    return msg.DrainReply(ok=not stuck, moved=tuple(moved), reason=reason)


def combine_drains(replies: Sequence[tuple[str, Message]]) -> Message:
    """One reply to a drain acted on by every service's plane ((service, its reply) each): the
    robots moved in any, `ok` when every plane that knows the deployment moved them all. A
    deployment no plane knows gets the first plane's refusal."""
    drained = [(s, r) for s, r in replies if isinstance(r, msg.DrainReply)]
    if not drained:
        return replies[0][1]
    if len(drained) == 1:
        return drained[0][1]
    moved = dict.fromkeys(robot for _, r in drained for robot in r.moved)
    reasons = [f"{service}: {r.reason}" for service, r in drained if r.reason]
    return msg.DrainReply(
        ok=all(r.ok for _, r in drained), moved=tuple(moved), reason="; ".join(reasons)
    )


def reroute(
    request: msg.RerouteRequest,
    rib: Rib,
    measurements: Measurements,
    evaluate: Evaluate,
    *,
    service: str | None = None,
) -> Message:
    """A robot's request for another deployment: answered with its route afterwards (for
    `service`, the plane's that acts on it)."""
    robot = request.robot
    if rib.robot(robot) is None:
        return ErrorReply.make(
            ErrorCode.REFUSED, f"unknown robot {robot!r}: its liveliness token was never seen"
        )
    route = rib.route(robot)
    if route is None or route.deployment is None:
        evaluate(robot)
    elif not 0 < request.epoch < route.epoch:
        # The route failing the robot is the current one (or the robot does not know which it
        # holds): a forced move, as after timeouts. An older epoch: it has moved already.
        measurements.force_timeouts(robot, route.deployment, request.consecutive_timeouts)
        evaluate(robot)
    now = rib.route(robot)
    moved = now is not None and (route is None or now.epoch != route.epoch)
    return route_change(
        robot,
        now.deployment if now else None,
        now.epoch if now else 0,
        "rerouted" if moved else "current route",
        pool=now.pool if now else (),
        service=service,
    )


def route_change(
    robot: str,
    deployment: str | None,
    epoch: int,
    reason: str,
    *,
    pool: tuple[str, ...] = (),
    service: str | None = None,
) -> msg.RouteChange:
    """A robot's route (for `service`) as of now, for a reroute's reply, a registration reply or
    a publication on its route key."""
    return msg.RouteChange(
        robot=robot,
        deployment=deployment,
        epoch=epoch,
        reason=reason,
        at=time.time(),
        pool=pool,
        service=service,
    )
