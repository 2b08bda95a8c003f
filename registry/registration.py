"""Admission to the fleet: who may be routed to, and why not.

A deployment is admitted from its probe reply (the registry probes every new cloud token), a
daemon that asks on `reg/register` from its request; both are checked with
`common.wire.registry.check_registration` (protocol version, capabilities, service, model digest).
The reference digest is the fleet file's model when this host has the file; for a `zoo:` model
(the registry never exports one) it is the digest of the deployments already accepted.

`Registrar` serves `reg/register` (a robot that is accepted gets its current route, and one left
without a deployment the reason, e.g. `no_capacity`; a robot not placed yet while every
deployment that could serve it is full is told `no_capacity` at once), and keeps the
registration state of every cloud whose token is alive (`pending` until its probe is answered,
then `accepted` or `refused`), which deployments were accepted in this run, and the model digest
each robot registered with. The control loop writes; the views and `reg/register` read from
Zenoh callback threads, hence the lock.
A registrar admits for one service (each service's plane has its own): a deployment's probe reply
must be for it, and the routes it tells are that service's. A request for a service the fleet
does not serve is refused by the daemon's dispatch with `refuse_service`, recorded like any.
A refusal is an event in the RIB and one warning naming the machine and the reason; nothing is ever
routed to a refused deployment.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from enum import Enum

import zenoh

from common import keys
from common.config import FleetConfig
from common.defaults import DEFAULT_MAX_REQUEST_BYTES
from common.keys import Role
from common.models import file_digest
from common.wire import registry as msg
from registry.deployment_table import deployment_table
from registry.replies import answer, decode_query
from registry.rib import EventKind, Rib, RibRouteRow
from registry.scheduler import Reason, RobotView, no_room_for

log = logging.getLogger(__name__)

# The reason of the route in a registration reply: the robot's route as it stands.
CURRENT_ROUTE_REASON = "current"
# The scheduler's reasons, the only ones a reply repeats from the RIB's route events.
ROUTE_REASONS = frozenset(r.value for r in Reason)


class RegistrationState(str, Enum):
    """Where a deployment's registration stands (the `deployments` view shows `refused`)."""

    PENDING = "pending"  # token seen, probe in flight
    ACCEPTED = "accepted"
    REFUSED = "refused"


@dataclass(frozen=True)
class Registration:
    """A deployment's registration. `retry`: refused for want of an answer, so probed again now
    and then."""

    state: RegistrationState
    reason: str = ""
    retry: bool = False


def fleet_model_digest(cfg: FleetConfig) -> str | None:
    """The fleet model's sha256 when the registry can tell without building anything: a model
    file present on this host. None for a zoo model (the registry never exports one): the first
    deployment accepted then sets the reference the others must match."""
    path = cfg.model_path
    if path is None or not path.is_file():
        return None
    try:
        return file_digest(path)
    except OSError as exc:
        log.warning("cannot read the model %s to check digests: %s", path, exc)
        return None


