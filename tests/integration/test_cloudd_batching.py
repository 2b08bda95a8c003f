"""The cloud daemon with batching on, over real Zenoh on loopback (its `run()` in a thread).

Three robots in service on one deployment: requests of one cut sent together run as one
onnxruntime batch and each robot gets exactly its own result (the model's rows are 32 per
request, so a mixed-up slice cannot pass); different cuts run apart; a request whose deadline
cannot afford the queue delay runs at once; a robot past its in-flight limit gets `busy`,
counted by reason.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from cloudd.daemon import CloudDaemon
from cloudd.refusals import RefusalReason
from common import keys
from common.config import fleet_from_dict
from common.partition import load_partition, sample_feeds
from common.partition.runtime import SplitModel
from common.wire import Message, decode
from common.wire.cloud_to_robot import BusyReply, InferReply
from common.wire.registry import CtlOp, CtlReply, CtlRequest
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import EncodedTensor
from tests.integration.conftest import Router
from tests.unit.test_cloudd_validate import write_tiny_model

ROBOTS = ("robot-1", "robot-2", "robot-3")
SERVICE = "vision"
WAIT_S = 10.0
POLL_S = 0.05
QUEUE_DELAY_MS = 400.0
"""Long, so a batch visibly waits for the robots it expects (and a short deadline visibly
does not)."""
RESULT_ATOL = 1e-4


@pytest.fixture(scope="module")
def tiny_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_model(tmp_path_factory.mktemp("model") / "tiny.onnx")


@pytest.fixture(scope="module")
def reference(tiny_path: Path) -> SplitModel:
    return SplitModel(load_partition(str(tiny_path)), lazy=True)


@pytest.fixture
def daemon(zenoh_router: Router, tiny_path: Path) -> Iterator[CloudDaemon]:
    """A ready cloud daemon batching up to 3 requests, one per robot in flight."""
    machines: dict[str, Any] = {
        "edge-1": {
            "role": "cloud",
            "listen": ["tcp/127.0.0.1:0"],
            "workers": 1,
            "batching": {
                "enabled": True,
                "preferred_batch_sizes": [len(ROBOTS)],
                "max_queue_delay_ms": QUEUE_DELAY_MS,
                "max_in_flight_per_robot": 1,
            },
        }
    }
    machines.update({r: {"role": "robot", "listen": ["tcp/127.0.0.1:0"]} for r in ROBOTS})
    cfg = fleet_from_dict(
        {
            "fleet": f"b-{uuid.uuid4().hex[:8]}",
            "service": SERVICE,
            "model": str(tiny_path),
            "registry": {"endpoint": zenoh_router.endpoint, "listen": [zenoh_router.endpoint]},
            "machines": machines,
            "initial_policy": {"edge-1": "service"},
            "latency_bound": {"seconds": 0.5},
            "deadline_s": 5.0,
        }
    )
    cloud = CloudDaemon(cfg, "edge-1")
    thread = threading.Thread(target=cloud.run, name="cloud-edge-1", daemon=True)
    thread.start()
    deadline = time.monotonic() + WAIT_S * 3
    while not cloud.ready.wait(POLL_S):
        assert thread.is_alive() and time.monotonic() < deadline, "edge-1 did not start"
    try:
        yield cloud
    finally:
        cloud.stop()
        thread.join(WAIT_S)
        assert not thread.is_alive(), "the daemon did not stop"


def svc_key(daemon: CloudDaemon, robot: str) -> str:
    return keys.svc_infer(daemon.cfg.fleet, SERVICE, robot)


def request(
    model: SplitModel, robot: str, cut: int, seed: int, deadline_s: float = 5.0
) -> tuple[InferRequest, dict[str, np.ndarray]]:
    """A request of `robot` at `cut` for its own input, and the full model's result for it."""
    feeds = sample_feeds(model.input_specs(), seed=seed)
    tensors = {n: EncodedTensor.raw(a) for n, a in model.run_prefix(cut, feeds).items()}
    message = InferRequest(
        robot=robot,
        frame=seed,
        model_digest=model.digest,
        cut=cut,
        tensors=tensors,
        deadline_s=deadline_s,
        sent_at=time.time(),
    )
    return message, model.run_full(feeds)


def send_together(
    session: zenoh.Session, daemon: CloudDaemon, requests: list[InferRequest]
) -> list[Message]:
    """Send every request at once (one get each, in flight together); their replies in order."""
    handlers = [
        session.get(svc_key(daemon, r.robot), payload=r.to_wire(), timeout=WAIT_S) for r in requests
    ]
    replies = []
    for handler in handlers:
        got = [decode(reply.ok.payload.to_bytes()) for reply in handler if reply.ok is not None]
        assert len(got) == 1, f"expected one reply, got {got!r}"
        replies.append(got[0])
    return replies


@pytest.fixture
def robots_in_service(
    daemon: CloudDaemon,
    open_peer: Callable[..., zenoh.Session],
    wait_for_token: Callable[..., None],
    reference: SplitModel,
) -> zenoh.Session:
    """Every robot in service, each heard from once (so a batch expects the others)."""
    session = open_peer()
    wait_for_token(session, keys.alive_deployment(daemon.cfg.fleet, "edge-1"))
    for robot in ROBOTS:
        ctl = CtlRequest(op=CtlOp.SERVICE, robot=robot, epoch=1, sender="test")
        replies = list(session.get(keys.dep_ctl(daemon.cfg.fleet, "edge-1"), payload=ctl.to_wire()))
        answer = decode(replies[0].ok.payload.to_bytes()) if replies and replies[0].ok else None
        assert isinstance(answer, CtlReply) and answer.ok, answer
    for i, robot in enumerate(ROBOTS):
        deadline = time.monotonic() + WAIT_S
        while True:  # the service key is on its way from the daemon to this session
            message, _ = request(reference, robot, 0, seed=i)
            got = [r for r in session.get(svc_key(daemon, robot), payload=message.to_wire())]
            if got:
                assert isinstance(decode(got[0].ok.payload.to_bytes()), InferReply)
                break
            assert time.monotonic() < deadline, f"{robot}'s service key never answered"
            threading.Event().wait(POLL_S)
    return session


