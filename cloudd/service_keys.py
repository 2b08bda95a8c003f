"""The robots' service keys on one deployment: declared when the registry puts a robot in service.

For each robot in service the deployment declares two queryables (complete=True): the robot's
anycast service key `svc/<service>/<robot>/infer`, which a robot of an anycast fleet queries, and
this deployment's pool member key `svc/<service>/<robot>/infer/<deployment>`, to which a robot in
a round-robin pool sends each frame. Both go to the admission (`cloudd.admission`) through the
daemon's `guarded` wrapper, so an unexpected error is answered INTERNAL. The `RobotBook` holds
what is declared; at shutdown every key is undeclared, a failure logged and the others still
undeclared.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import zenoh

from cloudd.admission import Admission
from cloudd.robot_book import RobotBook, ServiceQueryables
from common import keys

log = logging.getLogger(__name__)

# Wraps a query handler for one key as a Zenoh callback (the daemon's `guarded`).
Guard = Callable[[Callable[[zenoh.Query], None], str], Callable[[zenoh.Query], None]]


class ServiceKeys:
    """Declares and undeclares the service keys of robots in service (see the module
    docstring)."""

    def __init__(self, fleet: str, service: str, deployment: str, book: RobotBook) -> None:
        self._fleet = fleet
        self._service = service
        self._deployment = deployment
        self._book = book

    def declare(
        self,
        robot: str,
        session: zenoh.Session,
        admission: Admission,
        guard: Guard,
    ) -> None:
        """Declare `robot`'s service key and this deployment's pool member key for it, each
        query handed to `admission` through `guard(handler, key)`; replaces (and undeclares)
        what the robot had."""
        declared: list[zenoh.Queryable[None]] = []
        try:
            for key in (
                keys.svc_infer(self._fleet, self._service, robot),
                keys.svc_infer_at(self._fleet, self._service, robot, self._deployment),
            ):
                handler = guard(functools.partial(admission.on_query, robot, key), key)
                declared.append(session.declare_queryable(key, handler, complete=True))
        except zenoh.ZError:
            ServiceQueryables(tuple(declared)).undeclare()
            raise
        old = self._book.put_service(robot, ServiceQueryables(tuple(declared)))
        if old is not None:
            old.undeclare()

    def undeclare_all(self) -> None:
        """Undeclare every robot's keys (at shutdown); a failure is logged, the others go on."""
        for queryable in self._book.take_services():
            try:
                queryable.undeclare()
            except zenoh.ZError as exc:  # keep undeclaring the others
                log.warning("%s: undeclaring a service key failed: %s", self._deployment, exc)
