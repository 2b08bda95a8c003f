"""The registry daemon: the RIB, the scheduler and the switch protocol wired to Zenoh.

Services. Routing is per (robot, service): the daemon runs one plane per service of the fleet
(`registry.plane`: the single-service registry's parts, built from the service's view of the
fleet) and dispatches to them (`registry.planes`); a one-service fleet has one plane. Each plane
has a RIB file of its own: the first service keeps `registry.db` itself, another service
`<stem>.<service><suffix>` beside it.

Lifecycle (`common.daemon.Daemon`: startup -> main loop -> shutdown, in reverse order):

1. Open each service's RIB (routes, epochs and profiles come back from sqlite; liveness flags
   are reset) and restore its measurements from it; they are saved again just before it closes.
2. Open the session: a router listening on `registry.listen`, so a fresh host needs nothing
   else (data never flows through it: peers link to each other directly), or a peer of the
   router at `registry.endpoint`.
3. Start each service's prober pool and build its plane. (At shutdown, once the queryables are
   gone, requests still queued for the control loop are refused rather than left to time out.)
4. Declare the queryables (`rib/*`, `reg/register`, `reg/reroute`, `reg/drain`) and the
   subscribers (telemetry, probe reports).
5. Follow membership with a `common.membership.MembershipView` (a liveliness subscriber with
   history, seeded by a liveliness get): every cloud and robot token, those older than the
   registry included, and the end of each.
6. Announce `alive/registry/<id>`: from now on it serves.

Each step hands what it made to the lifecycle (`hold`, `on_release`, `announce`), which releases
it all at shutdown in reverse order, the token first, also after a failed startup.

Threads. Every Zenoh callback is `guarded` and short: membership changes, drain and reroute
requests (`registry.requests`) are queued for the control loop; telemetry and probe reports
(read by `registry.publications`) only update their service's measurements
(`registry.measurements`, under their own lock); the read-only views (`registry.views`) and
`reg/register` are answered on the callback thread. Probing deployments (registration, and a load
refresh every few seconds) runs on each prober's pool (`registry.prober`), which queues each
outcome. The control loop (the main thread) is the only one that decides and switches: it hands
queued events to the planes at once and runs every plane's scheduler every `tick_s` (~100 ms).

Decisions are `registry.control_loop.ControlLoop`'s, one per service (what a robot's route
becomes, when, and how it is carried out); the daemon makes the planes at startup, feeds them
and ticks them.

Registration (`registry.registration`). A new cloud token is probed and its reply checked; a
mismatch is refused with an event and a log line naming the deployment and the reason, and
nothing is ever routed to it. A deployment found serving a robot that the RIB routes elsewhere is
put back in standby (anycast repair).

Bad input to any queryable (garbage, an unknown schema version, a wrong message type, a malformed
request, a payload over `registry.max_request_bytes`, a service the fleet does not serve) gets an
`ErrorReply` naming the problem and one throttled warning (`reg/register` answers a refusal
naming the services); a bad publication is a throttled warning and dropped. Both are counted by
input and error code (`registry.refusals`, logged at shutdown). The daemon keeps serving either
way.
"""

from __future__ import annotations

import functools
import gc
import logging
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from common import keys
from common.config import FleetConfig
from common.daemon import Daemon
from common.file_safety import check_private_file
from common.keys import Role
from common.membership import MemberChange, MembershipView
from common.metrics import MetricsEndpoint, serve
from common.session import open_session
from common.wire.telemetry import ProbeReport, TelemetryRecord
from registry.control_loop import Evaluate, Event
from registry.measurements import Measurements
from registry.metrics import RegistryMetrics
from registry.plane import (
    Plane,
    build_plane,
    latency_bound,
    plane_db_path,
    plane_measurements,
)
from registry.planes import Planes
from registry.prober import RegistryProber
from registry.profile_saver import PacedSaver
from registry.publications import PublicationReader
from registry.refusals import Refusals
from registry.replies import UnknownService, answer_error
from registry.requests import (
    RequestQueue,
    refuse_queued,
)
from registry.rib import MEMORY, Rib
from registry.scheduler import SchedulerParams
from registry.switch import CTL_TIMEOUT_S
from registry.transport import ZenohTransport

log = logging.getLogger(__name__)