def test_requests_of_one_cut_run_as_one_batch_and_each_robot_gets_its_own_result(
    daemon: CloudDaemon, robots_in_service: zenoh.Session, reference: SplitModel
) -> None:
    assert daemon.model.batched(1), "the tiny model's suffixes take a batch axis"
    before = daemon.batch_stats.snapshot()
    pairs = [request(reference, robot, 1, seed=10 + i) for i, robot in enumerate(ROBOTS)]
    t0 = time.monotonic()
    replies = send_together(robots_in_service, daemon, [m for m, _ in pairs])
    took_s = time.monotonic() - t0
    for (message, expected), reply in zip(pairs, replies, strict=True):
        assert isinstance(reply, InferReply), reply
        assert reply.frame == message.frame
        for name, value in expected.items():
            err = float(np.max(np.abs(reply.outputs[name] - value)))
            assert err <= RESULT_ATOL, f"{message.robot} {name}: max abs error {err}"
    after = daemon.batch_stats.snapshot()
    assert after.get(3, 0) == before.get(3, 0) + 1, f"one batch of 3: {before} -> {after}"
    assert len({r.compute_s for r in replies if isinstance(r, InferReply)}) == 1, "one run"
    assert took_s < QUEUE_DELAY_MS / 1000, "a full batch leaves without waiting out the delay"


def test_different_cuts_run_apart_each_correct(
    daemon: CloudDaemon, robots_in_service: zenoh.Session, reference: SplitModel
) -> None:
    pairs = [request(reference, robot, cut, seed=20 + cut) for cut, robot in enumerate(ROBOTS)]
    replies = send_together(robots_in_service, daemon, [m for m, _ in pairs])
    for (_, expected), reply in zip(pairs, replies, strict=True):
        assert isinstance(reply, InferReply), reply
        for name, value in expected.items():
            assert float(np.max(np.abs(reply.outputs[name] - value))) <= RESULT_ATOL
    sizes = daemon.batch_stats.snapshot()
    assert max(sizes) == 1, f"nothing batched across cuts: {sizes}"


def test_a_short_deadline_is_not_held_for_a_batch(
    daemon: CloudDaemon, robots_in_service: zenoh.Session, reference: SplitModel
) -> None:
    # The other two robots are expected: with a long budget the request waits the delay...
    relaxed, _ = request(reference, "robot-1", 1, seed=30)
    t0 = time.monotonic()
    assert isinstance(send_together(robots_in_service, daemon, [relaxed])[0], InferReply)
    waited_s = time.monotonic() - t0
    assert waited_s >= QUEUE_DELAY_MS / 1000 * 0.9, f"answered after {waited_s:.3f} s"
    # ...but not one whose deadline cannot afford it.
    hurried, _ = request(reference, "robot-1", 1, seed=31, deadline_s=0.1)
    t0 = time.monotonic()
    assert isinstance(send_together(robots_in_service, daemon, [hurried])[0], InferReply)
    assert time.monotonic() - t0 < 0.1, "run at once, within its deadline"


def test_a_robot_past_its_in_flight_limit_is_answered_busy_at_once(
    daemon: CloudDaemon, robots_in_service: zenoh.Session, reference: SplitModel
) -> None:
    first, _ = request(reference, "robot-1", 1, seed=40)
    second, _ = request(reference, "robot-1", 1, seed=41)
    replies = send_together(robots_in_service, daemon, [first, second])
    kinds = sorted(type(r).__name__ for r in replies)
    assert kinds == ["BusyReply", "InferReply"], kinds
    busy = next(r for r in replies if isinstance(r, BusyReply))
    assert busy.deployment == "edge-1" and busy.capacity == 1 * len(ROBOTS) + 4
    assert daemon.refusals.snapshot() == {RefusalReason.ROBOT_IN_FLIGHT.value: 1}


def test_a_robot_announcing_more_in_flight_than_the_cap_is_counted_and_logged_once(
    daemon: CloudDaemon,
    robots_in_service: zenoh.Session,
    reference: SplitModel,
    caplog: pytest.LogCaptureFixture,
) -> None:
    ctl_key = keys.dep_ctl(daemon.cfg.fleet, "edge-1")
    for epoch in (2, 3):  # the registry passes it on with every service request
        ctl = CtlRequest(op=CtlOp.SERVICE, robot="robot-1", epoch=epoch, max_in_flight=4)
        replies = list(robots_in_service.get(ctl_key, payload=ctl.to_wire()))
        answer = decode(replies[0].ok.payload.to_bytes()) if replies and replies[0].ok else None
        assert isinstance(answer, CtlReply) and answer.ok, answer
    assert daemon.refusals.get(RefusalReason.IN_FLIGHT_CAP) == 1
    lines = [r.getMessage() for r in caplog.records if "keeps 4 frames in flight" in r.getMessage()]
    assert len(lines) == 1 and "admits 1 of its requests" in lines[0], lines
    # The cap of 1 holds: a second request in flight is answered busy.
    first, _ = request(reference, "robot-1", 1, seed=50)
    second, _ = request(reference, "robot-1", 1, seed=51)
    kinds = sorted(
        type(r).__name__ for r in send_together(robots_in_service, daemon, [first, second])
    )
    assert kinds == ["BusyReply", "InferReply"], kinds
