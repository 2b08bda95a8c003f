"""The RIB's events table: every transition, with its reason, kept for inspection.

`RibEvents` is the part of `registry.rib.Rib` that appends to and reads the `events` table (the
newest `EVENTS_KEEP` rows are kept: older ones are pruned every `EVENTS_PRUNE_EVERY` inserts), on
the store's one connection; the RIB's writes record their event inside their own transaction
(`_event`).
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from registry.rib_profiles import RibProfiles

# Events are kept for inspection, not forever: older rows are pruned past this count.
EVENTS_KEEP = 10_000
EVENTS_PRUNE_EVERY = 500
DEFAULT_EVENTS_LIMIT = 100


class EventKind(str, Enum):
    """What an event row records."""

    DEPLOYMENT_UP = "deployment_up"
    DEPLOYMENT_DOWN = "deployment_down"
    DEPLOYMENT_DRAIN = "deployment_drain"
    ROBOT_UP = "robot_up"
    ROBOT_DOWN = "robot_down"
    ROUTE = "route"
    STATE = "state"
    ACK_FAILED = "ack_failed"
    STANDBY_FAILED = "standby_failed"
    PUBLISH_FAILED = "publish_failed"
    SWITCH_FAILED = "switch_failed"
    EPOCH_RAISED = "epoch_raised"
    REGISTRATION_REFUSED = "registration_refused"


@dataclass(frozen=True)
class RibEventRow:
    """One recorded transition."""

    seq: int
    ts: float
    kind: str
    robot: str | None
    deployment: str | None
    epoch: int | None
    reason: str

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a JSON view."""
        return asdict(self)


class RibEvents(RibProfiles):
    """The events table of the RIB (see the module docstring)."""

    def __init__(self, path: str | Path, *, clock: Callable[[], float] = time.time) -> None:
        self._inserts_since_prune = 0
        super().__init__(path, clock=clock)

    def _event(
        self,
        conn: sqlite3.Connection,
        kind: EventKind | str,
        robot: str | None,
        deployment: str | None,
        epoch: int | None,
        reason: str,
    ) -> None:
        kind_s = kind.value if isinstance(kind, EventKind) else str(kind)
        conn.execute(
            "INSERT INTO events (ts, kind, robot, deployment, epoch, reason) VALUES (?,?,?,?,?,?)",
            (self._clock(), kind_s, robot, deployment, epoch, reason),
        )
        self._inserts_since_prune += 1
        if self._inserts_since_prune >= EVENTS_PRUNE_EVERY:
            self._inserts_since_prune = 0
            conn.execute(
                "DELETE FROM events WHERE seq <= (SELECT MAX(seq) FROM events) - ?", (EVENTS_KEEP,)
            )

    # -- events --------------------------------------------------------------------------------
    def record_event(
        self,
        kind: EventKind | str,
        *,
        robot: str | None = None,
        deployment: str | None = None,
        epoch: int | None = None,
        reason: str = "",
    ) -> None:
        """Append one event."""
        with self._tx() as conn:
            self._event(conn, kind, robot, deployment, epoch, reason)

    def events(
        self,
        limit: int = DEFAULT_EVENTS_LIMIT,
        *,
        robot: str | None = None,
        kind: str | None = None,
    ) -> list[RibEventRow]:
        """The newest `limit` events (optionally of one robot or kind), oldest first."""
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"events limit must be an integer >= 1, got {limit!r}")
        where, params = [], []
        if robot is not None:
            where.append("robot = ?")
            params.append(robot)
        if kind is not None:
            where.append("kind = ?")
            params.append(str(getattr(kind, "value", kind)))
        clause = f"WHERE {' AND '.join(where)}" if where else ""
        rows = self._query(
            f"SELECT * FROM events {clause} ORDER BY seq DESC LIMIT ?", [*params, limit]
        )
        return [
            RibEventRow(
                seq=r["seq"],
                ts=r["ts"],
                kind=r["kind"],
                robot=r["robot"],
                deployment=r["deployment"],
                epoch=r["epoch"],
                reason=r["reason"],
            )
            for r in reversed(rows)
        ]
