"""The registry daemon: the RIB, the scheduler and the switch protocol wired to Zenoh.

Lifecycle (`common.daemon.Daemon`: startup -> main loop -> shutdown, in reverse order):

1. Open the RIB (routes, epochs and profiles come back from sqlite; liveness flags are reset) and
   restore the measurements from it; they are saved again just before it closes.
2. Open the session: a router listening on `registry.listen`, so a fresh host needs nothing
   else (data never flows through it: peers link to each other directly), or a peer of the
   router at `registry.endpoint`.
3. Start the prober's pool. (At shutdown, once the queryables are gone, requests still queued
   for the control loop are refused rather than left to time out.)
4. Declare the queryables (`rib/*`, `reg/register`, `reg/reroute`, `reg/drain`) and the
   subscribers (telemetry, probe reports).
5. Follow membership with a `common.membership.MembershipView` (a liveliness subscriber with
   history, seeded by a liveliness get): every cloud and robot token, those older than the
   registry included, and the end of each.
6. Announce `alive/registry/<id>`: from now on it serves.

Each step hands what it made to the lifecycle (`hold`, `on_release`, `announce`), which releases
it all at shutdown in reverse order, the token first, also after a failed startup.

Threads. Every Zenoh callback is `guarded` and short: membership changes, drain and reroute
requests are queued for the control loop; telemetry and probe reports only update the
measurements (`registry.measurements`, under their own lock); the read-only views
(`registry.views`) and `reg/register` are answered on the callback thread. Probing deployments
(registration, and a load refresh every few seconds) runs on the prober's pool
(`registry.prober`), which queues each outcome. The control loop (the main thread) is the only
one that decides and switches: it handles queued events at once and runs the scheduler every
`tick_s` (~100 ms).

Decisions. A robot with no live route gets one: its restored route if that deployment is alive
(re-asserted at the same epoch, so a cloud daemon restarted meanwhile declares the key again),
else initial_policy's service machine if alive, else the scheduler's choice. A deployment whose
token disappears, or a robot reporting `timeout_count` consecutive timeouts (in telemetry or by a
`reg/reroute` request), is handled at once; bound violations and improvements wait out the
scheduler's hysteresis. After a restart, a route whose deployment has not reconnected yet is left
alone for `restore_grace_s` (peers retry their connection to the router every few seconds).

Registration (`registry.registration`). A new cloud token is probed and its reply checked; a
mismatch is refused with an event and a log line naming the deployment and the reason, and
nothing is ever routed to it. A deployment found serving a robot that the RIB routes elsewhere is
put back in standby (anycast repair).

Bad input to any queryable (garbage, an unknown schema version, a wrong message type, a malformed
request, a payload over `registry.max_request_bytes`) gets an `ErrorReply` naming the problem and
one throttled warning; a bad publication is a throttled warning and dropped. Both are counted by
input and error code (`registry.refusals`, logged at shutdown). The daemon keeps serving either
way.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from common import keys
from common.config import FleetConfig
from common.daemon import Daemon
from common.file_safety import check_private_file
from common.membership import MemberChange, MembershipView
from common.session import open_session
from common.wire import ErrorCode, ErrorReply, Message, WireError
from common.wire import registry as msg
from common.wire.telemetry import ProbeReport, TelemetryRecord
from registry.latency import LatencyBound
from registry.measurements import Measurements
from registry.prober import Probed, Prober
from registry.refusals import Refusals
from registry.registration import Registrar, RegistrationState, Role, fleet_model_digest
from registry.replies import answer, check_size, decode_query, error_payload, refusal
from registry.rib import MEMORY, DeploymentRow, Rib, RobotRow, RouteRow
from registry.scheduler import (
    Decision,
    DeploymentTable,
    DeploymentView,
    Reason,
    RobotView,
    Scheduler,
    SchedulerParams,
)
from registry.switch import (
    CTL_TIMEOUT_S,
    Outcome,
    Switcher,
    SwitchResult,
    TransportError,
    carry_out,
)
from registry.transport import ZenohTransport
from registry.views import RibViews

log = logging.getLogger(__name__)

SCHEDULER_TICK_S = 0.1
PROFILE_SAVE_INTERVAL_S = 5.0
LOAD_REFRESH_INTERVAL_S = 2.0
# Peers retry their connection to a restarted router with a back-off of up to 4 s (zenoh's
# default): until then a restored route's deployment is "not seen yet", not "lost".
RESTORE_GRACE_S = 5.0
# How long the membership's seeding get waits for replies (it returns earlier once every peer
# answered; tokens it misses still come through the subscriber's history).
MEMBERSHIP_SEED_TIMEOUT_S = 0.5
STOPPING_REASON = "the registry is stopping"


# -- events for the control loop (besides MemberChange and Probed) ------------------------------
@dataclass(frozen=True)
class _Evaluate:
    robot: str


@dataclass(frozen=True)
class _Request:
    message: Message
    query: zenoh.Query
    key: str  # the queryable's own key: replies go there (the query's may hold wildcards)


_Event = MemberChange | Probed | _Evaluate | _Request
_Published = TypeVar("_Published", TelemetryRecord, ProbeReport)


@dataclass(frozen=True)
class _Started:
    """What startup made that the callbacks and the control loop use."""

    session: zenoh.Session
    rib: Rib
    transport: ZenohTransport
    switcher: Switcher
    registrar: Registrar
    views: RibViews
    prober: Prober


class RegistryDaemon(Daemon):
    """`elasticfog registry`: see the module docstring."""

    name = "registry"

    def __init__(
        self,
        cfg: FleetConfig,
        *,
        db_path: str | Path | None = None,
        params: SchedulerParams | None = None,
        tick_s: float = SCHEDULER_TICK_S,
        ctl_timeout_s: float = CTL_TIMEOUT_S,
        restore_grace_s: float = RESTORE_GRACE_S,
        profile_save_interval_s: float = PROFILE_SAVE_INTERVAL_S,
        load_refresh_interval_s: float = LOAD_REFRESH_INTERVAL_S,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.fleet = cfg.fleet
        self.id = cfg.registry.id
        self.service = cfg.service
        self.db_path = Path(db_path) if db_path is not None else cfg.db_path
        self.bound = _latency_bound(cfg)
        self.params = params if params is not None else SchedulerParams()
        self.tick_s = tick_s
        self.ctl_timeout_s = ctl_timeout_s
        self.restore_grace_s = restore_grace_s
        self.profile_save_interval_s = profile_save_interval_s
        self.load_refresh_interval_s = load_refresh_interval_s
        self.max_request_bytes = cfg.registry.max_request_bytes
        # Error replies and dropped publications, by input and code (Zenoh threads count).
        self.refusals = Refusals()
        # Set once the registry's token is declared: it serves from then on.
        self.ready = threading.Event()
        self.scheduler = Scheduler(self.bound, self.params)
        self.measurements = Measurements(
            self.bound.window,
            deadline_s=cfg.deadline_s,
            timeout_count=self.params.timeout_count,
            on_bad_sample=self._bad_input,
        )

        self._events: queue.Queue[_Event] = queue.Queue()
        # Control-loop state (only the control loop touches these).
        self._confirmed: set[str] = set()  # robots whose route was confirmed in this run
        self._started_at = 0.0
        self._started: _Started | None = None  # made in startup, dropped after shutdown

    # -- what startup made ---------------------------------------------------------------------
    @property
    def _parts(self) -> _Started:
        """The started parts (RuntimeError before startup and after shutdown)."""
        if self._started is None:
            raise RuntimeError("the registry is not started")
        return self._started

    @property
    def rib(self) -> Rib | None:
        """The RIB while the daemon runs, else None."""
        return self._started.rib if self._started is not None else None

    @property
    def session(self) -> zenoh.Session | None:
        """The Zenoh session while the daemon runs, else None."""
        return self._started.session if self._started is not None else None

    # -- lifecycle -----------------------------------------------------------------------------
    def startup(self) -> None:
        """Open the RIB and the session, declare everything, follow membership, then go live."""
        self._started_at = time.monotonic()
        cfg, fleet = self.cfg, self.fleet
        if str(self.db_path) != MEMORY:
            check_private_file(self.db_path, "RIB file")  # refuse a world-writable RIB
        rib = self.hold(Rib(self.db_path), "RIB")
        rib.reset_liveness()
        self.measurements.restore(rib)
        # Released just before the RIB closes: by then the session is closed and nothing measures.
        self.on_release(self.measurements.save, rib, what="latency profiles")
        self.on_release(self.measurements.flush_loads, rib, what="deployment loads")
        if cfg.registry.embedded_router:
            session = self.hold(open_session(cfg, router=True), "zenoh session")
            where = ", ".join(cfg.registry.listen)
        else:
            # A peer of someone else's router: in a TLS fleet it still presents its own certificate.
            session = self.hold(open_session(cfg, identity=self.id), "zenoh session")
            where = f"the router at {cfg.registry.endpoint}"
        transport = ZenohTransport(session, fleet)
        registrar = Registrar(
            fleet,
            rib,
            self.service,
            fleet_model_digest(cfg),
            max_request_bytes=self.max_request_bytes,
        )
        prober = Prober(transport, self.id, self._events.put, self.closing)
        self.on_release(prober.close, what="probe pool")
        # After the queryables are gone: what they queued gets a refusal instead of a timeout.
        self.on_release(self._answer_pending, what="queued requests")
        self._started = _Started(
            session=session,
            rib=rib,
            transport=transport,
            switcher=Switcher(rib, transport, ctl_timeout_s=self.ctl_timeout_s, sender=self.id),
            registrar=registrar,
            views=RibViews(
                fleet,
                rib,
                self.measurements,
                registrar,
                self.bound,
                cfg.deadline_s,
                max_request_bytes=self.max_request_bytes,
            ),
            prober=prober,
        )
        self._declare(session)
        self.hold(
            MembershipView(
                session,
                fleet,
                roles=[role.value for role in Role],
                on_change=self.guarded(self._on_member, what="a membership change"),
                seed_timeout_s=MEMBERSHIP_SEED_TIMEOUT_S,
            ),
            "membership view",
        )
        self.announce(session.liveliness().declare_token(keys.alive_registry(fleet, self.id)))
        self.ready.set()
        log.info(
            "registry %s of fleet %s: listening on %s, RIB %s (%d routes restored)",
            self.id,
            fleet,
            where,
            self.db_path,
            self.measurements.routes_known(),
        )

    def _declare(self, session: zenoh.Session) -> None:
        """The queryables and subscribers, each guarded and held."""
        fleet = self.fleet
        # (input name for the refusal counts, key, handler, where an error reply goes)
        queryables: list[tuple[str, str, Callable[[zenoh.Query], None], Callable[..., str]]] = [
            ("rib", keys.rib_all(fleet), self._parts.views.answer, self._parts.views.reply_key),
            (
                "register",
                keys.reg_register(fleet),
                self._parts.registrar.answer,
                lambda _q: keys.reg_register(fleet),
            ),
            (
                "reroute",
                keys.reg_reroute(fleet),
                self._on_reroute,
                lambda _q: keys.reg_reroute(fleet),
            ),
            ("drain", keys.reg_drain(fleet), self._on_drain, lambda _q: keys.reg_drain(fleet)),
        ]
        for name, key, handler, reply_key in queryables:
            callback = self.guarded(
                handler,
                what=f"a query on {key}",
                on_error=functools.partial(self._answer_error, name, reply_key),
                drop_when_closing=True,
            )
            self.hold(session.declare_queryable(key, callback), f"queryable {key}")
        subscribers: list[tuple[str, Callable[[zenoh.Sample], None]]] = [
            (keys.tele_all(fleet), self._on_telemetry),
            (keys.tele_probe_all(fleet), self._on_probe_report),
        ]
        for key, on_sample in subscribers:
            follow = self.guarded(on_sample, what=f"a sample on {key}", drop_when_closing=True)
            self.hold(session.declare_subscriber(key, follow), f"subscriber {key}")

    def main_loop(self) -> None:
        """The control loop: queued events at once, the scheduler every tick."""
        now = time.monotonic()
        next_tick = now
        next_save = now + self.profile_save_interval_s
        next_refresh = now + self.load_refresh_interval_s
        while not self.should_exit.is_set():
            wait_s = min(self.tick_s, max(0.0, next_tick - time.monotonic()))
            try:
                event: _Event | None = self._events.get(timeout=wait_s)
            except queue.Empty:
                event = None
            if event is not None:
                self._safely(self._handle, event)
            now = time.monotonic()
            if now >= next_tick:
                self._safely(self._schedule_all)
                next_tick = now + self.tick_s
            if now >= next_save:
                self._safely(self.measurements.save, self._parts.rib)
                next_save = now + self.profile_save_interval_s
            if now >= next_refresh:
                self._safely(self._refresh_deployments)
                next_refresh = now + self.load_refresh_interval_s

    def shutdown(self) -> None:
        """Token first, then everything startup made in reverse: the membership view, the
        queryables and subscribers, queued requests (refused), the prober, the session, the
        measurements (saved), the RIB. Safe twice."""
        self.ready.clear()
        super().shutdown()
        self._started = None
        refused = self.refusals.summary()
        if refused:
            log.info("registry %s refused (input, code, count): %s", self.id, refused)
        log.info("registry %s stopped", self.id)

    # -- callbacks (Zenoh threads: short, never a decision) --------------------------------------
    def _on_member(self, change: MemberChange) -> None:
        """The membership view's news (under its lock): queued for the control loop."""
        if Role(change.role) is Role.REGISTRY:
            if change.id != self.id and change.alive:
                log.warning("another registry (%s) is alive in fleet %s", change.id, self.fleet)
            return
        self._events.put(change)

    def _on_telemetry(self, sample: zenoh.Sample) -> None:
        rec = self._publication(sample, TelemetryRecord, "telemetry")
        if rec is not None and self.measurements.record_telemetry(rec, str(sample.key_expr)):
            self._events.put(_Evaluate(rec.robot))

    def _on_probe_report(self, sample: zenoh.Sample) -> None:
        rep = self._publication(sample, ProbeReport, "probe report")
        if rep is not None:
            self.measurements.record_probe_report(rep, str(sample.key_expr))

    def _publication(
        self, sample: zenoh.Sample, kind: type[_Published], what: str
    ) -> _Published | None:
        """A robot's publication about itself (the key's robot must be the message's), or None
        once a bad one is logged."""
        key = str(sample.key_expr)
        try:
            data = sample.payload.to_bytes()
            check_size(data, self.max_request_bytes, what)
            message = kind.from_wire(data, max_bytes=self.max_request_bytes)
            parts = keys.parse_key(key)
            if parts is None or parts.id != message.robot:
                raise WireError(f"{what} of robot {message.robot!r} published on {key}")
        except WireError as exc:
            self.refusals.count(what, exc.code)
            self._bad_input(f"{what} on {key}", str(exc))
            return None
        return message

    def _bad_input(self, where: str, problem: str) -> None:
        """A dropped publication or sample: one throttled warning, so a misbehaving publisher
        cannot flood the log."""
        self.throttled.warning("ignored bad %s: %s", where, problem)

    def _on_reroute(self, query: zenoh.Query) -> None:
        request = decode_query(query, msg.RerouteRequest, max_bytes=self.max_request_bytes)
        self._events.put(_Request(request, query, keys.reg_reroute(self.fleet)))

    def _on_drain(self, query: zenoh.Query) -> None:
        request = decode_query(query, msg.DrainRequest, max_bytes=self.max_request_bytes)
        self._events.put(_Request(request, query, keys.reg_drain(self.fleet)))

    def _answer_error(
        self,
        name: str,
        reply_key: Callable[[zenoh.Query], str],
        query: zenoh.Query,
        exc: Exception,
    ) -> None:
        """Answer a query whose callback failed (`guarded` has logged why), and count it."""
        self.refusals.count(name, exc.code if isinstance(exc, WireError) else ErrorCode.INTERNAL)
        answer(query, (reply_key(query), error_payload(exc)))

    # -- control loop ----------------------------------------------------------------------------
    def _safely(self, fn: Callable[..., object], *args: Any) -> None:
        """One step of the control loop; a failure is logged (throttled), the loop goes on."""
        try:
            fn(*args)
        except Exception:
            what = getattr(fn, "__name__", fn)
            self.throttled.error("%s: unexpected error in %s", self.name, what, exc_info=True)

    def _handle(self, event: _Event) -> None:
        if isinstance(event, MemberChange):
            self._on_membership(event)
        elif isinstance(event, Probed):
            self._on_probed(event)
        elif isinstance(event, _Evaluate):
            self._evaluate(event.robot)
        else:
            self._on_request(event)

    def _on_request(self, event: _Request) -> None:
        """Act on a queued drain or reroute and answer it (an internal error if acting failed)."""
        try:
            if isinstance(event.message, msg.DrainRequest):
                payload = self._drain(event.message).to_wire()
            else:
                assert isinstance(event.message, msg.RerouteRequest)
                payload = self._reroute(event.message).to_wire()
        except Exception as exc:
            self.throttled.error("%s: unexpected error in %s", self.name, event.key, exc_info=True)
            payload = error_payload(exc)
        answer(event.query, (event.key, payload))

    def _answer_pending(self) -> None:
        """Requests still queued at shutdown get a refusal instead of a timeout."""
        while True:
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                return
            if isinstance(event, _Request):
                answer(event.query, (event.key, refusal(STOPPING_REASON)))

    def _on_membership(self, change: MemberChange) -> None:
        rib = self._parts.rib
        if Role(change.role) is Role.ROBOT:
            robot = change.id
            if change.alive:
                if robot not in self.cfg.machines:
                    log.info("robot %s is not in the fleet file; serving it anyway", robot)
                rib.upsert_robot(robot, service=self.service)
                log.info("robot %s is up", robot)
            elif rib.set_robot_alive(robot, False, "liveliness token gone"):
                log.info("robot %s is gone", robot)
                self.scheduler.forget(robot)
                self.measurements.forget_robot(robot)
            return
        deployment = change.id
        if change.alive:
            if self._parts.registrar.token_came(deployment):
                self._parts.prober.submit(deployment, refresh=False)
            return
        registration = self._parts.registrar.token_gone(deployment)
        self.measurements.forget_deployment(deployment)  # a returning process starts clean
        if registration is None or registration.state is not RegistrationState.ACCEPTED:
            return
        rib.set_deployment_alive(deployment, False, "liveliness token gone")
        log.info("deployment %s is gone", deployment)
        for route in rib.routes():
            if route.deployment == deployment:
                self._evaluate(route.robot)

    def _on_probed(self, event: Probed) -> None:
        deployment, reply = event.deployment, event.reply
        registrar = self._parts.registrar
        if event.refresh:
            if reply is not None and registrar.refresh(deployment, reply):
                self._repair(deployment, reply)
        elif registrar.admit(deployment, reply, event.error):
            assert reply is not None
            self._repair(deployment, reply)
            self._restore_routes(deployment)

    def _repair(self, deployment: str, reply: msg.ProbeReply) -> None:
        """Anycast repair: a deployment serving a robot the RIB routes elsewhere is put back in
        standby."""
        for robot, state in reply.states.items():
            if state is not msg.DeploymentState.SERVICE:
                continue
            routed_to, epoch = self.measurements.route(robot)
            if routed_to != deployment and (routed_to is not None or epoch > 0):
                log.warning(
                    "deployment %s serves %s, routed to %s: putting it in standby",
                    deployment,
                    robot,
                    routed_to or "local",
                )
                self._parts.switcher.fence(robot, deployment, at_least=reply.epochs.get(robot, 0))

    def _restore_routes(self, deployment: str) -> None:
        """Re-assert every restored route to this deployment that this run has not confirmed."""
        for route in self._parts.rib.routes():
            if route.deployment != deployment or route.robot in self._confirmed:
                continue
            result = self._parts.switcher.reassert(route.robot)
            if result.attempts and result.attempts[-1].outcome is Outcome.ACKED:
                self._confirmed.add(route.robot)
                self.measurements.set_route(result.robot, result.deployment, result.epoch)
                if not result.changed:
                    # Tell the robot again (receivers ignore an epoch they hold already).
                    self._publish(route.robot, deployment, result.epoch, "restore")
                log.info(
                    "restored route %s -> %s (epoch %d)", route.robot, deployment, result.epoch
                )
            else:
                detail = result.attempts[-1].detail if result.attempts else result.reason
                log.warning(
                    "cannot restore route %s -> %s: %s; rerouting",
                    route.robot,
                    deployment,
                    detail,
                )
                self._evaluate(route.robot, unusable=frozenset({deployment}))

    def _refresh_deployments(self) -> None:
        self.measurements.flush_loads(self._parts.rib)
        for deployment, refresh in self._parts.registrar.to_probe():
            self._parts.prober.submit(deployment, refresh=refresh)

    # -- decisions -------------------------------------------------------------------------------
    def _schedule_all(self) -> None:
        # One read of the RIB for the round (live robots with their routes, the deployments as
        # one table), not three per robot: per robot, reading and converting every deployment
        # made a round grow with robots x deployments (docs/scale.md).
        rib = self._parts.rib
        deployments = DeploymentTable(_deployment_views(rib.deployments(), frozenset()))
        for robot_row, route_row in rib.live_robots():
            self._evaluate(robot_row.id, read=(robot_row, route_row, deployments))

    def _waiting_for(self, robot: str, route: str | None) -> str | None:
        """The deployment a decision about `robot` should wait for (registration in flight, or a
        restored route's deployment not reconnected yet), else None."""
        target = route
        if target is None and robot in self.cfg.machines:
            target = self.cfg.initial_service(robot)
        if target is None:
            return None
        registrar = self._parts.registrar
        if registrar.is_state(target, RegistrationState.PENDING):
            return target
        in_grace = time.monotonic() - self._started_at < self.restore_grace_s
        if not registrar.seen(target) and in_grace:
            return target
        return None

    def _evaluate(
        self,
        robot: str,
        *,
        unusable: frozenset[str] = frozenset(),
        read: tuple[RobotRow | None, RouteRow | None, DeploymentTable] | None = None,
    ) -> SwitchResult | None:
        """Ask the scheduler about one robot and carry out its decision (control loop only).
        `read`: the robot's row, its route and the deployments as the round read them (else
        they are read here)."""
        rib = self._parts.rib
        if read is None:
            deployments = DeploymentTable(_deployment_views(rib.deployments(), unusable))
            read = (rib.robot(robot), rib.route(robot), deployments)
        robot_row, route_row, deployments = read
        current = route_row.deployment if route_row else None
        if not unusable and self._waiting_for(robot, current) is not None:
            return None
        measures = self.measurements.for_scheduler(robot, current)
        view = RobotView(
            id=robot,
            service=robot_row.service if robot_row is not None else self.service,
            route=current,
            telemetry=measures.telemetry,
            timeouts=measures.timeouts,
            timeouts_on=measures.timeouts_on,
            model_digest=self._parts.registrar.robot_digest(robot),
            busy=measures.busy,
            offloaded=measures.offloaded,
        )
        decision = self.scheduler.evaluate(view, deployments, measures.profiles)
        if decision is None:
            return None
        return self._carry_out(_prefer_initial(self.cfg, decision))

    def _carry_out(self, decision: Decision) -> SwitchResult:
        switcher, scheduler = self._parts.switcher, self.scheduler
        if decision.reason is Reason.INITIAL:
            # A placement is not a move: it must not start the scheduler's dwell time, or a
            # robot placed on a slow deployment would wait min_dwell_s on top of the hysteresis.
            result = switcher.apply(decision)
            if not result.changed and result.attempts:
                scheduler.record_failure(decision.robot)
        else:
            result = carry_out(scheduler, switcher, decision)
        if result.changed:
            self._confirmed.add(decision.robot)
            self.measurements.set_route(result.robot, result.deployment, result.epoch)
            log.info(
                "route %s: %s -> %s (epoch %d, %s)",
                result.robot,
                result.previous or "local",
                result.deployment or "local",
                result.epoch,
                decision.reason.value,
            )
        elif result.attempts:
            tried = ", ".join(f"{a.deployment}: {a.outcome.value}" for a in result.attempts)
            log.warning("route %s not moved (%s): %s", result.robot, decision.reason.value, tried)
        return result

    def _drain(self, request: msg.DrainRequest) -> Message:
        """Move every robot of a deployment that stops; the reply lists the robots moved."""
        deployment = request.deployment
        rib = self._parts.rib
        if rib.deployment(deployment) is None and self._parts.registrar.get(deployment) is None:
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
            result = self._evaluate(route.robot)
            if result is not None and result.changed:
                moved.append(route.robot)
            else:
                stuck.append(route.robot)
        reason = ""
        if stuck:
            reason = (
                f"no other deployment took {', '.join(stuck)}; they compute locally once it stops"
            )
            log.warning("drain of %s: %s", deployment, reason)
        return msg.DrainReply(ok=not stuck, moved=tuple(moved), reason=reason)

    def _reroute(self, request: msg.RerouteRequest) -> Message:
        """A robot's request for another deployment: answered with its route afterwards."""
        robot = request.robot
        rib = self._parts.rib
        if rib.robot(robot) is None:
            return ErrorReply.make(
                ErrorCode.REFUSED, f"unknown robot {robot!r}: its liveliness token was never seen"
            )
        route = rib.route(robot)
        if route is None or route.deployment is None:
            self._evaluate(robot)
        elif not 0 < request.epoch < route.epoch:
            # The route failing the robot is the current one (or the robot does not know which it
            # holds): a forced move, as after timeouts. An older epoch: it has moved already.
            self.measurements.force_timeouts(robot, route.deployment, request.consecutive_timeouts)
            self._evaluate(robot)
        now = rib.route(robot)
        moved = now is not None and (route is None or now.epoch != route.epoch)
        return _route_change(
            robot,
            now.deployment if now else None,
            now.epoch if now else 0,
            "rerouted" if moved else "current route",
        )

    def _publish(self, robot: str, deployment: str | None, epoch: int, reason: str) -> None:
        try:
            self._parts.transport.publish_route(_route_change(robot, deployment, epoch, reason))
        except TransportError as exc:
            log.warning("%s", exc)


