"""The registry's read-only views (`rib/<view>`): rows built from the RIB and the measurements.

`RibViews.view(name, query)` is the reply message of one view under a `RibQuery`'s filters
(robot, deployment, limit). `RibViews.answer(query)` serves the registry's `rib/*` queryable on
Zenoh's callback thread: a wildcard query (`rib/*`) gets every view it names, each on its own
key; a key naming no view is refused, naming the views there are. Nothing here writes: the RIB
serializes its own reads, `Measurements` hands out snapshots, and the refusals come from the
`Registrar`'s table. The rows are wire contracts (common/wire/registry.py, the CLI's `--json`):
their fields and values do not change lightly.

| view | rows |
| --- | --- |
| deployments | every deployment in the RIB, then refused ones never accepted (`extra.refused`) |
| robots | every robot with its route and why, its deployment's state for it, its telemetry window |
| routes | every route with the reason of its last route event |
| events | the newest `limit` events (100 by default, at most 10 000), oldest first |
| profiles | the probe windows per robot x deployment |
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from enum import Enum
from typing import Any

import zenoh

from common import keys
from common.defaults import DEFAULT_MAX_REQUEST_BYTES
from common.errors import UserError
from common.wire import Message
from common.wire import registry as msg
from registry.latency import LatencyBound, Stat
from registry.measurements import Measurements
from registry.registration import Registrar
from registry.replies import answer, decode_query, refusal
from registry.rib import EventKind, Rib

DEFAULT_EVENTS_LIMIT = 100
MAX_EVENTS_LIMIT = 10_000


class RouteState(str, Enum):
    """A robot's state in the robots view when no deployment serves it (otherwise its
    deployment's state for it: `service` or `draining`)."""

    LOCAL = "local"  # routed to no deployment: it computes every frame itself
    UNROUTED = "unrouted"  # never routed yet


