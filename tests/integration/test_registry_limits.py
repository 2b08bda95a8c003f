"""The registry's request limit (fleet.yaml `registry.max_request_bytes`) over real Zenoh on
loopback: a register or reroute request of one byte over the limit gets a `too_large` error reply
naming the limit and the field that sets it, one of exactly the limit is read; an oversized
telemetry record is dropped; every refusal is counted by input and code, and the counts are
logged when the registry stops. A limit above the old fixed 64 KiB lets a bigger request in, so
the limit is the configured one.

Requests are padded with a field the decoder ignores (wire messages tolerate unknown fields), so
the same message is valid at one size and refused at the next.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common import keys
from common.config import FleetConfig
from common.wire import ErrorCode, ErrorReply, Message, encode_raw
from common.wire.codec import SCHEMA_VERSION
from common.wire.registry import (
    PROTOCOL_VERSION,
    RegisterReply,
    RegisterRequest,
    RerouteRequest,
    RouteChange,
)
from tests.helpers import registry as reg
from tests.helpers.registry import (
    ROBOT,
    FakeDeployment,
    FakeRobot,
    RunningRegistry,
    ask,
    model_digest,
    wait_view,
    write_fleet,
)

# The registry fixtures, shared with test_registry.py.
peer = reg.peer
start_registry = reg.start_registry

SMALL_LIMIT = 2048
BIG_LIMIT = 128 * 1024
OLD_FIXED_LIMIT = 64 * 1024
PAD_FIELD = "pad_for_the_test"


def _fleet(tmp_path: Path, limit: int) -> FleetConfig:
    """test_registry's fleet with `registry.max_request_bytes: limit`."""
    _, base = write_fleet(tmp_path)
    registry = {
        "endpoint": base.registry.endpoint,
        "listen": base.registry.listen,
        "max_request_bytes": limit,
    }
    _, cfg = write_fleet(tmp_path, fleet=base.fleet, registry=registry)
    assert cfg.registry.max_request_bytes == limit
    return cfg


def padded(message: Message, size: int) -> bytes:
    """`message` on the wire, grown to exactly `size` bytes by a field nobody reads."""
    body: dict[str, Any] = {"v": SCHEMA_VERSION, "t": message.TYPE, **message.to_map()}
    pad = 0
    for _ in range(8):  # msgpack's length prefix grows with the pad: settles in a step or two
        data = encode_raw({**body, PAD_FIELD: b"x" * pad})
        if len(data) == size:
            return data
        pad += size - len(data)
        if pad < 0:
            raise ValueError(f"{message.TYPE} is {len(data)} bytes already, more than {size}")
    raise AssertionError(f"cannot pad {message.TYPE} to exactly {size} bytes")


def _register() -> RegisterRequest:
    return RegisterRequest(
        role="robot",
        id=ROBOT,
        protocol_version=PROTOCOL_VERSION,
        capabilities=("local_fallback",),
        service=reg.SERVICE,
    )


def _reroute() -> RerouteRequest:
    return RerouteRequest(robot=ROBOT, deployment="edge-1", epoch=1, reason="timeout")


def _too_large(session: zenoh.Session, key: str, payload: bytes, limit: int) -> ErrorReply:
    reply = ask(session, key, payload)
    assert isinstance(reply, ErrorReply), reply
    assert reply.code == ErrorCode.TOO_LARGE.value, reply
    assert f"{len(payload)} bytes" in reply.reason and f"limit of {limit} bytes" in reply.reason
    assert "registry.max_request_bytes" in reply.reason, reply.reason
    return reply


def test_requests_over_the_configured_limit_are_refused_named_and_counted(
    tmp_path: Path,
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="registry")
    cfg = _fleet(tmp_path, SMALL_LIMIT)
    registry = start_registry(cfg)
    digest = model_digest(cfg)
    for edge in ("edge-1", "edge-2"):
        FakeDeployment(peer(cfg), cfg, edge, digest=digest)
    robot = FakeRobot(peer(cfg), cfg)
    robot.wait_route("to edge-1", lambda c: c.deployment == "edge-1")
    session, refusals = peer(cfg), registry.daemon.refusals
    register_key, reroute_key = keys.reg_register(cfg.fleet), keys.reg_reroute(cfg.fleet)

    # One byte over: refused before it is unpacked, with the limit and its field named.
    _too_large(session, register_key, padded(_register(), SMALL_LIMIT + 1), SMALL_LIMIT)
    _too_large(session, reroute_key, padded(_reroute(), SMALL_LIMIT + 1), SMALL_LIMIT)
    _too_large(session, reroute_key, padded(_reroute(), 10 * SMALL_LIMIT), SMALL_LIMIT)
    assert refusals.get("register", ErrorCode.TOO_LARGE) == 1
    assert refusals.get("reroute", ErrorCode.TOO_LARGE) == 2

    # A telemetry record over the limit is dropped and counted; the good one after it is read.
    robot.session.put(keys.tele(cfg.fleet, ROBOT), padded(robot.record("edge-1", 0.02), 4096))
    robot.frame_done("edge-1", 0.02)
    wait_view(session, cfg, "robots", lambda rows: _window_len(rows) >= 1, "the good frame")
    assert refusals.get("telemetry", ErrorCode.TOO_LARGE) == 1

    # Exactly the limit: read and answered as usual (the reroute moves the robot to edge-2).
    accepted = ask(session, register_key, padded(_register(), SMALL_LIMIT))
    assert isinstance(accepted, RegisterReply) and accepted.accepted, accepted
    moved = ask(session, reroute_key, padded(_reroute(), SMALL_LIMIT))
    assert isinstance(moved, RouteChange) and moved.robot == ROBOT, moved
    assert refusals.snapshot() == {
        "register": {"too_large": 1},
        "reroute": {"too_large": 2},
        "telemetry": {"too_large": 1},
    }

    registry.stop()
    logged = [
        r.getMessage() for r in caplog.records if "refused (input, code, count)" in r.getMessage()
    ]
    assert logged and "register too_large 1" in logged[-1] and "reroute too_large 2" in logged[-1]


def test_a_limit_above_the_default_lets_a_bigger_request_in(
    tmp_path: Path,
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
) -> None:
    cfg = _fleet(tmp_path, BIG_LIMIT)
    registry = start_registry(cfg)
    session = peer(cfg)
    key = keys.reg_register(cfg.fleet)
    accepted = ask(session, key, padded(_register(), OLD_FIXED_LIMIT + 1024))
    assert isinstance(accepted, RegisterReply) and accepted.accepted, accepted
    _too_large(session, key, padded(_register(), BIG_LIMIT + 1), BIG_LIMIT)
    assert registry.daemon.refusals.snapshot() == {"register": {"too_large": 1}}


def _window_len(rows: tuple[Any, ...]) -> int:
    lengths = [getattr(r, "window_len", 0) for r in rows if getattr(r, "id", None) == ROBOT]
    return lengths[0] if lengths else 0
