"""The registry's dispatch by service: what reaches the daemon goes to the planes it concerns.

The daemon (`registry.daemon`) has one session, one membership view, one queue and one set of
queryables and subscribers; each service's routing is a plane of its own (`registry.plane`).
`Planes` hands each input to the planes it concerns:

- a membership change: every plane whose service the fleet file gives the machine (a machine
  the file does not name: the first service's, as a peer of a one-service fleet);
- `reg/register`: the plane of `RegisterRequest.service` (a deployment serving several
  services, or a robot using several, registers once per service); a service the fleet does not
  serve, or one the fleet file does not give that machine, is refused by name;
- `reg/reroute`: the plane of `RerouteRequest.service` (None: the first service; an unknown one
  is refused before it is queued, `registry.requests`);
- `reg/drain`: every plane (a whole deployment drains), one reply for all;
- a probe outcome, a robot to evaluate: the plane that asked for it (`service`);
- telemetry, a probe report: the plane of its `service` (read by the daemon);
- `rib/*`: every plane's rows (`registry.views.FleetViews`).

Only the control loop's thread calls `handle`; `reply_to_register` runs on Zenoh's callback
threads (each registrar has its lock).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence

import zenoh

from common import keys
from common.config import FleetConfig
from common.membership import MemberChange
from common.wire import registry as msg
from registry.control_loop import Evaluate, Event
from registry.plane import Plane
from registry.prober import Probed
from registry.replies import answer, decode_query, error_payload, unknown_service
from registry.requests import QueuedRequest, combine_drains, drain
from registry.views import FleetViews

log = logging.getLogger("registry.daemon")  # one logger for the registry's lines


class Planes:
    """`Planes(cfg, planes)`: the fleet's planes (one per service, in the fleet file's order)
    and the dispatch to them."""

    def __init__(
        self, cfg: FleetConfig, planes: Sequence[Plane], *, max_request_bytes: int
    ) -> None:
        if not planes:
            raise ValueError("a registry needs a plane per service, got none")
        self.cfg = cfg
        self.max_request_bytes = max_request_bytes
        self._planes = {plane.service: plane for plane in planes}
        self.first = planes[0]
        self.views = FleetViews(
            cfg.fleet, [p.views for p in planes], max_request_bytes=max_request_bytes
        )

    def __iter__(self) -> Iterator[Plane]:
        return iter(self._planes.values())

    def __len__(self) -> int:
        return len(self._planes)

    @property
    def services(self) -> list[str]:
        """The services routed, the first first."""
        return list(self._planes)

    def get(self, service: str | None) -> Plane:
        """The plane of `service` (None: the first service's); `UnknownService` otherwise."""
        if service is None:
            return self.first
        plane = self._planes.get(service)
        if plane is None:
            raise unknown_service(service, self._planes)
        return plane

    def holding(self, machine: str) -> list[Plane]:
        """The planes routing for `machine`: those of the services the fleet file gives it, or
        the first service's for a machine the file does not name."""
        if machine not in self.cfg.machines:
            return [self.first]
        return [plane for plane in self if plane.holds(machine)]

    # -- the control loop's events ---------------------------------------------------------------
    def handle(self, event: Event) -> None:
        """Hand one queued event to the planes it concerns (control loop only)."""
        if isinstance(event, MemberChange):
            for plane in self.holding(event.id):
                plane.loop.handle(event)
        elif isinstance(event, (Probed, Evaluate)):
            self.get(event.service).loop.handle(event)
        elif isinstance(event.message, msg.DrainRequest):
            self._drain(event)
        else:
            assert isinstance(event.message, msg.RerouteRequest)
            self._reroute(event)

    def _reroute(self, event: QueuedRequest) -> None:
        assert isinstance(event.message, msg.RerouteRequest)
        service = event.message.service
        if service is not None and service not in self._planes:
            # Refused when queued already; a queue filled by someone else is refused here.
            answer(event.query, (event.key, error_payload(unknown_service(service, self._planes))))
            return
        self.get(service).loop.handle(event)

    def _drain(self, event: QueuedRequest) -> None:
        """A deployment drains from every service it serves: each plane moves its robots off it,
        one reply tells them all (`registry.requests.combine_drains`)."""
        request = event.message
        assert isinstance(request, msg.DrainRequest)
        try:
            replies = [
                (p.service, drain(request, p.rib, p.registrar, p.loop.evaluate)) for p in self
            ]
            payload = combine_drains(replies).to_wire()
        except Exception as exc:
            self.first.loop.throttled.error(
                "registry: unexpected error in %s", event.key, exc_info=True
            )
            payload = error_payload(exc)
        answer(event.query, (event.key, payload))

    # -- reg/register ------------------------------------------------------------------------------
    def answer_register(self, query: zenoh.Query) -> None:
        """Serve `reg/register` on Zenoh's callback thread (a WireError for a bad request, which
        the caller answers)."""
        request = decode_query(query, msg.RegisterRequest, max_bytes=self.max_request_bytes)
        reply = self.reply_to_register(request)
        answer(query, (keys.reg_register(self.cfg.fleet), reply.to_wire()))

    def reply_to_register(self, request: msg.RegisterRequest) -> msg.RegisterReply:
        """The plane of the request's service answers it; a service the fleet does not serve,
        or one the fleet file does not give that machine, is refused by name (and recorded)."""
        who = f"{request.role} {request.id!r}"
        plane = self._planes.get(request.service)
        if plane is None:
            known = ", ".join(repr(s) for s in self._planes)
            return self.first.registrar.refuse_service(
                request, f"{who} serves {request.service!r}, this fleet serves {known}"
            )
        if request.id in self.cfg.machines and not plane.holds(request.id):
            given = ", ".join(self.cfg.services_of(request.id)) or "none"
            return plane.registrar.refuse_service(
                request,
                f"{who} asks for service {request.service!r}, which the fleet file does not "
                f"give it (its services: {given})",
            )
        return plane.registrar.reply_to(request)