class Registrar:
    """`Registrar(fleet, rib, service, fleet_digest)`: the registration table and its checks.
    `max_request_bytes`: the largest `reg/register` request read (`registry.max_request_bytes`)."""

    def __init__(
        self,
        fleet: str,
        rib: Rib,
        service: str,
        fleet_digest: str | None,
        *,
        max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
    ) -> None:
        self.fleet = fleet
        self.rib = rib
        self.service = service
        self.fleet_digest = fleet_digest
        self.max_request_bytes = max_request_bytes
        self._lock = threading.Lock()
        self._table: dict[str, Registration] = {}
        self._seen: set[str] = set()  # deployments accepted in this run
        self._robot_digests: dict[str, str] = {}
        # Frames in flight each robot announced (`RegisterRequest.max_in_flight`).
        self._robot_in_flight: dict[str, int] = {}

    # -- the table -------------------------------------------------------------------------------
    def token_came(self, deployment: str) -> bool:
        """A cloud token appeared: pending from now on. False when it was known already."""
        with self._lock:
            if deployment in self._table:
                return False
            self._table[deployment] = Registration(RegistrationState.PENDING)
            return True

    def token_gone(self, deployment: str) -> Registration | None:
        """A cloud token went away: its registration (None if it had none) is forgotten."""
        with self._lock:
            return self._table.pop(deployment, None)

    def get(self, deployment: str) -> Registration | None:
        """The deployment's registration while its token is alive."""
        with self._lock:
            return self._table.get(deployment)

    def is_state(self, deployment: str, state: RegistrationState) -> bool:
        """Whether the deployment's token is alive and its registration is in `state`."""
        registration = self.get(deployment)
        return registration is not None and registration.state is state

    def seen(self, deployment: str) -> bool:
        """Whether the deployment was accepted in this run."""
        with self._lock:
            return deployment in self._seen

    def refused(self) -> dict[str, str]:
        """deployment -> reason, for every live deployment refused."""
        with self._lock:
            return {
                d: r.reason for d, r in self._table.items() if r.state is RegistrationState.REFUSED
            }

    def to_probe(self) -> list[tuple[str, bool]]:
        """(deployment, refresh) for each deployment to probe now: the accepted ones (a refresh,
        for load and repair) and those refused for want of an answer (registration again)."""
        with self._lock:
            return [
                (d, r.state is RegistrationState.ACCEPTED)
                for d, r in self._table.items()
                if r.state is RegistrationState.ACCEPTED or r.retry
            ]

    def robot_in_flight(self, robot: str) -> int | None:
        """The frames in flight the robot announced at registration (None: not announced)."""
        with self._lock:
            return self._robot_in_flight.get(robot)

    def robot_digest(self, robot: str) -> str | None:
        """The model digest the robot registered with, if it named one."""
        with self._lock:
            return self._robot_digests.get(robot)

    # -- admission -------------------------------------------------------------------------------
    def admit(self, deployment: str, reply: msg.ProbeReply | None, error: str) -> bool:
        """Decide a pending deployment's registration from its probe reply (`error` when none
        came); True when it is accepted now. A deployment gone meanwhile is left alone."""
        registration = self.get(deployment)
        if registration is None:
            return False
        reason = error if reply is None else self._check_probe(deployment, reply)
        if reason is not None:
            if registration.reason != reason:
                self.refuse(Role.CLOUD, deployment, reason)
            refused = Registration(RegistrationState.REFUSED, reason, retry=reply is None)
            with self._lock:
                self._table[deployment] = refused
            return False
        assert reply is not None
        self.rib.upsert_deployment(
            deployment,
            service=reply.service,
            model_digest=reply.model_digest,
            capacity=reply.capacity,
            version=f"protocol {reply.protocol_version}",
            load=reply.load,
        )
        with self._lock:
            self._table[deployment] = Registration(RegistrationState.ACCEPTED)
            self._seen.add(deployment)
        log.info(
            "deployment %s registered (service %s, model %s, capacity %d, on %s)",
            deployment,
            reply.service,
            reply.model_digest[:12],
            reply.capacity,
            ", ".join(reply.providers) or "unknown providers",
        )
        if reply.providers_fallback:
            # Accepted all the same: its machine allows it (`providers_fallback: allow`).
            log.warning(
                "deployment %s serves on %s, without an accelerator its machine asks for",
                deployment,
                ", ".join(reply.providers),
            )
        return True

    def refresh(self, deployment: str, reply: msg.ProbeReply) -> bool:
        """A refresh probe's reply: the load and capacity of an accepted deployment go to the
        RIB. False (and nothing written) when the deployment is not accepted now."""
        if not self.is_state(deployment, RegistrationState.ACCEPTED):
            return False
        row = self.rib.deployment(deployment)
        if row is not None and (row.load, row.capacity) != (reply.load, reply.capacity):
            self.rib.update_deployment_load(deployment, reply.load, reply.capacity)
        return True

    def answer(self, query: zenoh.Query) -> None:
        """Serve `reg/register` on Zenoh's callback thread (a WireError for a bad request, which
        the caller answers)."""
        request = decode_query(query, msg.RegisterRequest, max_bytes=self.max_request_bytes)
        reply = self.reply_to(request)
        answer(query, (keys.reg_register(self.fleet), reply.to_wire()))

    def reply_to(self, request: msg.RegisterRequest) -> msg.RegisterReply:
        """The answer to a `reg/register` request: accepted or the reason not, and for an
        accepted robot its current route."""
        reason = self.register(request)
        route = None
        if reason is None and Role(request.role) is Role.ROBOT:
            row = self.rib.route(request.id)
            if row is None:
                route = self._refused_for_capacity(request)
            else:
                route = msg.RouteChange(
                    robot=request.id,
                    deployment=row.deployment,
                    epoch=row.epoch,
                    reason=self._route_reason(row),
                    at=time.time(),
                    pool=row.pool,
                    service=self.service,
                )
        return msg.RegisterReply(
            accepted=reason is None,
            reason=reason or "accepted",
            protocol_version=msg.PROTOCOL_VERSION,
            route=route,
        )

    def _refused_for_capacity(self, request: msg.RegisterRequest) -> msg.RouteChange | None:
        """A robot not placed yet, when every deployment that could serve it is full: no route,
        `no_capacity`, told in its registration reply instead of by the next round's route
        change (which says the same under a newer epoch). None otherwise."""
        robot = RobotView(
            id=request.id,
            service=request.service,
            route=None,
            model_digest=request.model_digest,
        )
        if not no_room_for(robot, deployment_table(self.rib.deployments()).views):
            return None
        return msg.RouteChange(
            robot=request.id,
            deployment=None,
            epoch=self.rib.issued_epoch(request.id),
            reason=msg.NO_CAPACITY_REASON,
            at=time.time(),
            service=self.service,
        )

    def _route_reason(self, row: RibRouteRow) -> str:
        """Why a robot has its route, for the registration reply: `current` for a deployment;
        for none, the reason it was given (`no_capacity`: every deployment full), so a robot
        that registers again learns why it computes locally, as it did from the route change."""
        if row.deployment is not None:
            return CURRENT_ROUTE_REASON
        for event in self.rib.events(limit=1, robot=row.robot, kind=EventKind.ROUTE.value):
            # The RIB writes a route event as "<reason>: <from> -> <to>"; only a reason of the
            # scheduler's vocabulary, for this very epoch, is repeated.
            code = event.reason.partition(":")[0]
            if event.epoch == row.epoch and code in ROUTE_REASONS:
                return code
        return CURRENT_ROUTE_REASON

    def refuse_service(self, request: msg.RegisterRequest, reason: str) -> msg.RegisterReply:
        """Refuse a request this registrar's service cannot take (`reason`: e.g. a service the
        fleet does not serve), unless the checks that come first (protocol, capabilities)
        refuse it already, as `register` would; recorded like any refusal."""
        final = msg.check_registration(request, service=request.service) or reason
        self.refuse(Role(request.role), request.id, final)
        return msg.RegisterReply(
            accepted=False, reason=final, protocol_version=msg.PROTOCOL_VERSION
        )

    def register(self, request: msg.RegisterRequest) -> str | None:
        """Check a `reg/register` request; the reason to refuse it (recorded), or None. An
        accepted robot's model digest is kept for the scheduler."""
        reason = msg.check_registration(
            request, service=self.service, model_digest=self.reference_digest(request.id)
        )
        if reason is not None:
            self.refuse(Role(request.role), request.id, reason)
        elif Role(request.role) is Role.ROBOT:
            with self._lock:
                if request.model_digest:
                    self._robot_digests[request.id] = request.model_digest
                if request.max_in_flight is not None:
                    self._robot_in_flight[request.id] = request.max_in_flight
                else:
                    self._robot_in_flight.pop(request.id, None)
        return reason

    def refuse(self, role: Role, machine: str, reason: str) -> None:
        """Record a refusal: an event in the RIB and one warning naming the machine."""
        self.rib.record_event(
            EventKind.REGISTRATION_REFUSED,
            robot=machine if role is Role.ROBOT else None,
            deployment=machine if role is Role.CLOUD else None,
            reason=reason,
        )
        log.warning("refused %s %s: %s", role.value, machine, reason)

    def reference_digest(self, asking: str) -> str | None:
        """The model digest everyone must match: the fleet file's model when this host has it,
        else the one of the deployments accepted already (other than `asking`)."""
        if self.fleet_digest is not None:
            return self.fleet_digest
        for row in self.rib.deployments():
            if row.alive and row.id != asking and row.model_digest and row.service == self.service:
                return row.model_digest
        return None

    def _check_probe(self, deployment: str, reply: msg.ProbeReply) -> str | None:
        if reply.deployment != deployment:
            return f"cloud {deployment!r} answers its probe as {reply.deployment!r}"
        request = msg.RegisterRequest(
            role=Role.CLOUD,
            id=deployment,
            protocol_version=reply.protocol_version,
            capabilities=reply.capabilities,
            service=reply.service,
            model_digest=reply.model_digest or None,
        )
        return msg.check_registration(
            request, service=self.service, model_digest=self.reference_digest(deployment)
        )
