"""The registry's read-only views (`rib/<view>`): rows built from the RIB and the measurements.

`RibViews` are one service's rows (a plane's: its RIB, its measurements, its registrar), each
naming the service. `FleetViews` are the fleet's: every plane's rows, plane by plane (the events
merged by time), or one service's under `RibQuery.service`. `FleetViews.view(name, query)` is the
reply message of one view under a `RibQuery`'s filters (robot, deployment, limit, service).
`FleetViews.answer(query)` serves the registry's `rib/*` queryable on Zenoh's callback thread: a
wildcard query (`rib/*`) gets every view it names, each on its own key; a key naming no view is
refused, naming the views there are, and so is a service the fleet does not serve. Nothing here
writes: the RIB serializes its own reads, `Measurements` hands out snapshots, and the refusals
come from the `Registrar`'s table. The rows are wire contracts (common/wire/registry.py, the
CLI's `--json`): their fields and values do not change lightly.

| view | rows |
| --- | --- |
| deployments | every deployment in the RIB, then refused ones never accepted (`extra.refused`) |
| robots | every robot with its route and why, its deployment's state for it, its telemetry window |
| routes | every route with the reason of its last route event |
| events | the newest `limit` events (100 by default, at most 10 000) of the fleet, oldest first |
| profiles | the probe windows per robot x deployment |
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Callable, Iterable, Sequence
from enum import Enum
from typing import Any

import zenoh

from common import keys
from common.defaults import DEFAULT_MAX_REQUEST_BYTES
from common.errors import UserError
from common.wire import Message, Struct
from common.wire import registry as msg
from registry.latency import LatencyBound, Stat
from registry.measurements import Measurements
from registry.registration import Registrar
from registry.replies import answer, check_service, decode_query, refusal
from registry.rib import EventKind, Rib

DEFAULT_EVENTS_LIMIT = 100
MAX_EVENTS_LIMIT = 10_000


class RouteState(str, Enum):
    """A robot's state in the robots view when no deployment serves it (otherwise its
    deployment's state for it: `service` or `draining`)."""

    LOCAL = "local"  # routed to no deployment: it computes every frame itself
    UNROUTED = "unrouted"  # never routed yet


class RibViews:
    """One service's rows: `RibViews(fleet, rib, measurements, registrar, bound,
    deadline_s).view("routes")` (the service is the registrar's); `max_request_bytes`: the
    largest `RibQuery` read (`registry.max_request_bytes`)."""

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
        self.service = registrar.service
        self.bound = bound
        self.deadline_s = deadline_s
        self.max_request_bytes = max_request_bytes

    def answer(self, query: zenoh.Query) -> None:
        """Answer a query on `rib/*` with this service's rows (see `FleetViews.answer`)."""
        FleetViews(self.fleet, [self], max_request_bytes=self.max_request_bytes).answer(query)

    def reply_key(self, query: zenoh.Query) -> str:
        """Where an error about `query` is answered (see `FleetViews.reply_key`)."""
        return FleetViews(self.fleet, [self]).reply_key(query)

    def view(self, name: str, query: msg.RibQuery | None = None) -> Message:
        """The reply of the RIB view `name` (one of keys.RIB_VIEWS) under `query`'s filters."""
        return FleetViews(self.fleet, [self]).view(name, query)

    def rows(self, name: str, q: msg.RibQuery) -> list[Struct]:
        """This service's rows of view `name` under `q`'s filters (its service filter aside)."""
        if name == "deployments":
            return list(self._deployment_rows(q))
        if name == "robots":
            return list(self._robot_rows(q))
        if name == "routes":
            return list(self._route_rows(q))
        if name == "events":
            return list(self._event_rows(q))
        if name == "profiles":
            return list(self._profile_rows(q))
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
                    id=deployment, service=self.service, alive=False, extra={"refused": reason}
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
                service=self.service,
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
                service=self.service,
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
                service=self.service,
            )


class FleetViews:
    """The fleet's views: every service's rows (`planes`: each service's `RibViews`, the fleet's
    first service first). `max_request_bytes`: the largest `RibQuery` read."""

    def __init__(
        self,
        fleet: str,
        planes: Sequence[RibViews],
        *,
        max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
    ) -> None:
        if not planes:
            raise ValueError("a fleet's views need at least one service's")
        self.fleet = fleet
        self.planes = tuple(planes)
        self.max_request_bytes = max_request_bytes

    def answer(self, query: zenoh.Query) -> None:
        """Answer a query on `rib/*` (a WireError for a bad `RibQuery` or an unknown service,
        answered by the caller on `reply_key(query)`)."""
        views = self._views_asked(query)
        if not views:
            reason = (
                f"no RIB view at {query.key_expr}; views: {', '.join(keys.RIB_VIEWS)} "
                f"under {keys.rib_all(self.fleet)}"
            )
            answer(query, (str(query.key_expr), refusal(reason)))
            return
        request = decode_query(query, msg.RibQuery, max_bytes=self.max_request_bytes, empty_ok=True)
        check_service(request.service, [p.service for p in self.planes])
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
        """The reply of the RIB view `name` (one of keys.RIB_VIEWS) under `query`'s filters: the
        rows of every service (of `query.service` only, when it names one)."""
        q = query if query is not None else msg.RibQuery()
        if name not in msg.RIB_VIEW_REPLIES:
            raise UserError(f"unknown RIB view {name!r}; known: {', '.join(keys.RIB_VIEWS)}")
        planes = [p for p in self.planes if q.service in (None, p.service)]
        now = time.time()
        if name == "events":
            rows = self._events(planes, q)
        else:
            rows = [row for plane in planes for row in plane.rows(name, q)]
        make: Callable[..., Message] = msg.RIB_VIEW_REPLIES[name]
        return make(rows=tuple(rows), generated_at=now)

    @staticmethod
    def _events(planes: Sequence[RibViews], q: msg.RibQuery) -> list[Struct]:
        """The newest `limit` events of the planes, oldest first (one plane's as its log has
        them; several merged by time, each log's order kept)."""
        logs = [plane.rows("events", q) for plane in planes]
        if len(logs) == 1:
            return logs[0]
        limit = min(q.limit or DEFAULT_EVENTS_LIMIT, MAX_EVENTS_LIMIT)
        merged = list(heapq.merge(*logs, key=lambda row: getattr(row, "at", 0.0)))
        return merged[-limit:] if limit > 0 else []
