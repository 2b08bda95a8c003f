"""The registry daemon's Prometheus metrics (docs/metrics.md, "registry").

Counted where the registry acts, one call each: `round(seconds)` after every scheduling round
(the daemon's main loop, which ticks it), `route_change(reason, previous)` for every route that
changed (`registry.control_loop`; a failover is one that moved a robot off a deployment that
failed it: `deployment_lost` or `timeouts`), `probe_report()` for every robot probe report read
(the daemon's subscriber). Read from the RIB at scrape time: robots and
deployments alive, the RIB's rows per table, robots routed per deployment and each deployment's
last known load and capacity.

`RegistryMetrics(None)` counts nothing (metrics off), so the daemon calls it unconditionally.
"""

from __future__ import annotations

from collections import Counter as Tally
from collections.abc import Callable, Iterator

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
    """The registry's metrics in `registry` (None: off); `rib()` is the RIB while it is open."""

    def __init__(
        self, registry: CollectorRegistry | None, rib: Callable[[], Rib | None] = lambda: None
    ) -> None:
        self.enabled = registry is not None
        if registry is None:
            return
        self._rib = rib
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
        self._probe_reports = Counter(
            "probe_reports",
            "Robot probe reports received (tele/<robot>/probe), bad ones included.",
            namespace=ns,
            subsystem=sub,
            registry=registry,
        )
        for reason in [*(r.value for r in Reason), RESTORE]:
            self._changes.labels(reason)  # served at 0 from the start
        registry.register(ReadCollector(self._read, "the RIB"))

    def round(self, seconds: float) -> None:
        """One scheduling round took `seconds`."""
        if self.enabled:
            self._round.observe(seconds)

    def route_change(self, reason: str, previous: str | None) -> None:
        """A robot's route changed for `reason` (a `Reason` value, or `restore`), from
        deployment `previous` (None: from none)."""
        if not self.enabled:
            return
        self._changes.labels(reason).inc()
        if previous is not None and reason in FAILOVER_REASONS:
            self._failovers.inc()

    def probe_report(self) -> None:
        if self.enabled:
            self._probe_reports.inc()

    def _read(self) -> Iterator[Metric]:
        rib = self._rib()
        if rib is None:
            return
        ns = NAMESPACE
        deployments, robots, routes = rib.deployments(), rib.robots(), rib.routes()
        for name, text, value in (
            ("robots_alive", "Robots whose liveliness token is up.", sum(r.alive for r in robots)),
            (
                "deployments_alive",
                "Deployments registered and alive.",
                sum(d.alive for d in deployments),
            ),
        ):
            g = GaugeMetricFamily(f"{ns}_registry_{name}", text)
            g.add_metric([], value)
            yield g
        size = GaugeMetricFamily(
            f"{ns}_registry_rib_rows", "Rows of the RIB, by table.", labels=["table"]
        )
        for table, n in (
            ("deployments", len(deployments)),
            ("robots", len(robots)),
            ("routes", len(routes)),
        ):
            size.add_metric([table], n)
        yield size
        routed = Tally(r.deployment for r in routes if r.deployment is not None)
        per = GaugeMetricFamily(
            f"{ns}_registry_routed_robots",
            "Robots the RIB routes to each deployment.",
            labels=["deployment"],
        )
        load = GaugeMetricFamily(
            f"{ns}_registry_deployment_load_requests",
            "Each deployment's requests pending as its last probe reply said.",
            labels=["deployment"],
        )
        capacity = GaugeMetricFamily(
            f"{ns}_registry_deployment_capacity_requests",
            "Each deployment's capacity (requests admitted at once) as its last probe reply said.",
            labels=["deployment"],
        )
        for d in deployments:
            per.add_metric([d.id], routed.get(d.id, 0))
            load.add_metric([d.id], d.load)
            capacity.add_metric([d.id], d.capacity)
        yield per
        yield load
        yield capacity


__all__ = ["FAILOVER_REASONS", "RegistryMetrics"]