class RibViews:
    """`RibViews(fleet, rib, measurements, registrar, bound, deadline_s).view("routes")`;
    `max_request_bytes`: the largest `RibQuery` read (`registry.max_request_bytes`)."""

    def __init__(
        self,
        fleet: str,
        rib: Rib,
        measurements: Measurements,
        registrar: Registrar,
        bound: LatencyBound,
        deadline_s: float,
        *,
        max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
    ) -> None:
        self.fleet = fleet
        self.rib = rib
        self.measurements = measurements
        self.registrar = registrar
        self.bound = bound
        self.deadline_s = deadline_s
        self.max_request_bytes = max_request_bytes

    def answer(self, query: zenoh.Query) -> None:
        """Answer a query on `rib/*` (a WireError for a bad `RibQuery`, answered by the caller
        on `reply_key(query)`)."""
        views = self._views_asked(query)
        if not views:
            reason = (
                f"no RIB view at {query.key_expr}; views: {', '.join(keys.RIB_VIEWS)} "
                f"under {keys.rib_all(self.fleet)}"
            )
            answer(query, (str(query.key_expr), refusal(reason)))
            return
        request = decode_query(query, msg.RibQuery, max_bytes=self.max_request_bytes, empty_ok=True)
        answer(query, *((keys.rib(self.fleet, v), self.view(v, request).to_wire()) for v in views))

    def reply_key(self, query: zenoh.Query) -> str:
        """Where an error about `query` is answered: the first view it names, else its key."""
        views = self._views_asked(query)
        return keys.rib(self.fleet, views[0]) if views else str(query.key_expr)

    def _views_asked(self, query: zenoh.Query) -> list[str]:
        return [
            v
            for v in keys.RIB_VIEWS
            if zenoh.KeyExpr(keys.rib(self.fleet, v)).intersects(query.key_expr)
        ]

    def view(self, name: str, query: msg.RibQuery | None = None) -> Message:
        """The reply of the RIB view `name` (one of keys.RIB_VIEWS) under `query`'s filters."""
        q = query if query is not None else msg.RibQuery()
        now = time.time()
        if name == "deployments":
            return msg.DeploymentsView(rows=tuple(self._deployment_rows(q)), generated_at=now)
        if name == "robots":
            return msg.RobotsView(rows=tuple(self._robot_rows(q)), generated_at=now)
        if name == "routes":
            return msg.RoutesView(rows=tuple(self._route_rows(q)), generated_at=now)
        if name == "events":
            return msg.EventsView(rows=tuple(self._event_rows(q)), generated_at=now)
        if name == "profiles":
            return msg.ProfilesView(rows=tuple(self._profile_rows(q)), generated_at=now)
        raise UserError(f"unknown RIB view {name!r}; known: {', '.join(keys.RIB_VIEWS)}")

    def _deployment_rows(self, q: msg.RibQuery) -> Iterable[msg.DeploymentRow]:
        rib = self.rib
        refused = self.registrar.refused()
        listed: set[str] = set()
        for row in rib.deployments():
            if q.deployment is not None and row.id != q.deployment:
                continue
            listed.add(row.id)
            states = rib.deployment_states(deployment=row.id)
            extra: dict[str, Any] = {
                "version": row.version,
                "draining": row.draining,
                "epochs": {s.robot: s.epoch for s in states},
            }
            if row.id in refused:
                extra["refused"] = refused[row.id]
            yield msg.DeploymentRow(
                id=row.id,
                service=row.service,
                alive=row.alive,
                model_digest=row.model_digest or None,
                states={s.robot: s.state for s in states},
                load=row.load,
                capacity=row.capacity,
                last_seen=row.last_seen,
                extra=extra,
            )
        for deployment, reason in sorted(refused.items()):
            if deployment not in listed and q.deployment in (None, deployment):
                yield msg.DeploymentRow(
                    id=deployment, service="", alive=False, extra={"refused": reason}
                )

    def _robot_rows(self, q: msg.RibQuery) -> Iterable[msg.RobotRow]:
        rib = self.rib
        for row in rib.robots():
            if q.robot is not None and row.id != q.robot:
                continue
            route = rib.route(row.id)
            deployment = route.deployment if route else None
            if deployment is not None:
                states = rib.deployment_states(robot=row.id, deployment=deployment)
                state = (states[0].state if states else msg.DeploymentState.SERVICE).value
            elif route is not None:
                state = RouteState.LOCAL.value
            else:
                state = RouteState.UNROUTED.value
            status = self.measurements.robot_status(row.id, deployment)
            stats = status.telemetry
            # Why the robot is where it is: its last route event (as in the routes view).
            last = rib.events(limit=1, robot=row.id, kind=EventKind.ROUTE.value)
            yield msg.RobotRow(
                id=row.id,
                service=row.service,
                alive=row.alive,
                deployment=deployment,
                epoch=route.epoch if route else 0,
                bound_stat=Stat(self.bound.stat).value,
                bound_s=self.bound.seconds,
                window_stat_s=stats.value(self.bound.stat) if stats else None,
                window_len=stats.count if stats else 0,
                deadline_s=self.deadline_s,
                action=status.action,
                reason=last[0].reason if last else "",
                extra={
                    "state": state,
                    "consecutive_timeouts": status.timeouts,
                    "last_seen": row.last_seen,
                    "last_telemetry": status.last_telemetry,
                },
            )

    def _route_rows(self, q: msg.RibQuery) -> Iterable[msg.RouteRow]:
        rib = self.rib
        for route in rib.routes():
            if q.robot is not None and route.robot != q.robot:
                continue
            if q.deployment is not None and route.deployment != q.deployment:
                continue
            last = rib.events(limit=1, robot=route.robot, kind=EventKind.ROUTE.value)
            yield msg.RouteRow(
                robot=route.robot,
                deployment=route.deployment,
                epoch=route.epoch,
                since=route.since,
                reason=last[0].reason if last else "",
                pool=route.pool,
            )

    def _event_rows(self, q: msg.RibQuery) -> Iterable[msg.EventRow]:
        limit = min(q.limit or DEFAULT_EVENTS_LIMIT, MAX_EVENTS_LIMIT)
        if limit < 1:
            return
        fetch = MAX_EVENTS_LIMIT if q.deployment is not None else limit
        rows = self.rib.events(fetch, robot=q.robot)
        if q.deployment is not None:
            rows = [e for e in rows if e.deployment == q.deployment][-limit:]
        for e in rows:
            yield msg.EventRow(
                seq=e.seq,
                at=e.ts,
                kind=e.kind,
                reason=e.reason,
                robot=e.robot,
                deployment=e.deployment,
                epoch=e.epoch,
            )

    def _profile_rows(self, q: msg.RibQuery) -> Iterable[msg.ProfileRow]:
        for profile in self.measurements.probe_profiles():
            if q.robot not in (None, profile.robot) or q.deployment not in (
                None,
                profile.deployment,
            ):
                continue
            stats = profile.stats
            yield msg.ProfileRow(
                robot=profile.robot,
                deployment=profile.deployment,
                samples=stats.count,
                median_s=stats.median,
                mean_s=stats.mean,
                p95_s=stats.p95,
                max_s=stats.max,
                stddev_s=stats.stddev,
                updated_at=profile.updated_at,
            )
