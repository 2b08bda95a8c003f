"""The cloud daemon's /metrics over HTTP on loopback (its `run()` in a thread, real Zenoh).

Each outcome a request comes to is counted under its own label, by robot, where the daemon
decides it: answered (`ok`, with the queue and compute histograms and a batch), over the
deployment's limits (`too_large`), another robot's body (`wrong_robot`); the robot's state, the
queue's numbers and the providers are read at scrape time.
The endpoint is the daemon's own registry (two daemons in one process would collide on the
global one), chosen with port 0. A port already taken is one named error at start.
"""

from __future__ import annotations

import dataclasses
import socket
import threading
import time
import urllib.request
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh
from prometheus_client.parser import text_string_to_metric_families

from cloudd.daemon import CloudDaemon
from common.errors import UserError
from common.partition.runtime import SplitModel
from common.wire import ErrorReply
from common.wire.cloud_to_robot import InferReply
from common.wire.registry import CtlOp
from tests.integration.conftest import Router
from tests.integration.test_cloudd import (
    POLL_S,
    ROBOT,
    WAIT_S,
    ask_one,
    connect,
    ctl,
    fleet_config,
    infer_request,
    reference,
    serve,
    svc_key,
    tiny_path,
)

# The fixtures shared with the daemon's main integration tests (pytest finds them by name).
__all__ = ["reference", "tiny_path"]

REQUEST_LIMIT = 100 * 1024
"""Above a good request of the tiny model (64 KiB of tensor), below the fleet's limit."""


def scrape(url: str) -> dict[tuple[str, frozenset[tuple[str, str]]], float]:
    with urllib.request.urlopen(url, timeout=2.0) as response:
        text = response.read().decode("utf-8")
    return {
        (s.name, frozenset(s.labels.items())): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def value(
    samples: dict[tuple[str, frozenset[tuple[str, str]]], float], name: str, **labels: str
) -> float:
    want = set(labels.items())
    return sum(v for (n, ls), v in samples.items() if n == name and want <= ls)


@pytest.fixture
def metered(zenoh_router: Router, tiny_path: Path) -> Iterator[CloudDaemon]:
    fleet = f"m-{uuid.uuid4().hex[:8]}"
    cfg = fleet_config(
        tiny_path,
        zenoh_router.endpoint,
        fleet,
        limits={"max_request_bytes": REQUEST_LIMIT},
        metrics={"port": 0, "host": "127.0.0.1"},
    )
    daemon = CloudDaemon(cfg, "edge-1")
    thread = threading.Thread(target=daemon.run, name="cloud-edge-1", daemon=True)
    thread.start()
    deadline = time.monotonic() + WAIT_S * 3  # the first start splits the model
    while not daemon.ready.wait(POLL_S):
        assert thread.is_alive() and time.monotonic() < deadline, "edge-1 did not start"
    try:
        yield daemon
    finally:
        daemon.stop()
        thread.join(WAIT_S)
        assert not thread.is_alive(), "the daemon did not stop"


def test_each_outcome_is_counted_by_robot_and_read_over_http(
    metered: CloudDaemon,
    open_peer: Callable[..., zenoh.Session],
    wait_for_token: Callable[..., None],
    reference: SplitModel,
) -> None:
    daemon = metered
    assert daemon.metrics_endpoint is not None
    url = daemon.metrics_endpoint.url
    assert url.startswith("http://127.0.0.1:") and not url.endswith(":0/metrics")
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference)
    served_before = value(scrape(url), "elasticfog_cloud_inference_requests_total", outcome="ok")
    good = infer_request(reference, 1, frame=2)
    for frame in range(3):
        reply = ask_one(session, svc_key(daemon), dataclasses.replace(good, frame=frame).to_wire())
        assert isinstance(reply, InferReply), reply
    too_large = ask_one(session, svc_key(daemon), bytes(REQUEST_LIMIT + 1))
    assert isinstance(too_large, ErrorReply)
    other = ask_one(session, svc_key(daemon), dataclasses.replace(good, robot="robot-2").to_wire())
    assert isinstance(other, ErrorReply)

    samples = scrape(url)
    requests = "elasticfog_cloud_inference_requests_total"
    outcomes = {
        outcome: value(samples, requests, robot=ROBOT, outcome=outcome, deployment="edge-1")
        for outcome in ("ok", "too_large", "wrong_robot", "busy")
    }
    assert served_before >= 1  # serve() waits for one answer
    outcomes["ok"] -= served_before
    assert outcomes == {"ok": 3, "too_large": 1, "wrong_robot": 1, "busy": 0}
    ok = 3 + served_before
    assert value(samples, "elasticfog_cloud_inference_queue_duration_seconds_count") == ok
    assert value(samples, "elasticfog_cloud_inference_compute_infer_duration_seconds_count") == ok
    assert value(samples, "elasticfog_cloud_inference_batch_size_count") == ok
    assert value(samples, "elasticfog_cloud_robot_state", robot=ROBOT, state="service") == 1
    assert value(samples, "elasticfog_cloud_robot_state", robot=ROBOT, state="standby") == 0
    assert value(samples, "elasticfog_cloud_inference_pending_requests") == 0
    assert value(samples, "elasticfog_cloud_capacity_requests") > 0
    assert value(samples, "elasticfog_cloud_provider_rank", provider="CPUExecutionProvider") == 0
    assert value(samples, "process_cpu_seconds_total") > 0

    assert ctl(session, daemon, CtlOp.STANDBY, 2).ok
    samples = scrape(url)
    assert value(samples, "elasticfog_cloud_robot_state", robot=ROBOT, state="standby") == 1


def test_a_taken_metrics_port_is_one_named_error_at_start(
    zenoh_router: Router, tiny_path: Path
) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cfg = fleet_config(
            tiny_path,
            zenoh_router.endpoint,
            f"m-{uuid.uuid4().hex[:8]}",
            metrics={"port": port, "host": "127.0.0.1"},
        )
        with pytest.raises(
            UserError, match=f"cloud edge-1: cannot serve metrics on 127.0.0.1:{port}"
        ):
            CloudDaemon(cfg, "edge-1").run()
