"""A daemon's Prometheus endpoint: `/metrics` served from the daemon's own registry.

Each daemon keeps its metrics in a `prometheus_client.CollectorRegistry` of its own, never the
library's global one, so several daemons in one process (the integration tests) do not collide,
and serves it over HTTP on the port its machine's `metrics` section (or `--metrics-port`) names
(`MetricsEndpoint`, a context manager the daemon's lifecycle holds: the server stops at
shutdown). Off unless a port is set. The names are documented in docs/metrics.md; what each
daemon counts lives beside it (`robotd.metrics`, `cloudd.metrics`, `registry.metrics`).

Values read at scrape time (gauges of state: routes, states, sizes) come from `ReadCollector`,
which calls a function on the scraping thread and tolerates a daemon half started or stopping:
a read that fails yields nothing for that scrape, never an HTTP 500.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, start_http_server
from prometheus_client.core import Metric
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from common.errors import UserError

if TYPE_CHECKING:
    from wsgiref.simple_server import WSGIServer

    from common.config import MetricsConfig
    from common.daemon import Daemon

log = logging.getLogger(__name__)

NAMESPACE = "elasticfog"
"""The first word of every metric name of ours (Prometheus: a single-word application prefix)."""

LATENCY_BUCKETS_S = (
    0.005,
    0.01,
    0.02,
    0.03,
    0.05,
    0.075,
    0.1,
    0.15,
    0.2,
    0.3,
    0.5,
    0.75,
    1.0,
    2.0,
)
"""Histogram buckets of a frame's or a request's seconds: fine where deadlines sit (tens to
hundreds of ms), coarse beyond a second."""

ROUND_BUCKETS_S = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0)
"""Histogram buckets of a registry round: well under a millisecond with a few robots, tens of
ms at a thousand (docs/scale.md)."""

BATCH_SIZE_BUCKETS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32)
"""Histogram buckets of a batch's size, requests (up to common.config's largest batch)."""


def new_registry() -> CollectorRegistry:
    """A registry of one daemon, with the process's CPU, memory and file descriptors
    (`process_*`) and the Python version (`python_info`) in it, as the global one has."""
    registry = CollectorRegistry(auto_describe=True)
    ProcessCollector(registry=registry)
    PlatformCollector(registry=registry)
    return registry


class ReadCollector(Collector):
    """Metrics read at scrape time: `read()` yields metric families, e.g. from a snapshot of the
    daemon's state. A failed read (a part not started yet, or gone at shutdown) yields nothing
    for this scrape and one debug line."""

    def __init__(self, read: Callable[[], Iterable[Metric]], what: str) -> None:
        self._read = read
        self._what = what

    def collect(self) -> Iterator[Metric]:
        try:
            families = list(self._read())
        except Exception as exc:
            log.debug("metrics: %s not read: %s", self._what, exc)
            return iter(())
        return iter(families)

    def describe(self) -> Iterator[Metric]:
        # Nothing to describe ahead: the read must not run at registration (nothing started).
        return iter(())


class MetricsEndpoint:
    """`/metrics` of `registry` on `host:port` while entered (a thread of the HTTP server).

    `port` 0 takes any free port: `port` is the bound one once entered. A port that cannot be
    bound is a UserError naming it (what the machine's config or `--metrics-port` asked for)."""

    def __init__(self, registry: CollectorRegistry, host: str, port: int, *, who: str) -> None:
        self.registry = registry
        self.host = host
        self.port = port
        self.who = who
        self._server: WSGIServer | None = None

    @classmethod
    def of(
        cls, registry: CollectorRegistry, config: MetricsConfig, port: int | None, *, who: str
    ) -> MetricsEndpoint | None:
        """The endpoint a daemon serves: `port` (its `--metrics-port`) or its config's; None
        when neither sets one (metrics off)."""
        chosen = port if port is not None else config.port
        if chosen is None:
            return None
        return cls(registry, config.host, chosen, who=who)

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}/metrics"

    def __enter__(self) -> MetricsEndpoint:
        try:
            server, _thread = start_http_server(self.port, addr=self.host, registry=self.registry)
        except OSError as exc:
            reason = exc.strerror or str(exc)
            raise UserError(
                f"{self.who}: cannot serve metrics on {self.host}:{self.port}: {reason}"
            ) from None
        self._server = server
        self.port = int(server.server_port)
        log.info("%s: metrics on %s", self.who, self.url)
        return self

    def __exit__(self, *exc: object) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.shutdown()
            server.server_close()


def serve(
    owner: Daemon, config: MetricsConfig, port: int | None, *, who: str
) -> MetricsEndpoint | None:
    """A new registry served on the endpoint `config` and `port` name, held by `owner`'s
    lifecycle (the server stops at shutdown); None when metrics are off."""
    endpoint = MetricsEndpoint.of(new_registry(), config, port, who=who)
    if endpoint is None:
        return None
    return owner.hold(endpoint, "metrics endpoint")


def check_port(port: int | None, option: str = "--metrics-port") -> None:
    """UserError for a port outside 0..65535 (None: not given)."""
    if port is not None and not 0 <= port <= 65535:
        raise UserError(f"{option} {port}: expected a TCP port in 0..65535")


__all__ = [
    "BATCH_SIZE_BUCKETS",
    "LATENCY_BUCKETS_S",
    "NAMESPACE",
    "ROUND_BUCKETS_S",
    "MetricsEndpoint",
    "ReadCollector",
    "check_port",
    "new_registry",
    "serve",
]
