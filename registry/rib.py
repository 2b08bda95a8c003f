"""The routing information base (RIB): the registry's state in one sqlite file.

Tables: deployments, deployment_states (per deployment and robot: standby, service or draining, with
the epoch of the last state change), robots, routes (robot → deployment, epoch), profiles
(latency samples per robot × deployment × source: `registry.rib_profiles`) and events (every
transition, with its reason: `registry.rib_events`).
The file survives restarts: a restarted registry reads routes and epochs back and resumes from
them, so epochs keep growing and the anycast invariant can be repaired. Liveness flags are not
trusted after a restart: call `reset_liveness()` and seed membership again from liveliness.

The schema carries a version in sqlite's `user_version`; a file written by another version is
refused with a message naming the file. WAL journal mode lets readers (the CLI's queryables) run
while the scheduler writes. One connection is shared behind a lock, so callers on Zenoh callback
threads and the scheduler thread are serialized; every write is its own short transaction, and
what comes in bulk (profile windows, deployment loads) is written by one call in one transaction.

Times stored here (`last_seen`, `since`, `ts`, `updated_at`) are wall-clock seconds since the epoch,
so they mean something after a restart and on another host.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

# One definition of a deployment's state per robot: the wire's (re-exported here for the RIB's
# callers).
from common.wire.registry import DeploymentState
from registry.rib_events import EventKind as EventKind  # re-exported
from registry.rib_events import RibEventRow as RibEventRow
from registry.rib_events import RibEvents
from registry.rib_profiles import RibProfileRow as RibProfileRow  # re-exported
from registry.rib_store import MEMORY as MEMORY  # re-exported: callers open Rib(MEMORY)
from registry.rib_store import SCHEMA_VERSION as SCHEMA_VERSION


@dataclass(frozen=True)
class RibDeploymentRow:
    """A cloud/edge deployment as the registry last saw it."""

    id: str
    service: str
    model_digest: str
    capacity: int
    load: int
    version: str
    last_seen: float
    alive: bool
    draining: bool

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a JSON view."""
        return asdict(self)


@dataclass(frozen=True)
class RibRobotRow:
    """A robot as the registry last saw it."""

    id: str
    service: str
    alive: bool
    last_seen: float

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a JSON view."""
        return asdict(self)


@dataclass(frozen=True)
class RibRouteRow:
    """Which deployment serves a robot (None: the robot computes locally), under which epoch;
    `pool`: in a round-robin fleet every deployment serving it, `deployment` first (empty in an
    anycast fleet)."""

    robot: str
    deployment: str | None
    epoch: int
    since: float
    pool: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a JSON view."""
        return asdict(self)


