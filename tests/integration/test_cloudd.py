"""The cloud daemon over real Zenoh on loopback, started in-process (its `run()` in a thread).

Each test plays the registry and the robot with real peer sessions and the wire messages of
`common/wire`: ctl service -> the robot's service key answers, every cut's result equals the full
model run here; standby -> it no longer answers; bad input of every kind gets an error reply that
names the problem and the next good request still succeeds; a full pool answers busy; a stale
epoch is refused; injected faults (delay, drop, stall) are observed; drain asks the registry
first; an unreachable registry is named in the log while the daemon serves.
"""

from __future__ import annotations

import dataclasses
import logging
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from cloudd.daemon import DRAIN_TIMEOUT_S, CloudDaemon
from common import keys
from common.config import FleetConfig, fleet_from_dict
from common.partition import load_partition, sample_feeds
from common.partition.runtime import SplitModel
from common.session import open_session
from common.wire import ErrorCode, ErrorReply, Message, decode, encode_raw
from common.wire.cloud_to_robot import BusyReply, InferReply
from common.wire.codec import SCHEMA_VERSION
from common.wire.registry import (
    CtlOp,
    CtlReply,
    CtlRequest,
    DeploymentState,
    DrainReply,
    DrainRequest,
    FaultSpec,
    ProbeReply,
    ProbeRequest,
)
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import EncodedTensor
from deploy.readiness import wait_until
from tests.integration.conftest import Router, find_free_port, loopback_endpoint
from tests.unit.test_cloudd_validate import TINY_BATCH, TINY_DIM, write_tiny_model

ROBOT = "robot-1"
SERVICE = "vision"
WAIT_S = 10.0
MAX_PAYLOAD_BYTES = 256 * 1024
STOP_WITHIN_S = 2.0
RESULT_ATOL = 1e-4
INJECTED_DELAY_S = 0.3
POLL_S = 0.05
SLOTS_RELEASED_S = 5.0
"""Bound of the wait for a deployment's slots to be free again after its requests are answered."""


# -- fixtures --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_model(tmp_path_factory.mktemp("model") / "tiny.onnx")


@pytest.fixture(scope="module")
def reference(tiny_path: Path) -> SplitModel:
    """The same split as the daemon's (same cache entry), run here as the robot would."""
    return SplitModel(load_partition(str(tiny_path)), lazy=True)


def fleet_config(
    model: Path, endpoint: str, fleet: str, *, listen: str = "tcp/127.0.0.1:0", **machine: Any
) -> FleetConfig:
    data = {
        "fleet": fleet,
        "service": SERVICE,
        "model": str(model),
        "registry": {"endpoint": endpoint, "listen": [endpoint]},
        "machines": {
            "edge-1": {"role": "cloud", "listen": [listen], **machine},
            ROBOT: {"role": "robot", "listen": ["tcp/127.0.0.1:0"]},
        },
        "initial_policy": {"edge-1": "service"},
        "latency_bound": {"seconds": 0.5},
        "deadline_s": 1.0,
        "max_payload_bytes": MAX_PAYLOAD_BYTES,
    }
    return fleet_from_dict(data)


@pytest.fixture
def start_cloud(zenoh_router: Router, tiny_path: Path) -> Iterator[Callable[..., CloudDaemon]]:
    """`start_cloud(endpoint=None, fault=None, listen=..., **machine)` -> a ready CloudDaemon
    running in a thread; stopped (and checked to have stopped) at teardown."""
    running: list[tuple[CloudDaemon, threading.Thread]] = []
    fleet = f"t-{uuid.uuid4().hex[:8]}"

    def start(
        *, endpoint: str | None = None, fault: FaultSpec | None = None, **machine: Any
    ) -> CloudDaemon:
        cfg = fleet_config(tiny_path, endpoint or zenoh_router.endpoint, fleet, **machine)
        daemon = CloudDaemon(cfg, "edge-1", fault=fault)
        errors: list[BaseException] = []

        def run() -> None:
            try:
                daemon.run()
            except BaseException as exc:
                errors.append(exc)

        thread = threading.Thread(target=run, name="cloud-edge-1", daemon=True)
        thread.start()
        running.append((daemon, thread))
        deadline = time.monotonic() + WAIT_S * 3  # the first start splits the model
        while not daemon.ready.wait(POLL_S):
            if not thread.is_alive() or time.monotonic() > deadline:
                pytest.fail(f"edge-1 did not become ready: {errors or 'timeout'}")
        return daemon

    try:
        yield start
    finally:
        for daemon, thread in reversed(running):
            daemon.stop()
            thread.join(WAIT_S)
            assert not thread.is_alive(), "the daemon did not stop"


