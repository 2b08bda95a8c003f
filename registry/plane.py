"""One service's routing inside the registry daemon: a plane.

A fleet serves several services, and routing is per (robot, service): the anycast invariant,
standby and service states, latency bounds, placement by load, pools and failover all hold per
service, so a deployment may serve robot-1's `detect` and stand by for its `segment`. The registry
daemon keeps one Zenoh session, one liveliness token, one membership view and the queryables, and
runs one plane per service (`registry.planes` dispatches to them); a one-service fleet has one
plane, and routes as the registry always did.

A plane is the single-service registry's parts, built from the service's view of the fleet
(`FleetConfig.for_service`: its overrides in place, only the machines that serve or use it), so
their logic is unchanged: its RIB (a sqlite file of its own, `plane_db_path`), its measurements,
its scheduler (the service's latency bound), registrar, prober, switcher (every ctl request and
route change it sends names the service), round-robin pools, control loop and views. Nothing in a
plane knows of the others.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from common.config import FleetConfig
from common.throttled_log import ThrottledLog
from registry.control_loop import ControlLoop
from registry.latency import LatencyBound
from registry.measurements import Measurements
from registry.metrics import RegistryMetrics
from registry.pool_keeper import pool_keeper
from registry.pools import pool_planner
from registry.prober import RegistryProber
from registry.registration import Registrar, fleet_model_digest
from registry.rib import MEMORY, Rib
from registry.scheduler import Scheduler, SchedulerParams
from registry.switch import Switcher
from registry.transport import ZenohTransport
from registry.views import RibViews


@dataclass(frozen=True)
class Plane:
    """One service's routing: its view of the fleet and the parts built from it."""

    service: str
    cfg: FleetConfig
    """The service's view of the fleet (`FleetConfig.for_service`)."""
    rib: Rib
    measurements: Measurements
    registrar: Registrar
    loop: ControlLoop
    views: RibViews

    def holds(self, machine: str) -> bool:
        """Whether the fleet file gives `machine` this service (it serves or uses it)."""
        return machine in self.cfg.machines


def plane_db_path(db_path: str | Path, service: str, *, first: bool) -> str | Path:
    """Where a service's RIB lives: the fleet's first service keeps `db_path` itself (a
    one-service fleet's RIB file is unchanged), another `<stem>.<service><suffix>` beside it;
    an in-memory RIB stays in memory."""
    if first or str(db_path) == MEMORY:
        return db_path
    path = Path(db_path)
    return path.with_name(f"{path.stem}.{service}{path.suffix}")


def latency_bound(cfg: FleetConfig) -> LatencyBound:
    """The latency bound of `cfg` (a service's view: the service's bound)."""
    lb = cfg.latency_bound
    return LatencyBound(
        stat=lb.stat,
        seconds=lb.seconds,
        window=lb.window,
        hysteresis_s=lb.hysteresis_s,
        better_margin=lb.better_margin,
    )


def plane_measurements(
    cfg: FleetConfig, params: SchedulerParams, on_bad_sample: Callable[[str, str], None]
) -> Measurements:
    """A service's measurements: its bound's window, its deadline."""
    return Measurements(
        latency_bound(cfg).window,
        deadline_s=cfg.deadline_s,
        timeout_count=params.timeout_count,
        on_bad_sample=on_bad_sample,
    )


def build_plane(
    cfg: FleetConfig,
    rib: Rib,
    measurements: Measurements,
    *,
    transport: ZenohTransport,
    prober: RegistryProber,
    sender: str,
    params: SchedulerParams,
    ctl_timeout_s: float,
    throttled: ThrottledLog,
    started_at: float,
    restore_grace_s: float,
    metrics: RegistryMetrics,
    max_request_bytes: int,
) -> Plane:
    """The parts of one service's routing over an opened RIB (`cfg`: the service's view; the
    prober probes for the service). Opens nothing."""
    service = cfg.service_name
    bound = latency_bound(cfg)
    registrar = Registrar(
        cfg.fleet, rib, service, fleet_model_digest(cfg), max_request_bytes=max_request_bytes
    )
    switcher = Switcher(
        rib,
        transport,
        ctl_timeout_s=ctl_timeout_s,
        sender=sender,
        pools=pool_planner(cfg, rib),
        in_flight=registrar.robot_in_flight,
        service=service,
    )
    loop = ControlLoop(
        cfg,
        rib=rib,
        transport=transport,
        switcher=switcher,
        registrar=registrar,
        prober=prober,
        pools=pool_keeper(switcher),
        scheduler=Scheduler(bound, params),
        measurements=measurements,
        throttled=throttled,
        started_at=started_at,
        restore_grace_s=restore_grace_s,
        metrics=metrics,
    )
    views = RibViews(
        cfg.fleet,
        rib,
        measurements,
        registrar,
        bound,
        cfg.deadline_s,
        max_request_bytes=max_request_bytes,
    )
    return Plane(service, cfg, rib, measurements, registrar, loop, views)