SCHEDULER_TICK_S = 0.1
PROFILE_SAVE_INTERVAL_S = 5.0
LOAD_REFRESH_INTERVAL_S = 2.0
# Peers retry their connection to a restarted router with a back-off of up to 4 s (zenoh's
# default): until then a restored route's deployment is "not seen yet", not "lost".
RESTORE_GRACE_S = 5.0
# How long the membership's seeding get waits for replies (it returns earlier once every peer
# answered; tokens it misses still come through the subscriber's history).
MEMBERSHIP_SEED_TIMEOUT_S = 0.5
# Net allocations of container objects between two collections of the youngest generation
# (Python's default: 700). A scheduling round at 1,000 robots holds thousands of short-lived
# objects at once (rows, views, candidates); collected every 700, the round's own working set
# was promoted to the oldest generation and triggered full passes over the half-million
# long-lived objects of the latency windows, up to 0.2 s each, 7 in 20 s (docs/scale.md). At
# 50,000 the round's objects are freed by their reference counts before a collection sees them.
GC_YOUNG_THRESHOLD = 50_000


def tune_collector() -> None:
    """Collect the youngest generation every GC_YOUNG_THRESHOLD allocations, not fewer (a higher
    threshold set by whoever embeds the registry is kept); the older generations as they were."""
    young, older, oldest = gc.get_threshold()
    gc.set_threshold(max(young, GC_YOUNG_THRESHOLD), older, oldest)


@dataclass(frozen=True)
class _Started:
    """What startup made that the callbacks and the control loop use."""

    session: zenoh.Session
    planes: Planes