# -- helpers ---------------------------------------------------------------------------------------
def ask(
    session: zenoh.Session, key: str, payload: bytes | None = None, timeout_s: float = 5.0
) -> list[Message]:
    """Every decoded reply to one get."""
    kwargs: dict[str, Any] = {"timeout": timeout_s}
    if payload is not None:
        kwargs["payload"] = payload
    return [decode(r.ok.payload.to_bytes()) for r in session.get(key, **kwargs) if r.ok is not None]


def ask_one(session: zenoh.Session, key: str, payload: bytes | None = None) -> Message:
    replies = ask(session, key, payload)
    assert len(replies) == 1, f"{key}: {len(replies)} replies: {replies!r}"
    return replies[0]


def wait_reply(session: zenoh.Session, key: str, payload: bytes | None = None) -> Message:
    """The first reply on `key`, asking again until one comes (a declaration still on its way
    from the daemon to this session), or fail after WAIT_S."""
    replies = wait_until(
        lambda: ask(session, key, payload, timeout_s=1.0),
        timeout_s=WAIT_S,
        what=f"a reply on {key}",
        interval_s=POLL_S,
    )
    return replies[0]


def probe_key(daemon: CloudDaemon) -> str:
    return keys.dep_probe(daemon.cfg.fleet, "edge-1")


def ctl_key(daemon: CloudDaemon) -> str:
    return keys.dep_ctl(daemon.cfg.fleet, "edge-1")


def svc_key(daemon: CloudDaemon) -> str:
    return keys.svc_infer(daemon.cfg.fleet, SERVICE, ROBOT)


def ctl(
    session: zenoh.Session, daemon: CloudDaemon, op: CtlOp, epoch: int = 0, **fields: Any
) -> CtlReply:
    robot = fields.pop("robot", ROBOT if op in (CtlOp.SERVICE, CtlOp.STANDBY) else None)
    request = CtlRequest(op=op, robot=robot, epoch=epoch, sender="test", **fields)
    reply = ask_one(session, ctl_key(daemon), request.to_wire())
    assert isinstance(reply, CtlReply), reply
    return reply


def probe(session: zenoh.Session, daemon: CloudDaemon, **fields: Any) -> ProbeReply:
    request = ProbeRequest(sender="test", sent_at=time.time(), **fields)
    reply = ask_one(session, probe_key(daemon), request.to_wire())
    assert isinstance(reply, ProbeReply), reply
    return reply


def infer_request(
    model: SplitModel, cut: int, frame: int = 0, feeds: dict[str, np.ndarray] | None = None
) -> InferRequest:
    feeds = feeds if feeds is not None else sample_feeds(model.input_specs(), seed=frame)
    return InferRequest(
        robot=ROBOT,
        frame=frame,
        model_digest=model.digest,
        cut=cut,
        tensors={n: EncodedTensor.raw(a) for n, a in model.run_prefix(cut, feeds).items()},
        deadline_s=5.0,
        sent_at=time.time(),
    )


def connect(open_peer: Callable[..., zenoh.Session], daemon: CloudDaemon, wait: Any) -> Any:
    """A peer session that sees the daemon (its token and its probe queryable)."""
    session = open_peer()
    wait(session, keys.alive_deployment(daemon.cfg.fleet, "edge-1"))
    assert isinstance(wait_reply(session, probe_key(daemon)), ProbeReply)
    return session


def serve(session: zenoh.Session, daemon: CloudDaemon, model: SplitModel, epoch: int = 1) -> None:
    """Put ROBOT in service at `epoch` and wait until its service key answers here."""
    reply = ctl(session, daemon, CtlOp.SERVICE, epoch)
    assert reply.ok and reply.state is DeploymentState.SERVICE and reply.epoch == epoch, reply
    answer = wait_reply(session, svc_key(daemon), infer_request(model, 0).to_wire())
    assert isinstance(answer, InferReply), answer


