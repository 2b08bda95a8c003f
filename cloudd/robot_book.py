"""A cloud daemon's book of its robots: states and epochs, frames served, declared service keys.

`cloudd.state.StateTable` decides; this class keeps its table together with what the daemon
counts per robot and the robots' service queryables, all under one lock, so a control request's
verdict and the service key it frees are taken in one step (two requests for one robot cannot
each take the other's key). The daemon's `closing` event is set under the same lock
(`close`): once shutdown has collected the service keys (`take_services`), no control request
takes a robot into service any more.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from dataclasses import dataclass

import zenoh

from cloudd.state import RobotServiceState, StateTable, Verdict
from common.wire.registry import CtlOp

STOPPING_REASON = "this deployment is stopping"


@dataclass(frozen=True)
class ServiceQueryables:
    """The queryables a robot in service has here: its anycast service key and this deployment's
    pool member key (`common.keys.svc_infer_at`), declared and undeclared together."""

    queryables: tuple[zenoh.Queryable[None], ...]

    def undeclare(self) -> None:
        """Undeclare every one; the first failure is raised after the others were tried."""
        failure: zenoh.ZError | None = None
        for queryable in self.queryables:
            try:
                queryable.undeclare()
            except zenoh.ZError as exc:
                failure = failure or exc
        if failure is not None:
            raise failure


@dataclass(frozen=True)
class CtlDecision:
    """A verdict on a service or standby request, and what carrying it out needs: the robot's
    service key to undeclare before the ack (`undeclare`), or none. `stopping`: refused
    because the daemon is shutting down (not a disagreement worth a log line)."""

    verdict: Verdict
    undeclare: ServiceQueryables | None = None
    stopping: bool = False


class RobotBook:
    """Per-robot state, frames served and service keys of one deployment (thread-safe)."""

    def __init__(self, robots: Iterable[str], closing: threading.Event) -> None:
        self._lock = threading.Lock()
        self._closing = closing
        self._states = StateTable(robots)
        self._served: dict[str, int] = {}
        self._unanswered: set[str] = set()  # robots in service not answered since they entered
        self._services: dict[str, ServiceQueryables] = {}

    # -- views -----------------------------------------------------------------------------
    def states(self) -> dict[str, RobotServiceState]:
        """Every known robot's state and epoch here."""
        with self._lock:
            return self._states.snapshot()

    def served(self) -> dict[str, int]:
        """Frames computed and answered, per robot."""
        with self._lock:
            return dict(self._served)

    def snapshot(self) -> tuple[dict[str, RobotServiceState], dict[str, int]]:
        """States and frames served, read together."""
        with self._lock:
            return self._states.snapshot(), dict(self._served)

    def serving(self, robot: str) -> bool:
        """Whether a request of `robot` is served now (in service or draining, not stopping)."""
        with self._lock:
            return self._states.get(robot).serving and not self._closing.is_set()

    def wire_epoch(self, robot: str) -> int:
        """The robot's epoch as replies carry it."""
        with self._lock:
            return self._states.get(robot).wire_epoch

    def serving_robots(self) -> list[str]:
        """Robots whose service key is declared here."""
        with self._lock:
            return self._states.serving_robots()

    # -- control ---------------------------------------------------------------------------
    def decide(self, op: CtlOp, robot: str, epoch: int) -> CtlDecision:
        """Decide `op(robot, epoch)` (service or standby) and apply an accepted verdict."""
        with self._lock:
            if self._closing.is_set():
                current = self._states.get(robot)
                refused = Verdict(False, robot, current, current, STOPPING_REASON)
                return CtlDecision(refused, stopping=True)
            if op is CtlOp.SERVICE:
                verdict = self._states.decide_service(robot, epoch)
            else:
                verdict = self._states.decide_standby(robot, epoch)
            self._states.apply(verdict)
            undeclare = self._services.pop(robot, None) if verdict.undeclare else None
            if verdict.declare:
                self._unanswered.add(robot)
        return CtlDecision(verdict, undeclare)

    def restore(self, verdict: Verdict) -> None:
        """Undo an applied verdict (its service key could not be declared)."""
        with self._lock:
            self._states.restore(verdict)

    def drain_robot(self, robot: str) -> RobotServiceState:
        """Mark one robot draining if it is in service; its state afterwards."""
        with self._lock:
            return self._states.drain_robot(robot)

    def drain_all(self) -> list[str]:
        """Refuse new robots, mark the served ones draining; returns those."""
        with self._lock:
            return self._states.drain_all()

    # -- service keys ----------------------------------------------------------------------
    def put_service(self, robot: str, queryables: ServiceQueryables) -> ServiceQueryables | None:
        """Keep `robot`'s newly declared service queryables; returns those they replace."""
        with self._lock:
            old = self._services.pop(robot, None)
            self._services[robot] = queryables
        return old

    def take_services(self) -> list[ServiceQueryables]:
        """Every robot's service queryables, forgotten here (to undeclare them)."""
        with self._lock:
            services = list(self._services.values())
            self._services.clear()
        return services

    # -- lifecycle and counting ------------------------------------------------------------
    def close(self) -> None:
        """Set the daemon's `closing` event under the lock (see the module docstring)."""
        with self._lock:
            self._closing.set()

    def count_served(self, robot: str) -> bool:
        """Count one frame answered for `robot`; True if it is its first since it entered
        service."""
        with self._lock:
            self._served[robot] = self._served.get(robot, 0) + 1
            first = robot in self._unanswered
            self._unanswered.discard(robot)
        return first
