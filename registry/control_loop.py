"""The registry's control loop: what it decides and carries out, apart from the daemon.

`ControlLoop` takes the registry's parts (the RIB, the transport to the deployments and robots,
the switch protocol, the registrar, the prober, the pools of a round-robin fleet, the scheduler
and the measurements) and hands out decisions: `handle` acts on one event at once (a membership
change, a probe outcome, a robot to evaluate, a queued drain or reroute), `schedule_all` is one
scheduling round (every live robot evaluated, moves carried out), `refresh_deployments` submits
the probes that are due. Every route that changes is counted in `metrics` (`registry.metrics`,
off unless the daemon serves them). A control loop routes one service (its `cfg` is that
service's view of the fleet, `FleetConfig.for_service`): the registry daemon runs one per service
(`registry.plane`) and dispatches each event to the planes it concerns (`registry.planes`). It
opens nothing and runs no thread: the daemon
(`registry.daemon`) makes the parts at startup, feeds it from its queue and ticks it; the
registry simulation (`benchmarks/registry_sim_fleet.py`) drives it with simulated parts and time.

Decisions. A robot with no live route gets one: its restored route if that deployment is alive
(re-asserted at the same epoch, so a cloud daemon restarted meanwhile declares the key again),
else initial_policy's service machine if alive, else the scheduler's choice (what it is asked
with: `registry.round_inputs`). A deployment whose token disappears, or a robot reporting
`timeout_count` consecutive timeouts, is handled at once; bound violations and improvements wait
out the scheduler's hysteresis. After a restart, a route whose deployment has not reconnected yet
is left alone for `restore_grace_s`. A deployment found serving a robot that the RIB routes
elsewhere is put back in standby (anycast repair).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from common.config import FleetConfig
from common.keys import Role
from common.membership import MemberChange
from common.throttled_log import ThrottledLog
from common.wire import registry as msg
from registry.deployment_table import deployment_table
from registry.measurements import Measurements
from registry.metrics import RESTORE, RegistryMetrics
from registry.pool_keeper import PoolKeeper
from registry.prober import Probed, RegistryProber
from registry.registration import Registrar, RegistrationState
from registry.replies import answer, error_payload
from registry.requests import QueuedRequest, drain, reroute, route_change
from registry.rib import Rib, RibRobotRow, RibRouteRow
from registry.round_inputs import prefer_initial, robot_view, waiting_for
from registry.scheduler import DeploymentTable, Reason, RouteDecision, Scheduler
from registry.switch import Switcher, SwitchOutcome, SwitchResult, TransportError, carry_out
from registry.transport import ZenohTransport

log = logging.getLogger("registry.daemon")  # one logger for the registry's lines


@dataclass(frozen=True)
class Evaluate:
    """Evaluate one robot now (its telemetry reported a timeout run) for `service` (None: the
    fleet's first)."""

    robot: str
    service: str | None = None


Event = MemberChange | Probed | Evaluate | QueuedRequest


@dataclass
class ControlLoop:
    """The registry's decisions over its parts (see the module docstring). Only one thread (the
    daemon's main thread, or the simulation) calls it."""

    cfg: FleetConfig
    rib: Rib
    transport: ZenohTransport
    switcher: Switcher
    registrar: Registrar
    prober: RegistryProber
    pools: PoolKeeper | None  # round robin only
    scheduler: Scheduler
    measurements: Measurements
    throttled: ThrottledLog
    started_at: float
    """When the daemon started (its clock): restored routes wait `restore_grace_s` from it."""
    restore_grace_s: float
    confirmed: set[str] = field(default_factory=set)
    """Robots whose route was confirmed in this run."""
    metrics: RegistryMetrics = field(default_factory=lambda: RegistryMetrics(None))
    """Counts every route change (`registry.metrics`); off (counts nothing) by default."""

    @property
    def service(self) -> str:
        return self.cfg.service_name

    def handle(self, event: Event) -> None:
        """Act on one event (a membership change, a probe outcome, a robot to evaluate, a
        queued request) at once."""
        if isinstance(event, MemberChange):
            self._on_membership(event)
        elif isinstance(event, Probed):
            self._on_probed(event)
        elif isinstance(event, Evaluate):
            self.evaluate(event.robot)
        else:
            self._on_request(event)

    def _on_request(self, event: QueuedRequest) -> None:
        """Act on a queued drain or reroute and answer it (an internal error if acting failed)."""
        rib, request = self.rib, event.message
        try:
            if isinstance(request, msg.DrainRequest):
                reply = drain(request, rib, self.registrar, self.evaluate)
            else:
                assert isinstance(request, msg.RerouteRequest)
                reply = reroute(
                    request, rib, self.measurements, self.evaluate, service=self.service
                )
            payload = reply.to_wire()
        except Exception as exc:
            self.throttled.error("registry: unexpected error in %s", event.key, exc_info=True)
            payload = error_payload(exc)
        answer(event.query, (event.key, payload))

    def _on_membership(self, change: MemberChange) -> None:
        rib = self.rib
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
            if self.registrar.token_came(deployment):
                self.prober.submit(deployment, refresh=False)
            return
        registration = self.registrar.token_gone(deployment)
        self.measurements.forget_deployment(deployment)  # a returning process starts clean
        if registration is None or registration.state is not RegistrationState.ACCEPTED:
            return
        rib.set_deployment_alive(deployment, False, "liveliness token gone")
        log.info("deployment %s is gone", deployment)
        for route in rib.routes():
            if route.deployment == deployment:
                self.evaluate(route.robot)
            elif deployment in route.pool and self.pools is not None:
                self.pools.rebuild(route.robot, "pool member gone")

    def _on_probed(self, event: Probed) -> None:
        deployment, reply = event.deployment, event.reply
        registrar = self.registrar
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
            if routed_to == deployment or (routed_to is None and epoch == 0):
                continue
            if deployment in self.rib.pool(robot):
                continue  # a member of the robot's round-robin pool serves it by design
            log.warning(
                "deployment %s serves %s, routed to %s: putting it in standby",
                deployment,
                robot,
                routed_to or "local",
            )
            self.switcher.fence(robot, deployment, at_least=reply.epochs.get(robot, 0))

    def _restore_routes(self, deployment: str) -> None:
        """Re-assert every restored route to this deployment that this run has not confirmed."""
        for route in self.rib.routes():
            if route.deployment != deployment or route.robot in self.confirmed:
                continue
            result = self.switcher.reassert(route.robot)
            if result.attempts and result.attempts[-1].outcome is SwitchOutcome.ACKED:
                self.confirmed.add(route.robot)
                row = self.rib.robot(route.robot)
                # A robot not back yet holds no room there: a round counts it once it is.
                pool = route.pool if row is not None and row.alive else None
                self.measurements.set_route(result.robot, result.deployment, result.epoch, pool)
                if result.changed:
                    self.metrics.route_change(RESTORE, None, service=self.service)
                else:
                    # Tell the robot again (receivers ignore an epoch they hold already).
                    self._publish(route.robot, deployment, result.epoch, "restore", pool=route.pool)
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
                self.evaluate(route.robot, unusable=frozenset({deployment}))

    def refresh_deployments(self) -> None:
        """Flush the loads and submit the deployments due for a probe (registration or load)."""
        self.measurements.flush_loads(self.rib)
        for deployment, refresh in self.registrar.to_probe():
            self.prober.submit(deployment, refresh=refresh)

    # -- decisions -------------------------------------------------------------------------------
    def schedule_all(self) -> None:
        """One round: every live robot evaluated, the decisions carried out, pools tended."""
        # One read of the RIB for the round (live robots with their routes, the deployments as
        # one table), not three per robot (`registry.round_inputs`).
        rib = self.rib
        rows = rib.deployments()
        deployments = deployment_table(rows)
        pools = self.pools
        usable = pools.planner.usable(rows) if pools is not None else set()
        for robot_row, route_row in rib.live_robots():
            result = self.evaluate(robot_row.id, read=(robot_row, route_row, deployments))
            if (
                pools is not None
                and route_row is not None
                and (result is None or not result.changed)
            ):
                pools.tend(route_row, usable)

    def evaluate(
        self,
        robot: str,
        *,
        unusable: frozenset[str] = frozenset(),
        read: tuple[RibRobotRow | None, RibRouteRow | None, DeploymentTable] | None = None,
    ) -> SwitchResult | None:
        """Ask the scheduler about one robot and carry out its decision (control loop only).
        `read`: the robot's row, its route and the deployments as the round read them (else
        they are read here)."""
        rib, registrar = self.rib, self.registrar
        if read is None:
            read = (
                rib.robot(robot),
                rib.route(robot),
                deployment_table(rib.deployments(), unusable),
            )
        robot_row, route_row, deployments = read
        current = route_row.deployment if route_row else None
        if not unusable:
            grace_until = self.started_at + self.restore_grace_s
            if (
                waiting_for(self.cfg, registrar, robot, current, grace_until=grace_until)
                is not None
            ):
                return None
        measures = self.measurements.for_scheduler(
            robot, current, route_row.pool if route_row else ()
        )
        view = robot_view(
            robot,
            robot_row,
            current,
            measures,
            default_service=self.service,
            model_digest=registrar.robot_digest(robot),
        )
        decision = self.scheduler.evaluate(view, deployments, measures.profiles)
        if decision is None:
            return None
        return self._carry_out(prefer_initial(self.cfg, decision))

    def _carry_out(self, decision: RouteDecision) -> SwitchResult:
        switcher, scheduler = self.switcher, self.scheduler
        if decision.reason is Reason.INITIAL:
            # A placement is not a move: it must not start the scheduler's dwell time, or a
            # robot placed on a slow deployment would wait min_dwell_s on top of the hysteresis.
            result = switcher.apply(decision)
            if not result.changed and result.attempts:
                scheduler.record_failure(decision.robot)
        else:
            result = carry_out(scheduler, switcher, decision)
        if result.changed:
            self.metrics.route_change(decision.reason.value, result.previous, service=self.service)
        if result.changed and decision.reason is Reason.NO_CAPACITY:
            self.measurements.set_route(result.robot, None, result.epoch)
            log.info(
                "route %s: no deployment has room, the robot computes locally (epoch %d)",
                result.robot,
                result.epoch,
            )
        elif result.changed:
            self.confirmed.add(decision.robot)
            self.measurements.set_route(result.robot, result.deployment, result.epoch, result.pool)
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

    def _publish(
        self,
        robot: str,
        deployment: str | None,
        epoch: int,
        reason: str,
        *,
        pool: tuple[str, ...] = (),
    ) -> None:
        try:
            self.transport.publish_route(
                route_change(robot, deployment, epoch, reason, pool=pool, service=self.service)
            )
        except TransportError as exc:
            log.warning("%s", exc)
