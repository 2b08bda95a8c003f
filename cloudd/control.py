"""A cloud daemon's control key `dep/<id>/ctl`: fault settings, drain, service and standby.

`CtlKey.on_query` (one per deployment) decodes a `CtlRequest` and answers it with what the
request's service does with it (`route`: the service's plane, `cloudd.planes`; a service this
deployment does not serve gets a named `unknown_service` error reply). Each service's
`Controller` carries the request out for its robots: service and standby follow the verdict of
`cloudd.state` (through `RobotBook.decide`): a robot entering service has its service key
declared before the ack, one leaving has it undeclared before the ack, since the registry relies
on both having happened when it reads the ack. A key that cannot be declared undoes the verdict
and is refused with the reason. Fault settings are the deployment's, whichever service names
them; a drain of the whole deployment drains the robots of the service it names. A request that
does not decode (over the request limit, `cloudd.limits`, or malformed) gets the codec's error
reply and is counted (`cloudd.refusals`). Every reply names the service (`CtlReply.service`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import zenoh

from cloudd.faults import FaultInjector, describe
from cloudd.refusals import RefusalReason, Refusals, decode_refusal
from cloudd.replies import Replier, query_payload
from cloudd.robot_book import RobotBook
from cloudd.state import Verdict
from common.session import zenoh_error_text
from common.throttled_log import ThrottledLog
from common.wire import ErrorReply, WireError, error_reply
from common.wire.registry import CtlOp, CtlReply, CtlRequest, DeploymentState

log = logging.getLogger(__name__)


class CtlKey:
    """The ctl queryable's callback: decodes each request and answers what `route(request)`
    makes of it (the service's `Controller.control`, or a named error reply)."""

    def __init__(
        self,
        deployment: str,
        *,
        key: str,
        route: Callable[[CtlRequest], CtlReply | ErrorReply],
        replies: Replier,
        max_request_bytes: int,
        refusals: Refusals,
        throttled: ThrottledLog,
    ) -> None:
        self.deployment = deployment
        self.key = key
        self._route = route
        self._replies = replies
        self._max_request_bytes = max_request_bytes
        self._refusals = refusals
        self._throttled = throttled

    def on_query(self, query: zenoh.Query) -> None:
        """Answered at once, in every fault state."""
        try:
            request = CtlRequest.from_wire(query_payload(query), max_bytes=self._max_request_bytes)
        except WireError as exc:
            self._refusals.count(decode_refusal(exc))
            self._throttled.warning("%s: bad ctl request: %s", self.deployment, exc.reason)
            self._replies.send(query, self.key, error_reply(exc), 0.0)
            return
        reply = self._route(request)
        self._replies.send(query, self.key, reply.to_wire(), 0.0)


class Controller:
    """Carries out a deployment's control requests for one service (`service`);
    `declare_service(robot)` declares the robot's service key (raising if it cannot). `who`
    names the deployment (and the service, when it serves several) in the log."""

    def __init__(
        self,
        deployment: str,
        *,
        service: str,
        book: RobotBook,
        faults: FaultInjector,
        declare_service: Callable[[str], None],
        refusals: Refusals,
        set_in_flight: Callable[[str, int], int | None] = lambda robot, announced: None,
        left_service: Callable[[str], None] = lambda robot: None,
        who: str = "",
    ) -> None:
        self.deployment = deployment
        self.service = service
        self._who = who or deployment
        self._book = book
        self._faults = faults
        self._declare_service = declare_service
        self._refusals = refusals
        self._set_in_flight = set_in_flight
        # What the plane frees of a robot that left service here (its video stream).
        self._left_service = left_service
        # Robots whose announced frames in flight exceed the cap: counted and logged once each.
        self._over_cap: set[str] = set()
        self._over_cap_lock = threading.Lock()

    def control(self, request: CtlRequest) -> CtlReply:
        """Carry out a control request (what the ctl key does) and return the reply."""
        sender = f" from {request.sender}" if request.sender else ""
        if request.op is CtlOp.FAULT:
            assert request.fault is not None  # checked by CtlRequest
            self._faults.set(request.fault)
            log.info("%s: fault injection%s: %s", self._who, sender, describe(request.fault))
            return CtlReply(
                ok=True, deployment=self.deployment, op=request.op, service=self.service
            )
        if request.op is CtlOp.DRAIN:
            return self._drain(request, sender)
        assert request.robot is not None  # checked by CtlRequest for service and standby
        return self._service_or_standby(request, request.robot, sender)

    def _drain(self, request: CtlRequest, sender: str) -> CtlReply:
        if request.robot is None:
            moved = self._book.drain_all()
            state = DeploymentState.DRAINING
            epoch = 0
        else:
            st = self._book.drain_robot(request.robot)
            moved = [request.robot] if st.serving else []
            state, epoch = st.state, st.wire_epoch
        log.info(
            "%s: drain%s of %s: draining %s",
            self._who,
            sender,
            request.robot or "the deployment",
            ", ".join(moved) or "no robot",
        )
        return CtlReply(
            ok=True,
            deployment=self.deployment,
            op=request.op,
            robot=request.robot,
            epoch=epoch,
            state=state,
            service=self.service,
        )

    def _admit_in_flight(self, robot: str, announced: int) -> None:
        """Admit as many of the robot's requests at once as it keeps frames in flight, up to
        the cap; a robot asking for more than the cap is counted and logged once."""
        limit = self._set_in_flight(robot, announced)
        if limit is None or limit >= announced:
            return
        with self._over_cap_lock:
            if robot in self._over_cap:
                return
            self._over_cap.add(robot)
        self._refusals.count(RefusalReason.IN_FLIGHT_CAP)
        log.warning(
            "%s: %s keeps %d frames in flight, but this deployment admits %d of its requests at "
            "once (batching.max_in_flight_per_robot): the rest are answered busy",
            self._who,
            robot,
            announced,
            limit,
        )

    def _service_or_standby(self, request: CtlRequest, robot: str, sender: str) -> CtlReply:
        if request.max_in_flight is not None:
            self._admit_in_flight(robot, request.max_in_flight)
        decision = self._book.decide(request.op, robot, request.epoch)
        verdict = decision.verdict
        if decision.stopping:
            return self._reply(request, verdict)
        if verdict.declare:
            try:
                self._declare_service(robot)
            except Exception as exc:
                self._book.restore(verdict)
                reason = f"cannot declare the service key of {robot}: {zenoh_error_text(exc)}"
                log.warning("%s: %s", self._who, reason)
                return self._reply(
                    request, Verdict(False, robot, verdict.before, verdict.before, reason)
                )
        if decision.undeclare is not None:
            decision.undeclare.undeclare()  # before the ack: the registry relies on it being gone
        if verdict.ok and not verdict.after.serving:
            self._left_service(robot)
        if verdict.ok:
            log.info(
                "%s: %s %s at epoch %d%s",
                self._who,
                robot,
                verdict.after.state.value,
                verdict.after.epoch,
                sender,
            )
        else:
            log.warning(
                "%s: refused %s(%s, epoch %d)%s: %s",
                self._who,
                request.op.value,
                robot,
                request.epoch,
                sender,
                verdict.reason,
            )
        return self._reply(request, verdict)

    def _reply(self, request: CtlRequest, verdict: Verdict) -> CtlReply:
        return CtlReply(
            ok=verdict.ok,
            deployment=self.deployment,
            op=request.op,
            robot=verdict.robot,
            epoch=verdict.after.wire_epoch,
            state=verdict.after.state,
            reason=verdict.reason,
            service=self.service,
        )
