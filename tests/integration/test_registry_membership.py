"""The registry's membership over real Zenoh on loopback: a cloud token declared before the
registry started is seen, registered, and its end noticed.

Regression guarded against: the registry followed `alive/**` with a subscriber without history
and seeded itself with a liveliness get. Zenoh (1.10) does not always deliver the end of a token
that existed before such a subscriber, so a deployment alive when the registry started could die
unnoticed and stay routed to. The registry here is a peer of a router that runs elsewhere
(`embedded_router: false`), so the deployment's token exists before the registry's session does.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common import keys
from common.config import FleetConfig
from common.session import open_session
from common.wire import decode
from deploy.readiness import wait_until
from tests.helpers import registry as reg
from tests.helpers.registry import (
    LEASE_MS,
    QUERY_TIMEOUT_S,
    WAIT_S,
    FakeDeployment,
    RunningRegistry,
    model_digest,
    view,
    write_fleet,
)
from tests.integration.conftest import find_free_port, loopback_endpoint

peer = reg.peer
start_registry = reg.start_registry


@pytest.fixture
def external_router(tmp_path: Path) -> Iterator[tuple[FleetConfig, zenoh.Session]]:
    """A fleet whose registry is a peer of a router running apart, and that router."""
    endpoint = loopback_endpoint(find_free_port())
    _, cfg = write_fleet(
        tmp_path,
        registry={"endpoint": endpoint, "listen": [endpoint], "embedded_router": False},
    )
    router = open_session(router=True, listen=[endpoint], lease_ms=LEASE_MS)
    try:
        yield cfg, router
    finally:
        router.close()


def test_a_cloud_token_older_than_the_registry_is_seen_and_so_is_its_end(
    external_router: tuple[FleetConfig, zenoh.Session],
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
    wait_for_token: Callable[..., None],
) -> None:
    cfg, router = external_router
    edge = FakeDeployment(peer(cfg), cfg, "edge-1", digest=model_digest(cfg))
    wait_for_token(router, keys.alive_deployment(cfg.fleet, "edge-1"))

    start_registry(cfg)
    observer = peer(cfg)
    rows = _wait_deployments(
        observer, cfg, lambda rows: any(d.id == "edge-1" and d.alive for d in rows)
    )
    assert [d.id for d in rows] == ["edge-1"]
    assert edge.probes >= 1, "registered from its probe reply"

    edge.die()
    _wait_deployments(observer, cfg, lambda rows: not {d.id: d for d in rows}["edge-1"].alive)
    downs = [e for e in view(observer, cfg, "events") if e.kind == "deployment_down"]
    assert [e.deployment for e in downs] == ["edge-1"]


def _wait_deployments(
    session: zenoh.Session, cfg: FleetConfig, predicate: Callable[[tuple[Any, ...]], bool]
) -> tuple[Any, ...]:
    """Ask the `deployments` view until its rows satisfy `predicate`, each round waiting on the
    get. A get may find no registry yet: the router relays no queries between peers, and the
    observer learns the registry's queryable only once gossip has linked them."""
    seen: list[tuple[Any, ...]] = []

    def rows_now() -> tuple[Any, ...] | None:
        replies = session.get(keys.rib(cfg.fleet, "deployments"), timeout=QUERY_TIMEOUT_S)
        answers = [decode(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        if not answers:
            return None
        seen[:] = [answers[0].rows]
        return answers[0].rows if predicate(answers[0].rows) else None

    return wait_until(
        rows_now, timeout_s=WAIT_S, what=f"the deployments view to hold (last: {seen})"
    )
