"""A deployment's planes, one per service it serves, and the dispatch of its one probe key and
one ctl key to them.

A probe or ctl request names its service (`ProbeRequest.service`, `CtlRequest.service`; none,
or an empty probe: the fleet's first service, what a peer of a one-service fleet means). The
plane of that service answers it; a service the fleet lacks, or one this deployment does not
serve, gets a named `unknown_service` error reply listing the services served here, is counted
(`cloudd.refusals`) and logged through the throttle, and the daemon keeps serving.
"""

from __future__ import annotations

from collections.abc import Iterator

from cloudd.plane import DeploymentParts, ServicePlane
from cloudd.refusals import RefusalReason
from common.config import FleetConfig
from common.errors import UserError
from common.wire import ErrorCode, ErrorReply
from common.wire.registry import CtlReply, CtlRequest, ProbeReply


class Planes:
    """The planes of deployment `parts.deployment`, in the fleet file's order of services."""

    def __init__(self, cfg: FleetConfig, parts: DeploymentParts) -> None:
        self._cfg = cfg
        self._parts = parts
        names = cfg.services_of(parts.deployment)
        if not names:
            raise UserError(
                f"cloud {parts.deployment!r} serves no service (machines.{parts.deployment}."
                f"services is empty); services: {', '.join(cfg.services)}"
            )
        several = len(names) > 1
        self._planes = {
            name: ServicePlane(
                cfg.for_service(name),
                parts,
                who=f"{parts.deployment} ({name})" if several else parts.deployment,
            )
            for name in names
        }

    def __iter__(self) -> Iterator[ServicePlane]:
        return iter(self._planes.values())

    def __len__(self) -> int:
        return len(self._planes)

    @property
    def first(self) -> ServicePlane:
        """The plane of the first service served here."""
        return next(iter(self._planes.values()))

    @property
    def names(self) -> list[str]:
        """The services served here, in file order."""
        return list(self._planes)

    def plane(self, service: str | None = None) -> ServicePlane:
        """The plane of `service` (None: the first served here); UserError naming the services
        served here when there is none. Requests go through `get` instead."""
        if service is None:
            return self.first
        found = self._find(service)
        if isinstance(found, str):
            raise UserError(found)
        return found

    def get(self, service: str | None) -> ServicePlane | ErrorReply:
        """The plane a request naming `service` goes to (None: the fleet's first service), or
        the named refusal to answer it with (counted and logged)."""
        found = self._find(service)
        if isinstance(found, ServicePlane):
            return found
        parts = self._parts
        parts.refusals.count(RefusalReason.UNKNOWN_SERVICE)
        parts.throttled.warning("%s: refused a request: %s", parts.deployment, found)
        return ErrorReply.make(ErrorCode.UNKNOWN_SERVICE, found)

    def _find(self, service: str | None) -> ServicePlane | str:
        """The plane of `service`, or why there is none."""
        deployment = self._parts.deployment
        served = ", ".join(self._planes)
        try:
            name = self._cfg.service_for(service)
        except UserError as exc:
            return f"{exc}; {deployment} serves {served}"
        plane = self._planes.get(name)
        if plane is None:
            return f"{deployment} does not serve {name!r}; it serves {served}"
        return plane

    # -- the probe and ctl keys' dispatch --------------------------------------------------
    def profile(self, service: str | None, echo_bytes: int = 0) -> ProbeReply | ErrorReply:
        """The profile of the service a probe names, or the refusal."""
        plane = self.get(service)
        return plane if isinstance(plane, ErrorReply) else plane.profile(echo_bytes)

    def control(self, request: CtlRequest) -> CtlReply | ErrorReply:
        """Carry out a ctl request on the service it names, or refuse it."""
        plane = self.get(request.service)
        return plane if isinstance(plane, ErrorReply) else plane.control(request)

    # -- the daemon's bookkeeping ----------------------------------------------------------
    def close(self) -> None:
        """Refuse new work in every plane (`RobotBook.close`)."""
        for plane in self:
            plane.book.close()

    def drain_all(self) -> list[str]:
        """Mark the robots in service of every plane draining; those, named by service when
        the deployment serves several."""
        return [self._label(plane, robot) for plane in self for robot in plane.book.drain_all()]

    def serving(self) -> list[str]:
        """The robots still served (service or draining), named like `drain_all`'s."""
        return [
            self._label(plane, robot) for plane in self for robot in plane.book.serving_robots()
        ]

    def _label(self, plane: ServicePlane, robot: str) -> str:
        return robot if len(self._planes) == 1 else f"{robot} ({plane.name})"