class RegistryDaemon(Daemon):
    """`elasticfog registry`: see the module docstring."""

    name = "registry"

    def __init__(
        self,
        cfg: FleetConfig,
        *,
        db_path: str | Path | None = None,
        params: SchedulerParams | None = None,
        tick_s: float = SCHEDULER_TICK_S,
        ctl_timeout_s: float = CTL_TIMEOUT_S,
        restore_grace_s: float = RESTORE_GRACE_S,
        profile_save_interval_s: float = PROFILE_SAVE_INTERVAL_S,
        load_refresh_interval_s: float = LOAD_REFRESH_INTERVAL_S,
        metrics_port: int | None = None,
    ) -> None:
        super().__init__()
        tune_collector()
        self.cfg = cfg
        self.fleet = cfg.fleet
        self.id = cfg.registry.id
        self.service = cfg.service_name
        # Each service's view of the fleet, in the file's order: a plane each at startup.
        self.services = {name: cfg.for_service(name) for name in cfg.services}
        self.db_path = Path(db_path) if db_path is not None else cfg.db_path
        self.bound = latency_bound(self.services[self.service])  # the first service's
        self.params = params if params is not None else SchedulerParams()
        self.tick_s = tick_s
        self.ctl_timeout_s = ctl_timeout_s
        self.restore_grace_s = restore_grace_s
        self.profile_save_interval_s = profile_save_interval_s
        self.load_refresh_interval_s = load_refresh_interval_s
        self.max_request_bytes = cfg.registry.max_request_bytes
        # Error replies and dropped publications, by input and code (Zenoh threads count).
        self.refusals = Refusals()

        self._events: queue.Queue[Event] = queue.Queue()
        services = list(self.services)
        self._publications = PublicationReader(
            self.refusals, self._bad_input, max_bytes=self.max_request_bytes, services=services
        )
        self._requests = RequestQueue(
            self.fleet,
            self._events.put,
            max_request_bytes=self.max_request_bytes,
            services=services,
        )
        self._started: _Started | None = None  # made in startup, dropped after shutdown
        # `/metrics` (`registry.metrics`): off (counts nothing) unless a port is set.
        self._metrics_port = metrics_port
        self.metrics = RegistryMetrics(None)
        self.metrics_endpoint: MetricsEndpoint | None = None

    # -- what startup made ---------------------------------------------------------------------
    @property
    def _parts(self) -> _Started:
        """The started parts (RuntimeError before startup and after shutdown)."""
        if self._started is None:
            raise RuntimeError("the registry is not started")
        return self._started

    @property
    def planes(self) -> Planes | None:
        """Each service's plane while the daemon runs, else None."""
        return self._started.planes if self._started is not None else None

    @property
    def rib(self) -> Rib | None:
        """The first service's RIB (a one-service fleet's only one) while the daemon runs, else
        None."""
        return self._started.planes.first.rib if self._started is not None else None

    @property
    def session(self) -> zenoh.Session | None:
        """The Zenoh session while the daemon runs, else None."""
        return self._started.session if self._started is not None else None

    # -- lifecycle -----------------------------------------------------------------------------
    def startup(self) -> None:
        """Open the RIBs and the session, build the planes, declare everything, follow
        membership, then go live."""
        started_at = time.monotonic()
        cfg, fleet = self.cfg, self.fleet
        ribs = {name: self._open_rib(name) for name in self.services}
        # Served while the RIBs are open: released before they close.
        self.metrics_endpoint = serve(
            self, cfg.registry.metrics, self._metrics_port, who=f"registry {self.id}"
        )
        if self.metrics_endpoint is not None:
            self.metrics = RegistryMetrics(
                self.metrics_endpoint.registry, self._open_ribs, services=list(self.services)
            )
        measured = {name: self._restore(name, rib) for name, rib in ribs.items()}
        if cfg.registry.embedded_router:
            session = self.hold(open_session(cfg, router=True), "zenoh session")
            where = ", ".join(cfg.registry.listen)
        else:
            # A peer of someone else's router: in a TLS fleet it still presents its own certificate.
            session = self.hold(open_session(cfg, identity=self.id), "zenoh session")
            where = f"the router at {cfg.registry.endpoint}"
        transport = ZenohTransport(session, fleet)
        planes: list[Plane] = []
        for name, view in self.services.items():
            prober = RegistryProber(
                transport, self.id, self._events.put, self.closing, service=name
            )
            self.on_release(prober.close, what=self._of("probe pool", name))
            planes.append(
                build_plane(
                    view,
                    ribs[name],
                    measured[name],
                    transport=transport,
                    prober=prober,
                    sender=self.id,
                    params=self.params,
                    ctl_timeout_s=self.ctl_timeout_s,
                    throttled=self.throttled,
                    started_at=started_at,
                    restore_grace_s=self.restore_grace_s,
                    metrics=self.metrics,
                    max_request_bytes=self.max_request_bytes,
                )
            )
        # After the queryables are gone: what they queued gets a refusal instead of a timeout.
        self.on_release(refuse_queued, self._events, what="queued requests")
        self._started = _Started(
            session=session,
            planes=Planes(cfg, planes, max_request_bytes=self.max_request_bytes),
        )
        self._declare(session)
        self.hold(
            MembershipView(
                session,
                fleet,
                roles=[role.value for role in Role],
                on_change=self.guarded(self._on_member, what="a membership change"),
                seed_timeout_s=MEMBERSHIP_SEED_TIMEOUT_S,
            ),
            "membership view",
        )
        self.announce(session.liveliness().declare_token(keys.alive_registry(fleet, self.id)))
        for plane in planes:
            log.info(
                "registry %s of fleet %s: listening on %s, RIB %s (%d routes restored%s)",
                self.id,
                fleet,
                where,
                plane_db_path(self.db_path, plane.service, first=plane is planes[0]),
                plane.measurements.routes_known(),
                f", service {plane.service}" if len(planes) > 1 else "",
            )

    def _of(self, what: str, service: str) -> str:
        """`what` of one service, named when the fleet has several."""
        return f"{what} of service {service}" if len(self.services) > 1 else what

    def _open_rib(self, service: str) -> Rib:
        """Open a service's RIB (its own file beside the first service's), liveness reset."""
        path = plane_db_path(self.db_path, service, first=service == self.service)
        if str(path) != MEMORY:
            check_private_file(Path(path), "RIB file")  # refuse a world-writable RIB
        rib = self.hold(Rib(path), self._of("RIB", service))
        rib.reset_liveness()
        return rib

    def _restore(self, service: str, rib: Rib) -> Measurements:
        """A service's measurements restored from its RIB, saved back just before it closes
        (by then the session is closed and nothing measures)."""
        measurements = plane_measurements(self.services[service], self.params, self._bad_input)
        measurements.restore(rib)
        self.on_release(measurements.save, rib, what=self._of("latency profiles", service))
        self.on_release(measurements.flush_loads, rib, what=self._of("deployment loads", service))
        return measurements

    def _open_ribs(self) -> dict[str, Rib]:
        """Each service's RIB while the daemon runs (empty otherwise): for the metrics."""
        planes = self.planes
        return {p.service: p.rib for p in planes} if planes is not None else {}

    def _declare(self, session: zenoh.Session) -> None:
        """The queryables and subscribers, each guarded and held."""
        fleet = self.fleet
        planes = self._parts.planes
        # (input name for the refusal counts, key, handler, where an error reply goes)
        queryables: list[tuple[str, str, Callable[[zenoh.Query], None], Callable[..., str]]] = [
            ("rib", keys.rib_all(fleet), planes.views.answer, planes.views.reply_key),
            (
                "register",
                keys.reg_register(fleet),
                planes.answer_register,
                lambda _q: keys.reg_register(fleet),
            ),
            (
                "reroute",
                keys.reg_reroute(fleet),
                self._requests.on_reroute,
                lambda _q: keys.reg_reroute(fleet),
            ),
            (
                "drain",
                keys.reg_drain(fleet),
                self._requests.on_drain,
                lambda _q: keys.reg_drain(fleet),
            ),
        ]
        for name, key, handler, reply_key in queryables:
            callback = self.guarded(
                handler,
                what=f"a query on {key}",
                on_error=functools.partial(answer_error, self.refusals, name, reply_key),
                drop_when_closing=True,
            )
            self.hold(session.declare_queryable(key, callback), f"queryable {key}")
        subscribers: list[tuple[str, Callable[[zenoh.Sample], None]]] = [
            (keys.tele_all(fleet), self._on_telemetry),
            (keys.tele_probe_all(fleet), self._on_probe_report),
        ]
        for key, on_sample in subscribers:
            follow = self.guarded(on_sample, what=f"a sample on {key}", drop_when_closing=True)
            self.hold(session.declare_subscriber(key, follow), f"subscriber {key}")

    def main_loop(self) -> None:
        """The control loops (`registry.control_loop`, one per service): queued events at once,
        every service's scheduler every tick, the load refresh and the paced profile save on
        their intervals."""
        planes = self._parts.planes
        now = time.monotonic()
        next_tick = now
        next_refresh = now + self.load_refresh_interval_s
        savers = [
            PacedSaver(
                plane.measurements,
                plane.rib,
                tick_s=self.tick_s,
                interval_s=max(self.tick_s, self.profile_save_interval_s),
            )
            for plane in planes
        ]
        while not self.should_exit.is_set():
            wait_s = min(self.tick_s, max(0.0, next_tick - time.monotonic()))
            try:
                event: Event | None = self._events.get(timeout=wait_s)
            except queue.Empty:
                event = None
            if event is not None:
                self._safely(planes.handle, event)
            now = time.monotonic()
            if now >= next_tick:
                for plane in planes:
                    self._safely(plane.loop.schedule_all)
                self.metrics.round(time.monotonic() - now)
                for saver in savers:
                    self._safely(saver.tick, now)
                next_tick = now + self.tick_s
            if now >= next_refresh:
                for plane in planes:
                    self._safely(plane.loop.refresh_deployments)
                next_refresh = now + self.load_refresh_interval_s

    def shutdown(self) -> None:
        """Token first, then everything startup made in reverse: the membership view, the
        queryables and subscribers, queued requests (refused), the probers, the session, the
        measurements (saved), the RIBs. Safe twice."""
        super().shutdown()
        self._started = None
        refused = self.refusals.summary()
        if refused:
            log.info("registry %s refused (input, code, count): %s", self.id, refused)
        log.info("registry %s stopped", self.id)

    # -- callbacks (Zenoh threads: short, never a decision) --------------------------------------
    def _on_member(self, change: MemberChange) -> None:
        """The membership view's news (under its lock): queued for the control loop."""
        if Role(change.role) is Role.REGISTRY:
            if change.id != self.id and change.alive:
                log.warning("another registry (%s) is alive in fleet %s", change.id, self.fleet)
            return
        self._events.put(change)

    def _on_telemetry(self, sample: zenoh.Sample) -> None:
        rec = self._publications.read(sample, TelemetryRecord, "telemetry")
        plane = self._plane_of(rec)
        if (
            rec is not None
            and plane is not None
            and plane.measurements.record_telemetry(rec, str(sample.key_expr))
        ):
            self._events.put(Evaluate(rec.robot, plane.service))

    def _on_probe_report(self, sample: zenoh.Sample) -> None:
        self.metrics.probe_report()
        rep = self._publications.read(sample, ProbeReport, "probe report")
        plane = self._plane_of(rep)
        if rep is not None and plane is not None:
            plane.measurements.record_probe_report(rep, str(sample.key_expr))

    def _plane_of(self, message: TelemetryRecord | ProbeReport | None) -> Plane | None:
        """The plane a robot's publication is about (its service checked when read), or None
        (none read, or stopped meanwhile)."""
        planes = self.planes
        if message is None or planes is None:
            return None
        try:
            return planes.get(message.service)
        except UnknownService:
            return None

    def _bad_input(self, where: str, problem: str) -> None:
        """A dropped publication or sample: one throttled warning, so a misbehaving publisher
        cannot flood the log."""
        self.throttled.warning("ignored bad %s: %s", where, problem)

    # -- control loop ----------------------------------------------------------------------------
    def _safely(self, fn: Callable[..., object], *args: Any) -> None:
        """One step of the control loop; a failure is logged (throttled), the loop goes on."""
        try:
            fn(*args)
        except Exception:
            what = getattr(fn, "__name__", fn)
            self.throttled.error("%s: unexpected error in %s", self.name, what, exc_info=True)


def run_registry(
    cfg: FleetConfig, *, db_path: str | Path | None = None, metrics_port: int | None = None
) -> int:
    """Run the registry in this (main) thread until SIGINT/SIGTERM; returns the exit code."""
    return RegistryDaemon(cfg, db_path=db_path, metrics_port=metrics_port).run()