def _latency_bound(cfg: FleetConfig) -> LatencyBound:
    lb = cfg.latency_bound
    return LatencyBound(
        stat=lb.stat,
        seconds=lb.seconds,
        window=lb.window,
        hysteresis_s=lb.hysteresis_s,
        better_margin=lb.better_margin,
    )


def _deployment_views(
    rows: Iterable[DeploymentRow], unusable: frozenset[str]
) -> list[DeploymentView]:
    """The scheduler's view of the RIB's deployments; those `unusable` count as dead."""
    return [
        DeploymentView(
            id=row.id,
            service=row.service,
            alive=row.alive and row.id not in unusable,
            draining=row.draining,
            load=row.load,
            capacity=row.capacity,
            model_digest=row.model_digest or None,
        )
        for row in rows
    ]


def _prefer_initial(cfg: FleetConfig, decision: Decision) -> Decision:
    """An initial placement goes to initial_policy's service machine when it can."""
    if decision.reason is not Reason.INITIAL or decision.robot not in cfg.machines:
        return decision
    wanted = cfg.initial_service(decision.robot)
    if wanted is None or wanted not in decision.candidates:
        return decision
    order = (wanted, *(c for c in decision.candidates if c != wanted))
    return Decision(decision.robot, decision.from_deployment, wanted, decision.reason, order, None)


def _route_change(robot: str, deployment: str | None, epoch: int, reason: str) -> msg.RouteChange:
    return msg.RouteChange(
        robot=robot, deployment=deployment, epoch=epoch, reason=reason, at=time.time()
    )


def run_registry(cfg: FleetConfig, *, db_path: str | Path | None = None) -> int:
    """Run the registry in this (main) thread until SIGINT/SIGTERM; returns the exit code."""
    return RegistryDaemon(cfg, db_path=db_path).run()