# -- tests -----------------------------------------------------------------------------------------
def test_starts_in_standby_and_answers_probes(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud(workers=2, queue=3)
    session = connect(open_peer, daemon, wait_for_token)
    reply = probe(session, daemon, echo_bytes=1000, padding=b"x" * 5000)
    assert reply.deployment == "edge-1" and reply.service == SERVICE
    assert reply.model_digest == reference.digest
    assert reply.num_cuts == reference.num_cuts >= 3
    assert reply.states == {ROBOT: DeploymentState.STANDBY}
    assert (reply.load, reply.capacity) == (0, 5)
    assert len(reply.echo) == 1000
    assert {"infer", "probe", "ctl"} <= set(reply.capabilities)
    # Never a service key on its own: the robot's key has no queryable.
    assert ask(session, svc_key(daemon), infer_request(reference, 0).to_wire(), 1.0) == []
    # The probe wildcard of every deployment reaches it too, and an empty probe is a profile.
    found = ask(session, keys.dep_probe_all(daemon.cfg.fleet), None, 2.0)
    assert [r.deployment for r in found if isinstance(r, ProbeReply)] == ["edge-1"]


def test_service_computes_every_cut_like_the_full_model_then_standby_stops_answering(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud()
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference, epoch=1)
    feeds = sample_feeds(reference.input_specs(), seed=11)
    full = reference.run_full(feeds)
    for cut in range(reference.num_cuts):
        request = infer_request(reference, cut, frame=100 + cut, feeds=feeds)
        reply = ask_one(session, svc_key(daemon), request.to_wire())
        assert isinstance(reply, InferReply), f"cut {cut}: {reply!r}"
        assert (reply.frame, reply.deployment, reply.epoch) == (100 + cut, "edge-1", 1)
        assert reply.queue_s >= 0 and reply.compute_s > 0
        assert set(reply.outputs) == set(full)
        for name, expected in full.items():
            err = float(np.max(np.abs(reply.outputs[name] - expected)))
            assert err <= RESULT_ATOL, f"cut {cut} output {name}: max abs error {err}"
    profile = probe(session, daemon)
    assert profile.states == {ROBOT: DeploymentState.SERVICE} and profile.epochs == {ROBOT: 1}
    assert profile.served[ROBOT] == reference.num_cuts + 1  # + the readiness request of serve()

    reply = ctl(session, daemon, CtlOp.STANDBY, 2)
    assert reply.ok and reply.state is DeploymentState.STANDBY and reply.epoch == 2
    # Undeclared before the ack: nothing answers the robot's key any more.
    assert ask(session, svc_key(daemon), infer_request(reference, 0).to_wire(), 1.0) == []
    assert probe(session, daemon).states == {ROBOT: DeploymentState.STANDBY}


def test_stale_epochs_are_refused_with_the_daemons_own_state(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud()
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference, epoch=5)
    stale = ctl(session, daemon, CtlOp.STANDBY, 4)
    assert not stale.ok and "stale epoch 4" in stale.reason
    assert (stale.state, stale.epoch) == (DeploymentState.SERVICE, 5)
    assert not ctl(session, daemon, CtlOp.SERVICE, 3).ok
    again = ctl(session, daemon, CtlOp.SERVICE, 5)
    assert again.ok and again.epoch == 5, "the same service request again is acknowledged"
    # Still serving after the refusals.
    reply = ask_one(session, svc_key(daemon), infer_request(reference, 1).to_wire())
    assert isinstance(reply, InferReply) and reply.epoch == 5
    assert ctl(session, daemon, CtlOp.STANDBY, 6).ok
    late = ctl(session, daemon, CtlOp.SERVICE, 6)
    assert not late.ok and (late.state, late.epoch) == (DeploymentState.STANDBY, 6)
    assert ctl(session, daemon, CtlOp.SERVICE, 7).ok


def _raw_request(reference: SplitModel, **changes: Any) -> bytes:
    body: dict[str, Any] = {
        "v": SCHEMA_VERSION,
        "t": "infer_request",
        "robot": ROBOT,
        "frame": 1,
        "model_digest": reference.digest,
        "cut": 0,
        "tensors": {
            "x": {
                "codec": "raw",
                "dtype": "float32",
                "shape": [TINY_BATCH, TINY_DIM],
                "data": bytes(4 * 16384),
            }
        },
        "deadline_s": 1.0,
        "sent_at": 0.0,
    }
    body.update(changes)
    return encode_raw(body)


def _bad_infer_cases(reference: SplitModel) -> list[tuple[str, bytes | None, ErrorCode, str]]:
    good = infer_request(reference, 0)
    x = np.frombuffer(good.tensors["x"].data, np.float32).reshape(TINY_BATCH, TINY_DIM)

    def with_tensors(**tensors: np.ndarray) -> bytes:
        encoded = {n: EncodedTensor.raw(a) for n, a in tensors.items()}
        return dataclasses.replace(good, tensors=encoded).to_wire()

    return [
        ("garbage bytes", b"\xc1\xff\x00garbage", ErrorCode.MALFORMED, "not a msgpack"),
        ("empty payload", None, ErrorCode.MALFORMED, "empty payload"),
        ("trailing bytes", good.to_wire() + b"\x00", ErrorCode.TRAILING_BYTES, "trailing"),
        ("schema version", _raw_request(reference, v=99), ErrorCode.SCHEMA_VERSION, "99"),
        (
            "wrong message type",
            ProbeRequest(sender=ROBOT, sent_at=0.0).to_wire(),
            ErrorCode.UNEXPECTED_TYPE,
            "'probe'",
        ),
        (
            "dtype not allowed",
            _raw_request(
                reference,
                tensors={
                    "x": {"codec": "raw", "dtype": "complex64", "shape": [1], "data": bytes(8)}
                },
            ),
            ErrorCode.BAD_DTYPE,
            "complex64",
        ),
        ("wrong dtype", with_tensors(x=x.astype(np.float64)), ErrorCode.BAD_DTYPE, "float64"),
        (
            "byte count",
            _raw_request(
                reference,
                tensors={
                    "x": {"codec": "raw", "dtype": "float32", "shape": [32, 512], "data": b"1"}
                },
            ),
            ErrorCode.SHAPE_MISMATCH,
            "needs 65536 bytes",
        ),
        (
            "wrong shape",
            with_tensors(x=x.reshape(TINY_BATCH * 2, TINY_DIM // 2)),
            ErrorCode.SHAPE_MISMATCH,
            f"expected [{TINY_BATCH}, {TINY_DIM}]",
        ),
        ("oversize", bytes(MAX_PAYLOAD_BYTES + 1), ErrorCode.TOO_LARGE, "exceeds the limit"),
        (
            "unknown cut",
            dataclasses.replace(good, cut=99).to_wire(),
            ErrorCode.UNKNOWN_CUT,
            "unknown cut 99",
        ),
        (
            "wrong digest",
            dataclasses.replace(good, model_digest="0" * 64).to_wire(),
            ErrorCode.MODEL_DIGEST,
            "000000000000",
        ),
        ("missing tensor", with_tensors(y=x), ErrorCode.MISSING_FIELD, "missing 'x'"),
        (
            "another robot",
            dataclasses.replace(good, robot="robot-2").to_wire(),
            ErrorCode.WRONG_ROBOT,
            "'robot-2'",
        ),
        ("bad value", _raw_request(reference, frame=-1), ErrorCode.BAD_VALUE, "frame"),
    ]


def test_bad_input_gets_a_named_error_and_the_daemon_keeps_serving(
    start_cloud, open_peer, wait_for_token, reference: SplitModel, caplog
) -> None:
    caplog.set_level(logging.INFO)
    daemon = start_cloud()
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference, epoch=1)
    good = infer_request(reference, 1, frame=7).to_wire()

    def expect_error(
        key: str, what: str, payload: bytes | None, code: ErrorCode, needle: str
    ) -> None:
        reply = ask_one(session, key, payload)
        assert isinstance(reply, ErrorReply), f"{what}: {reply!r}"
        assert reply.code == code.value, f"{what}: {reply.code} ({reply.reason})"
        assert needle in reply.reason, f"{what}: {needle!r} not in {reply.reason!r}"

    for what, payload, code, needle in _bad_infer_cases(reference):
        expect_error(svc_key(daemon), what, payload, code, needle)
        after = ask_one(session, svc_key(daemon), good)
        assert isinstance(after, InferReply), f"after {what}: {after!r}"

    ctl_cases: list[tuple[str, bytes | None, ErrorCode, str]] = [
        ("garbage ctl", b"\x91\x01", ErrorCode.MALFORMED, "expected a map"),
        ("empty ctl", None, ErrorCode.MALFORMED, "empty payload"),
        ("service without robot", encode_raw({"v": SCHEMA_VERSION, "t": "ctl", "op": "service"}), ErrorCode.BAD_VALUE, "robot"),  # noqa: E501
        ("unknown op", encode_raw({"v": SCHEMA_VERSION, "t": "ctl", "op": "reboot"}), ErrorCode.BAD_VALUE, "reboot"),  # noqa: E501
        ("ctl schema", encode_raw({"v": SCHEMA_VERSION + 1, "t": "ctl", "op": "drain"}), ErrorCode.SCHEMA_VERSION, str(SCHEMA_VERSION + 1)),  # noqa: E501
        ("fault drop > 1", encode_raw({"v": SCHEMA_VERSION, "t": "ctl", "op": "fault", "fault": {"drop": 2.0}}), ErrorCode.BAD_VALUE, "drop"),  # noqa: E501
    ]  # fmt: skip
    for what, payload, code, needle in ctl_cases:
        expect_error(ctl_key(daemon), what, payload, code, needle)
        assert ctl(session, daemon, CtlOp.SERVICE, 1).ok, f"ctl after {what}"

    probe_cases: list[tuple[str, bytes | None, ErrorCode, str]] = [
        ("garbage probe", b"\xc1garbage", ErrorCode.MALFORMED, "not a msgpack"),
        ("negative echo", encode_raw({"v": SCHEMA_VERSION, "t": "probe", "sender": "x", "sent_at": 0.0, "echo_bytes": -5}), ErrorCode.BAD_VALUE, "echo_bytes"),  # noqa: E501
        ("huge echo", encode_raw({"v": SCHEMA_VERSION, "t": "probe", "sender": "x", "sent_at": 0.0, "echo_bytes": 1 << 30}), ErrorCode.BAD_VALUE, "echo_bytes"),  # noqa: E501
        ("probe oversize", bytes(MAX_PAYLOAD_BYTES + 1), ErrorCode.TOO_LARGE, "exceeds"),
    ]  # fmt: skip
    for what, payload, code, needle in probe_cases:
        expect_error(probe_key(daemon), what, payload, code, needle)
        assert probe(session, daemon).deployment == "edge-1", f"probe after {what}"

    # Nothing logged as a crash; one warning per bad request, naming the robot or the key.
    records = [r for r in caplog.records if r.name.startswith("cloudd")]
    assert not [r for r in records if r.levelno >= logging.ERROR or r.exc_info], [
        r.getMessage() for r in records if r.levelno >= logging.ERROR
    ]
    warnings = [r.getMessage() for r in records if r.levelno == logging.WARNING]
    infer_warnings = [w for w in warnings if ROBOT in w]
    assert len(infer_warnings) == len(_bad_infer_cases(reference)), warnings
    assert len([w for w in warnings if "bad ctl request" in w]) == len(ctl_cases)
    assert len([w for w in warnings if "bad probe request" in w]) == len(probe_cases)
    assert probe(session, daemon).served[ROBOT] == len(_bad_infer_cases(reference)) + 1


def test_a_full_pool_answers_busy_at_once(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud(workers=1, queue=0)
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference)
    burst = 12
    payloads = [infer_request(reference, 0, frame=f).to_wire() for f in range(burst)]
    handlers = [session.get(svc_key(daemon), payload=p, timeout=10.0) for p in payloads]
    replies = [[decode(r.ok.payload.to_bytes()) for r in h if r.ok is not None] for h in handlers]
    assert all(len(r) == 1 for r in replies), "each request gets exactly one reply"
    kinds = [type(r[0]).__name__ for r in replies]
    busy = [r[0] for r in replies if isinstance(r[0], BusyReply)]
    assert busy and "InferReply" in kinds, kinds
    assert all(b.capacity == 1 and b.queued >= 1 and b.deployment == "edge-1" for b in busy)
    # A worker releases its slot just after its reply is sent: poll the probe, bounded in time.
    wait_until(
        lambda: probe(session, daemon).load == 0,
        timeout_s=SLOTS_RELEASED_S,
        what="every slot released",
        interval_s=POLL_S,
    )


def test_injected_delay_from_start_and_from_ctl_delays_replies(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud(fault=FaultSpec(delay_ms=INJECTED_DELAY_S * 1000))
    session = connect(open_peer, daemon, wait_for_token)

    def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
        t0 = time.monotonic()
        result = fn()
        return result, time.monotonic() - t0

    profile, took = timed(lambda: probe(session, daemon))
    assert took >= INJECTED_DELAY_S, f"probe answered in {took:.3f} s despite the delay"
    assert profile.fault.delay_ms == INJECTED_DELAY_S * 1000

    assert ctl(session, daemon, CtlOp.FAULT, fault=FaultSpec()).ok
    _, took = timed(lambda: probe(session, daemon))
    assert took < INJECTED_DELAY_S, f"probe took {took:.3f} s without a delay"

    serve(session, daemon, reference)
    assert ctl(session, daemon, CtlOp.FAULT, fault=FaultSpec(delay_ms=300)).ok
    request = infer_request(reference, 1).to_wire()
    reply, took = timed(lambda: ask_one(session, svc_key(daemon), request))
    assert isinstance(reply, InferReply)
    assert took >= INJECTED_DELAY_S, f"inference answered in {took:.3f} s despite the delay"
    assert reply.compute_s < took - INJECTED_DELAY_S + 0.05, "the delay is not compute time"


def test_drop_and_stall_leave_requests_unanswered_until_cleared(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud()
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference)
    assert ctl(session, daemon, CtlOp.FAULT, fault=FaultSpec(drop=1.0)).ok
    timeout_s = 0.5
    request = infer_request(reference, 0).to_wire()
    t0 = time.monotonic()
    assert ask(session, svc_key(daemon), request, timeout_s) == []
    took = time.monotonic() - t0
    assert took >= timeout_s * 0.9, f"a dropped request ended after {took:.3f} s, not a timeout"
    assert isinstance(probe(session, daemon), ProbeReply), "drop spares probes"

    assert ctl(session, daemon, CtlOp.FAULT, fault=FaultSpec(stall=True)).ok
    t0 = time.monotonic()
    assert ask(session, probe_key(daemon), None, timeout_s) == [], "a stalled host is silent"
    assert time.monotonic() - t0 >= timeout_s * 0.9
    assert ask(session, svc_key(daemon), request, timeout_s) == []
    assert ctl(session, daemon, CtlOp.FAULT, fault=FaultSpec()).ok, "ctl still obeyed"
    assert isinstance(ask_one(session, svc_key(daemon), request), InferReply)
    assert probe(session, daemon).fault == FaultSpec()


def test_drain_asks_the_registry_to_move_its_robots_then_stops(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud()
    fleet = daemon.cfg.fleet
    registry = connect(open_peer, daemon, wait_for_token)
    asked: list[DrainRequest] = []

    def move_robots(query: zenoh.Query) -> None:
        # As the registry does: move the robot away (standby at a newer epoch), then answer.
        payload = query.payload.to_bytes() if query.payload is not None else b""
        asked.append(DrainRequest.from_wire(payload))
        standby = ctl(registry, daemon, CtlOp.STANDBY, 2)
        reply = DrainReply(ok=standby.ok, moved=(ROBOT,) if standby.ok else ())
        query.reply(keys.reg_drain(fleet), reply.to_wire())
        query.drop()

    def on_drain(query: zenoh.Query) -> None:
        threading.Thread(target=move_robots, args=(query,), daemon=True).start()

    queryable = registry.declare_queryable(keys.reg_drain(fleet), on_drain)
    try:
        serve(registry, daemon, reference, epoch=1)
        thread = next(t for t in threading.enumerate() if t.name == "cloud-edge-1")
        t0 = time.monotonic()
        daemon.stop(drain=True)
        thread.join(WAIT_S)
        took = time.monotonic() - t0
    finally:
        queryable.undeclare()
    assert not thread.is_alive()
    assert took <= STOP_WITHIN_S, f"drain and stop took {took:.2f} s"
    assert [a.deployment for a in asked] == ["edge-1"]
    assert daemon.drained.is_set()
    assert daemon.states()[ROBOT].state is DeploymentState.STANDBY


def test_drain_without_a_registry_still_stops_in_time(
    start_cloud, open_peer, wait_for_token, reference: SplitModel, caplog
) -> None:
    caplog.set_level(logging.INFO)
    daemon = start_cloud()
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference, epoch=1)
    thread = next(t for t in threading.enumerate() if t.name == "cloud-edge-1")
    t0 = time.monotonic()
    daemon.stop(drain=True)
    thread.join(WAIT_S)
    assert time.monotonic() - t0 <= STOP_WITHIN_S
    assert not daemon.drained.is_set()
    text = caplog.text
    assert "no registry answered the drain request" in text and "still serving robot-1" in text
    # Stopped: its token and its keys are gone.
    assert ask(session, probe_key(daemon), None, 1.0) == []


def test_drain_with_a_silent_registry_waits_its_timeout_and_still_stops_in_time(
    start_cloud, open_peer, wait_for_token, reference: SplitModel
) -> None:
    daemon = start_cloud()
    registry = connect(open_peer, daemon, wait_for_token)
    held: list[zenoh.Query] = []
    queryable = registry.declare_queryable(keys.reg_drain(daemon.cfg.fleet), held.append)
    try:
        serve(registry, daemon, reference, epoch=1)
        thread = next(t for t in threading.enumerate() if t.name == "cloud-edge-1")
        t0 = time.monotonic()
        daemon.stop(drain=True)
        thread.join(WAIT_S)
        took = time.monotonic() - t0
    finally:
        for query in held:
            query.drop()
        queryable.undeclare()
    assert len(held) == 1, "the drain request reached the registry"
    assert DRAIN_TIMEOUT_S * 0.9 <= took <= STOP_WITHIN_S, f"stopped after {took:.2f} s"
    assert not daemon.drained.is_set()


def test_unreachable_registry_is_named_and_the_daemon_serves_meanwhile(
    start_cloud, reference: SplitModel, caplog
) -> None:
    caplog.set_level(logging.WARNING)
    nobody = loopback_endpoint(find_free_port())
    port = find_free_port()
    daemon = start_cloud(endpoint=nobody, listen=loopback_endpoint(port))
    assert not daemon.registry_seen.is_set()
    assert f"the registry at {nobody} is not reachable yet" in caplog.text
    # Peers can reach it directly anyway.
    session = open_session(
        mode="peer", connect=[loopback_endpoint(port)], listen=["tcp/127.0.0.1:0"]
    )
    try:
        reply = wait_reply(session, probe_key(daemon))
        assert isinstance(reply, ProbeReply) and reply.model_digest == reference.digest
    finally:
        session.close()


def test_registry_token_is_followed(start_cloud, open_peer, zenoh_router: Router) -> None:
    daemon = start_cloud()
    registry = open_peer()
    token = registry.liveliness().declare_token(keys.alive_registry(daemon.cfg.fleet, "registry"))
    try:
        assert daemon.registry_seen.wait(WAIT_S), "the registry's token was not seen"
    finally:
        token.undeclare()
    wait_until(
        lambda: not daemon.registry_seen.is_set(),
        timeout_s=WAIT_S,
        what="the registry's token seen to go",
        interval_s=POLL_S,
    )


def test_port_in_use_is_a_clear_error(start_cloud) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(pytest.fail.Exception, match="cannot open a Zenoh peer session"):
            start_cloud(listen=loopback_endpoint(port))
