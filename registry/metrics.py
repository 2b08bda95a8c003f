"""The registry daemon's Prometheus metrics (docs/metrics.md, "registry").

Counted where the registry acts, one call each: `round(seconds)` after every scheduling round
(the daemon's main loop, which ticks it; one round ticks every service), `route_change(reason,
previous, service=...)` for every route that changed (`registry.control_loop`; a failover is one
that moved a robot off a deployment that failed it: `deployment_lost` or `timeouts`), counted for
the fleet and, by `service`, for the service, `probe_report()` for every robot probe report read
(the daemon's subscriber). Read from each service's RIB at scrape time, with a `service` label:
robots and deployments alive, the RIB's rows per table, robots routed per deployment and each
deployment's last known load and capacity.

`RegistryMetrics(None)` counts nothing (metrics off), so the daemon calls it unconditionally.
"""

from __future__ import annotations

from collections import Counter as Tally
from collections.abc import Callable, Iterator, Mapping, Sequence

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric

from common.metrics import NAMESPACE, ROUND_BUCKETS_S, ReadCollector
from registry.rib import Rib
from registry.scheduler import Reason

FAILOVER_REASONS = frozenset({Reason.DEPLOYMENT_LOST.value, Reason.TIMEOUTS.value})
"""Route changes that count as failovers: the robot's deployment died or stopped answering."""

RESTORE = "restore"
"""The reason label of a restored route re-asserted after a restart."""


class RegistryMetrics:
    """The registry's metrics in `registry` (None: off); `ribs()` is each service's RIB (service
    -> RIB) while they are open (empty otherwise); `services`' counters are served at 0 from the
    start."""

    def __init__(
        self,
        registry: CollectorRegistry | None,
        ribs: Callable[[], Mapping[str, Rib]] = dict,
        services: Sequence[str] = (),
    ) -> None:
        self.enabled = registry is not None
        if registry is None:
            return
        self._ribs = ribs
        ns, sub = NAMESPACE, "registry"
        self._round = Histogram(
            "round_duration_seconds",
            "Seconds of one scheduling round (every live robot evaluated once).",
            namespace=ns,
            subsystem=sub,
            buckets=ROUND_BUCKETS_S,
            registry=registry,
        )
        self._changes = Counter(
            "route_changes",
            "Routes changed, by reason (initial, deployment_lost, drain, timeouts, "
            "bound_violation, better, busy, no_capacity, restore).",
            ["reason"],
            namespace=ns,
            subsystem=sub,
            registry=registry,
        )
        self._failovers = Counter(
            "failovers",
            "Robots moved off a deployment that died or stopped answering (route changes for "
            "deployment_lost or timeouts).",
            namespace=ns,
            subsystem=sub,
            registry=registry,
        )
        self._service_changes = Counter(
            "service_route_changes",
            "Routes changed, by service and reason (the route_changes of each service).",
            ["service", "reason"],
            namespace=ns,
            subsystem=sub,
            registry=registry,
        )
        self._service_failovers = Counter(
            "service_failovers",
            "Robots moved off a deployment that died or stopped answering, by service.",
            ["service"],
            namespace=ns,
            subsystem=sub,
            registry=registry,
        )
        self._probe_reports = Counter(
            "probe_reports",
            "Robot probe reports received (tele/<robot>/probe), bad ones included.",
            namespace=ns,
            subsystem=sub,
            registry=registry,
        )
        for reason in [*(r.value for r in Reason), RESTORE]:
            self._changes.labels(reason)  # served at 0 from the start
            for service in services:
                self._service_changes.labels(service, reason)
        for service in services:
            self._service_failovers.labels(service)
        registry.register(ReadCollector(self._read, "the RIB"))

    def round(self, seconds: float) -> None:
        """One scheduling round took `seconds`."""
        if self.enabled:
            self._round.observe(seconds)

    def route_change(
        self, reason: str, previous: str | None, *, service: str | None = None
    ) -> None:
        """A robot's route (for `service`, when named) changed for `reason` (a `Reason` value,
        or `restore`), from deployment `previous` (None: from none)."""
        if not self.enabled:
            return
        failover = previous is not None and reason in FAILOVER_REASONS
        self._changes.labels(reason).inc()
        if failover:
            self._failovers.inc()
        if service is not None:
            self._service_changes.labels(service, reason).inc()
            if failover:
                self._service_failovers.labels(service).inc()

    def probe_report(self) -> None:
        if self.enabled:
            self._probe_reports.inc()

    def _read(self) -> Iterator[Metric]:
        ribs = self._ribs()
        if not ribs:
            return
        ns = NAMESPACE
        robots_alive = GaugeMetricFamily(
            f"{ns}_registry_robots_alive",
            "Robots whose liveliness token is up.",
            labels=["service"],
        )
        deployments_alive = GaugeMetricFamily(
            f"{ns}_registry_deployments_alive",
            "Deployments registered and alive.",
            labels=["service"],
        )
        size = GaugeMetricFamily(
            f"{ns}_registry_rib_rows", "Rows of the RIB, by table.", labels=["table", "service"]
        )
        per = GaugeMetricFamily(
            f"{ns}_registry_routed_robots",
            "Robots the RIB routes to each deployment.",
            labels=["deployment", "service"],
        )
        load = GaugeMetricFamily(
            f"{ns}_registry_deployment_load_requests",
            "Each deployment's requests pending as its last probe reply said.",
            labels=["deployment", "service"],
        )
        capacity = GaugeMetricFamily(
            f"{ns}_registry_deployment_capacity_requests",
            "Each deployment's capacity (requests admitted at once) as its last probe reply said.",
            labels=["deployment", "service"],
        )
        for service, rib in ribs.items():
            deployments, robots, routes = rib.deployments(), rib.robots(), rib.routes()
            robots_alive.add_metric([service], sum(r.alive for r in robots))
            deployments_alive.add_metric([service], sum(d.alive for d in deployments))
            for table, n in (
                ("deployments", len(deployments)),
                ("robots", len(robots)),
                ("routes", len(routes)),
            ):
                size.add_metric([table, service], n)
            routed = Tally(r.deployment for r in routes if r.deployment is not None)
            for d in deployments:
                per.add_metric([d.id, service], routed.get(d.id, 0))
                load.add_metric([d.id, service], d.load)
                capacity.add_metric([d.id, service], d.capacity)
        yield from (robots_alive, deployments_alive, size, per, load, capacity)


__all__ = ["FAILOVER_REASONS", "RegistryMetrics"]