@dataclass(frozen=True)
class RibDeploymentStateRow:
    """One deployment's state for one robot."""

    deployment: str
    robot: str
    state: DeploymentState
    epoch: int

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a JSON view."""
        return {**asdict(self), "state": self.state.value}


def _check_id(what: str, value: str) -> None:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what} must be a non-empty string, got {value!r}")


def _check_count(what: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{what} must be an integer >= 0, got {value!r}")


class Rib(RibEvents):
    """The routing information base over one sqlite file (or `":memory:"` for tests)."""

    # -- deployments -----------------------------------------------------------------------------
    def upsert_deployment(
        self,
        deployment: str,
        *,
        service: str,
        model_digest: str,
        capacity: int,
        version: str,
        load: int = 0,
    ) -> None:
        """Register or refresh a live deployment; records `deployment_up` when it was not alive."""
        _check_id("deployment id", deployment)
        _check_id("service", service)
        _check_count("capacity", capacity)
        _check_count("load", load)
        now = self._clock()
        with self._tx() as conn:
            row = conn.execute(
                "SELECT alive FROM deployments WHERE id = ?", (deployment,)
            ).fetchone()
            conn.execute(
                "INSERT INTO deployments (id, service, model_digest, capacity, load, version,"
                " last_seen, alive, draining) VALUES (?,?,?,?,?,?,?,1,0)"
                " ON CONFLICT (id) DO UPDATE SET service=excluded.service,"
                " model_digest=excluded.model_digest, capacity=excluded.capacity,"
                " load=excluded.load, version=excluded.version, last_seen=excluded.last_seen,"
                " alive=1,"
                " draining=CASE WHEN deployments.alive THEN deployments.draining ELSE 0 END",
                (deployment, service, model_digest, capacity, load, version, now),
            )
            if row is None or not row[0]:
                self._event(
                    conn, EventKind.DEPLOYMENT_UP, None, deployment, None, f"service {service}"
                )

    def set_deployment_alive(self, deployment: str, alive: bool, reason: str = "") -> bool:
        """Mark a known deployment alive or gone; returns whether the flag changed."""
        with self._tx() as conn:
            row = conn.execute(
                "SELECT alive FROM deployments WHERE id = ?", (deployment,)
            ).fetchone()
            if row is None or bool(row[0]) == alive:
                return False
            conn.execute(
                "UPDATE deployments SET alive = ?, last_seen = ?, draining = 0 WHERE id = ?",
                (int(alive), self._clock(), deployment),
            )
            kind = EventKind.DEPLOYMENT_UP if alive else EventKind.DEPLOYMENT_DOWN
            self._event(conn, kind, None, deployment, None, reason)
            return True

    def set_deployment_draining(self, deployment: str, reason: str = "") -> bool:
        """Mark a live deployment as draining (planned shutdown); returns whether it changed."""
        with self._tx() as conn:
            row = conn.execute(
                "SELECT alive, draining FROM deployments WHERE id = ?", (deployment,)
            ).fetchone()
            if row is None or not row[0] or row[1]:
                return False
            conn.execute(
                "UPDATE deployments SET draining = 1, last_seen = ? WHERE id = ?",
                (self._clock(), deployment),
            )
            self._event(conn, EventKind.DEPLOYMENT_DRAIN, None, deployment, None, reason)
            return True

    def update_deployment_load(
        self, deployment: str, load: int, capacity: int | None = None
    ) -> None:
        """Record a deployment's reported load (and capacity); refreshes `last_seen`."""
        _check_count("load", load)
        if capacity is not None:
            _check_count("capacity", capacity)
        with self._tx() as conn:
            conn.execute(
                "UPDATE deployments SET load = ?, capacity = COALESCE(?, capacity), last_seen = ?"
                " WHERE id = ?",
                (load, capacity, self._clock(), deployment),
            )

    def update_deployment_loads(self, loads: Mapping[str, tuple[int, int | None]]) -> int:
        """Record reported (load, capacity) pairs (capacity None: unchanged) of the live
        deployments whose values differ, in one transaction; returns how many rows changed."""
        for deployment, (load, capacity) in loads.items():
            _check_count(f"load of {deployment}", load)
            if capacity is not None:
                _check_count(f"capacity of {deployment}", capacity)
        now = self._clock()
        with self._tx() as conn:
            before = conn.total_changes
            conn.executemany(
                "UPDATE deployments SET load = ?, capacity = COALESCE(?, capacity), last_seen = ?"
                " WHERE id = ? AND alive AND (load != ? OR capacity != COALESCE(?, capacity))",
                [
                    (load, capacity, now, deployment, load, capacity)
                    for deployment, (load, capacity) in loads.items()
                ],
            )
            return conn.total_changes - before

    def deployments(self) -> list[RibDeploymentRow]:
        """Every known deployment, by id."""
        return [_deployment_row(r) for r in self._query("SELECT * FROM deployments ORDER BY id")]

    def deployment(self, deployment: str) -> RibDeploymentRow | None:
        """One deployment, or None when unknown."""
        rows = self._query("SELECT * FROM deployments WHERE id = ?", (deployment,))
        return _deployment_row(rows[0]) if rows else None

    # -- robots --------------------------------------------------------------------------------
    def upsert_robot(self, robot: str, *, service: str) -> None:
        """Register (or refresh) a live robot; records `robot_up` when it was not alive."""
        _check_id("robot id", robot)
        _check_id("service", service)
        with self._tx() as conn:
            row = conn.execute("SELECT alive FROM robots WHERE id = ?", (robot,)).fetchone()
            conn.execute(
                "INSERT INTO robots (id, service, alive, last_seen) VALUES (?,?,1,?)"
                " ON CONFLICT (id) DO UPDATE SET service=excluded.service, alive=1,"
                " last_seen=excluded.last_seen",
                (robot, service, self._clock()),
            )
            if row is None or not row[0]:
                self._event(conn, EventKind.ROBOT_UP, robot, None, None, f"service {service}")

    def set_robot_alive(self, robot: str, alive: bool, reason: str = "") -> bool:
        """Mark a known robot alive or gone; returns whether the flag changed."""
        with self._tx() as conn:
            row = conn.execute("SELECT alive FROM robots WHERE id = ?", (robot,)).fetchone()
            if row is None or bool(row[0]) == alive:
                return False
            conn.execute(
                "UPDATE robots SET alive = ?, last_seen = ? WHERE id = ?",
                (int(alive), self._clock(), robot),
            )
            kind = EventKind.ROBOT_UP if alive else EventKind.ROBOT_DOWN
            self._event(conn, kind, robot, None, None, reason)
            return True

    def robots(self) -> list[RibRobotRow]:
        """Every known robot, by id."""
        return [_robot_row(r) for r in self._query("SELECT * FROM robots ORDER BY id")]

    def live_robots(self) -> list[tuple[RibRobotRow, RibRouteRow | None]]:
        """Every live robot with its route (None when it never had one), by robot: what a
        scheduling round reads, in one query rather than two per robot."""
        rows = self._query(
            "SELECT r.id, r.service, r.alive, r.last_seen, t.deployment, t.epoch, t.since, t.pool"
            " FROM robots AS r LEFT JOIN routes AS t ON t.robot = r.id AND t.epoch > 0"
            " WHERE r.alive ORDER BY r.id"
        )
        return [
            (
                _robot_row(r),
                RibRouteRow(r["id"], r["deployment"], r["epoch"], r["since"], _pool(r["pool"]))
                if r["epoch"] is not None
                else None,
            )
            for r in rows
        ]

    def robot(self, robot: str) -> RibRobotRow | None:
        """One robot, or None when unknown."""
        rows = self._query("SELECT * FROM robots WHERE id = ?", (robot,))
        return _robot_row(rows[0]) if rows else None

    def reset_liveness(self) -> None:
        """Mark every deployment and robot as not alive, without events.

        Called at startup: flags from a previous run mean nothing until liveliness confirms them.
        """
        with self._tx() as conn:
            conn.execute("UPDATE deployments SET alive = 0, draining = 0")
            conn.execute("UPDATE robots SET alive = 0")

    # -- deployment states -------------------------------------------------------------------
    def set_deployment_state(
        self, deployment: str, robot: str, state: DeploymentState | str, epoch: int
    ) -> None:
        """Record a deployment's state for a robot (acknowledged or assumed)."""
        state = DeploymentState(state)
        _check_count("epoch", epoch)
        with self._tx() as conn:
            conn.execute(
                "INSERT INTO deployment_states (deployment, robot, state, epoch) VALUES (?,?,?,?)"
                " ON CONFLICT (deployment, robot) DO UPDATE SET state=excluded.state,"
                " epoch=excluded.epoch",
                (deployment, robot, state.value, epoch),
            )
            self._event(conn, EventKind.STATE, robot, deployment, epoch, state.value)

    def deployment_states(
        self, *, robot: str | None = None, deployment: str | None = None
    ) -> list[RibDeploymentStateRow]:
        """States, optionally of one robot or one deployment."""
        where, params = [], []
        if robot is not None:
            where.append("robot = ?")
            params.append(robot)
        if deployment is not None:
            where.append("deployment = ?")
            params.append(deployment)
        clause = f"WHERE {' AND '.join(where)}" if where else ""
        rows = self._query(
            f"SELECT * FROM deployment_states {clause} ORDER BY robot, deployment", params
        )
        return [
            RibDeploymentStateRow(
                deployment=r["deployment"],
                robot=r["robot"],
                state=DeploymentState(r["state"]),
                epoch=r["epoch"],
            )
            for r in rows
        ]

    # -- routes and epochs -----------------------------------------------------------------------
    def reserve_epoch(self, robot: str, at_least: int = 0) -> int:
        """Issue a new epoch for a robot: larger than every epoch issued before, and ≥ `at_least`.

        The issued high-water mark is persisted before any deployment hears of the epoch, so a
        registry that crashes mid-switch never issues the same epoch twice after its restart.
        """
        _check_id("robot id", robot)
        with self._tx() as conn:
            row = conn.execute(
                "SELECT issued_epoch FROM routes WHERE robot = ?", (robot,)
            ).fetchone()
            issued = max((row[0] if row else 0) + 1, at_least)
            if row is None:
                conn.execute(
                    "INSERT INTO routes (robot, deployment, epoch, since, issued_epoch)"
                    " VALUES (?, NULL, 0, ?, ?)",
                    (robot, self._clock(), issued),
                )
            else:
                conn.execute("UPDATE routes SET issued_epoch = ? WHERE robot = ?", (issued, robot))
            return issued

    def set_route(
        self,
        robot: str,
        deployment: str | None,
        epoch: int,
        reason: str = "",
        *,
        pool: Sequence[str] = (),
    ) -> RibRouteRow:
        """Persist a route (None: the robot computes locally) under an epoch from `reserve_epoch`.

        Epochs only grow: an epoch not newer than the current route's is refused. The new
        deployment's state for the robot becomes `service` in the same transaction, and so does
        every member of `pool` (round robin: the deployments serving it, `deployment` first).
        """
        _check_id("robot id", robot)
        _check_count("epoch", epoch)
        if pool and (deployment is None or pool[0] != deployment):
            raise ValueError(f"pool {list(pool)} of robot {robot!r} must start with {deployment}")
        now = self._clock()
        with self._tx() as conn:
            row = conn.execute(
                "SELECT deployment, epoch, issued_epoch FROM routes WHERE robot = ?", (robot,)
            ).fetchone()
            previous, current, issued = (row[0], row[1], row[2]) if row else (None, 0, 0)
            if epoch <= current:
                raise ValueError(
                    f"route epoch {epoch} for robot {robot!r} is not newer than the current"
                    f" {current}"
                )
            conn.execute(
                "INSERT INTO routes (robot, deployment, epoch, since, issued_epoch, pool)"
                " VALUES (?,?,?,?,?,?) ON CONFLICT (robot) DO UPDATE SET"
                " deployment=excluded.deployment, epoch=excluded.epoch, since=excluded.since,"
                " issued_epoch=excluded.issued_epoch, pool=excluded.pool",
                (robot, deployment, epoch, now, max(issued, epoch), json.dumps(list(pool))),
            )
            serving = list(pool) or ([deployment] if deployment is not None else [])
            conn.executemany(
                "INSERT INTO deployment_states (deployment, robot, state, epoch)"
                " VALUES (?,?,'service',?) ON CONFLICT (deployment, robot) DO UPDATE SET"
                " state='service', epoch=excluded.epoch",
                [(member, robot, epoch) for member in serving],
            )
            moved = f"{previous or 'local'} -> {deployment or 'local'}"
            if len(pool) > 1:
                moved += f" (pool {', '.join(pool)})"
            self._event(
                conn,
                EventKind.ROUTE,
                robot,
                deployment,
                epoch,
                f"{reason}: {moved}" if reason else moved,
            )
        return RibRouteRow(
            robot=robot, deployment=deployment, epoch=epoch, since=now, pool=tuple(pool)
        )

    def route(self, robot: str) -> RibRouteRow | None:
        """A robot's route, or None when it never had one (a reserved epoch alone is no route)."""
        rows = self._query("SELECT * FROM routes WHERE robot = ? AND epoch > 0", (robot,))
        return _route_row(rows[0]) if rows else None

    def routes(self) -> list[RibRouteRow]:
        """Every route, by robot."""
        return [
            _route_row(r)
            for r in self._query("SELECT * FROM routes WHERE epoch > 0 ORDER BY robot")
        ]

    def pool(self, robot: str) -> tuple[str, ...]:
        """The deployments of a robot's round-robin pool (empty in an anycast fleet)."""
        route = self.route(robot)
        return route.pool if route is not None else ()

    def issued_epoch(self, robot: str) -> int:
        """The highest epoch ever issued for a robot (0 when none)."""
        rows = self._query("SELECT issued_epoch FROM routes WHERE robot = ?", (robot,))
        return int(rows[0][0]) if rows else 0


def _deployment_row(r: sqlite3.Row) -> RibDeploymentRow:
    return RibDeploymentRow(
        id=r["id"],
        service=r["service"],
        model_digest=r["model_digest"],
        capacity=r["capacity"],
        load=r["load"],
        version=r["version"],
        last_seen=r["last_seen"],
        alive=bool(r["alive"]),
        draining=bool(r["draining"]),
    )


def _robot_row(r: sqlite3.Row) -> RibRobotRow:
    return RibRobotRow(
        id=r["id"], service=r["service"], alive=bool(r["alive"]), last_seen=r["last_seen"]
    )


def _route_row(r: sqlite3.Row) -> RibRouteRow:
    return RibRouteRow(
        robot=r["robot"],
        deployment=r["deployment"],
        epoch=r["epoch"],
        since=r["since"],
        pool=_pool(r["pool"]),
    )


def _pool(text: str) -> tuple[str, ...]:
    """A route's pool column (a JSON list); an anycast fleet's `[]` without parsing (read for
    every live robot in every round)."""
    return () if text == "[]" else tuple(json.loads(text))
