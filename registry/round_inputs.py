"""What the registry hands the scheduler about a robot, built from the RIB's rows, the
measurements and the registrar; and the initial placement's preference, applied to its answer.

The preference (`prefer_initial`: initial_policy's service machine) gives way to load: it does not
send a robot to a deployment the scheduler found crowded (`RouteDecision.crowded`), so a fleet
whose robots are all in service on one deployment spreads to the others once it has no room to
spare (docs/registry.md, "Choice").

The scheduler (`registry.scheduler`) is pure: it sees `RobotView`s and a `DeploymentTable`, never
the RIB. A scheduling round reads the deployments once as one table
(`registry.deployment_table`) and
each live robot's row and route with them; reading and converting every deployment per robot
made a round grow with robots x deployments (docs/scale.md). `waiting_for` says when a decision
about a robot should wait instead (a registration in flight, or a restored route whose deployment
has not reconnected yet).
"""

from __future__ import annotations

import time
from dataclasses import replace

from common.config import FleetConfig
from registry.measurements import RobotMeasures
from registry.registration import Registrar, RegistrationState
from registry.rib import RibRobotRow
from registry.scheduler import (
    Reason,
    RobotView,
    RouteDecision,
)


def robot_view(
    robot: str,
    row: RibRobotRow | None,
    route: str | None,
    measures: RobotMeasures,
    *,
    default_service: str,
    model_digest: str | None,
) -> RobotView:
    """The scheduler's view of one robot: its RIB row (`default_service` without one), its
    current route and its measurements (with the robots routed to each deployment)."""
    return RobotView(
        id=robot,
        service=row.service if row is not None else default_service,
        route=route,
        telemetry=measures.telemetry,
        timeouts=measures.timeouts,
        timeouts_on=measures.timeouts_on,
        model_digest=model_digest,
        busy=measures.busy,
        offloaded=measures.offloaded,
        routed=measures.routed,
    )


def waiting_for(
    cfg: FleetConfig,
    registrar: Registrar,
    robot: str,
    route: str | None,
    *,
    grace_until: float,
) -> str | None:
    """The deployment a decision about `robot` should wait for (registration in flight, or a
    restored route's deployment not reconnected before `grace_until`, on the monotonic clock),
    else None."""
    target = route
    if target is None and robot in cfg.machines:
        target = cfg.initial_service(robot)
    if target is None:
        return None
    if registrar.is_state(target, RegistrationState.PENDING):
        return target
    if not registrar.seen(target) and time.monotonic() < grace_until:
        return target
    return None


def prefer_initial(cfg: FleetConfig, decision: RouteDecision) -> RouteDecision:
    """An initial placement goes to initial_policy's service machine when it can: a candidate
    with room to spare (not crowded)."""
    if decision.reason is not Reason.INITIAL or decision.robot not in cfg.machines:
        return decision
    wanted = cfg.initial_service(decision.robot)
    if wanted is None or wanted not in decision.candidates or wanted in decision.crowded:
        return decision
    order = (wanted, *(c for c in decision.candidates if c != wanted))
    return replace(decision, to_deployment=wanted, candidates=order, predicted_s=None)
