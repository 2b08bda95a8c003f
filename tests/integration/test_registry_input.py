"""Bad input to every registry queryable gets an error reply naming the problem, bad
publications are logged and dropped, a deployment answering garbage is skipped; the registry
keeps serving and logs nothing as a crash (no ERROR record, no traceback)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from common import keys
from common.config import FleetConfig
from common.wire import ErrorCode, ErrorReply, encode_raw
from common.wire.codec import SCHEMA_VERSION
from common.wire.registry import (
    PROTOCOL_VERSION,
    DrainRequest,
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
    Fleet,
    RunningRegistry,
    ask,
    model_digest,
    view,
    wait_view,
)

# The registry fixtures, shared with test_registry.py.
fleet = reg.fleet
peer = reg.peer
routed = reg.routed
start_registry = reg.start_registry

GARBAGE = b"\xc1 this is not msgpack"
OVERSIZE = encode_raw({"v": SCHEMA_VERSION, "t": "rib_query", "pad": b"x" * (70 * 1024)})


@pytest.fixture
def no_crash_logged(caplog: pytest.LogCaptureFixture) -> Iterator[pytest.LogCaptureFixture]:
    """Fails the test if the registry logs an ERROR (what a crash or a traceback looks like)."""
    caplog.set_level(logging.INFO, logger="registry")
    yield caplog
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert not errors, [r.getMessage() for r in errors]


def _error(session: zenoh.Session, key: str, payload: bytes | None) -> ErrorReply:
    reply = ask(session, key, payload)
    assert isinstance(reply, ErrorReply), reply
    return reply


def _bad_cases(fleet_name: str) -> list[tuple[str, bytes, ErrorCode, str]]:
    """(key, payload, expected code, a word of the reason) for every registry queryable."""
    cases: list[tuple[str, bytes, ErrorCode, str]] = []
    requests = {
        keys.reg_register(fleet_name): "register",
        keys.reg_reroute(fleet_name): "reroute",
        keys.reg_drain(fleet_name): "drain",
        **{keys.rib(fleet_name, v): "rib_query" for v in keys.RIB_VIEWS},
    }
    for key, tag in requests.items():
        cases += [
            (key, GARBAGE, ErrorCode.MALFORMED, "msgpack"),
            (key, encode_raw({"v": 99, "t": tag}), ErrorCode.SCHEMA_VERSION, "99"),
            (
                key,
                encode_raw({"v": SCHEMA_VERSION, "t": "no_such_message"}),
                ErrorCode.UNKNOWN_TYPE,
                "no_such",
            ),
            (key, OVERSIZE, ErrorCode.TOO_LARGE, "exceeds"),
            (
                key,
                encode_raw({"v": SCHEMA_VERSION, "t": tag}) + b"\x00",
                ErrorCode.TRAILING_BYTES,
                "trailing",
            ),
        ]
        if tag != "rib_query":  # a view accepts an empty query; requests need their fields
            cases.append(
                (
                    key,
                    encode_raw({"v": SCHEMA_VERSION, "t": tag}),
                    ErrorCode.MISSING_FIELD,
                    "missing",
                )
            )
    cases += [
        (
            keys.reg_reroute(fleet_name),
            DrainRequest(deployment="edge-1").to_wire(),
            ErrorCode.UNEXPECTED_TYPE,
            "'reroute'",
        ),
        (
            keys.reg_drain(fleet_name),
            encode_raw({"v": SCHEMA_VERSION, "t": "drain", "deployment": 7}),
            ErrorCode.WRONG_TYPE,
            "drain.deployment",
        ),
        (
            keys.reg_drain(fleet_name),
            encode_raw({"v": SCHEMA_VERSION, "t": "drain", "deployment": "a/b"}),
            ErrorCode.BAD_VALUE,
            "'/'",
        ),
        (
            keys.rib(fleet_name, "events"),
            encode_raw({"v": SCHEMA_VERSION, "t": "rib_query", "limit": -1}),
            ErrorCode.BAD_VALUE,
            "limit",
        ),
    ]
    return cases


def test_bad_input_to_every_queryable_gets_a_named_error(
    routed: Fleet, no_crash_logged: pytest.LogCaptureFixture
) -> None:
    session, fleet_name = routed.observer, routed.cfg.fleet
    for key, payload, code, word in _bad_cases(fleet_name):
        error = _error(session, key, payload)
        assert (error.code, word in error.reason) == (code.value, True), (key, error)

    # Well-formed but refused: unknown deployment, unknown robot, unknown view.
    drain = _error(session, keys.reg_drain(fleet_name), DrainRequest(deployment="edge-9").to_wire())
    assert drain.code == ErrorCode.REFUSED.value and "edge-9" in drain.reason
    reroute = RerouteRequest(robot="robot-9", deployment=None, epoch=0, reason="timeouts")
    error = _error(session, keys.reg_reroute(fleet_name), reroute.to_wire())
    assert error.code == ErrorCode.REFUSED.value and "robot-9" in error.reason
    bogus = keys.rib_all(fleet_name).replace("*", "bogus")
    error = _error(session, bogus, None)
    assert "no RIB view" in error.reason and "routes" in error.reason

    # Still serving, state untouched.
    [route] = view(session, routed.cfg, "routes")
    assert (route.deployment, route.epoch) == ("edge-1", 1)


def test_registration_requests_are_checked(
    routed: Fleet, no_crash_logged: pytest.LogCaptureFixture
) -> None:
    session, cfg = routed.observer, routed.cfg
    key = keys.reg_register(cfg.fleet)

    def register(**changes: object) -> RegisterReply:
        fields: dict[str, object] = {
            "role": "robot",
            "id": ROBOT,
            "protocol_version": PROTOCOL_VERSION,
            "capabilities": ("local_fallback",),
            "service": cfg.service,
        }
        fields.update(changes)
        reply = ask(session, key, RegisterRequest(**fields).to_wire())  # type: ignore[arg-type]
        assert isinstance(reply, RegisterReply)
        return reply

    accepted = register()
    assert accepted.accepted and accepted.route is not None
    assert (accepted.route.deployment, accepted.route.epoch) == ("edge-1", 1)
    cases: list[tuple[dict[str, object], str]] = [
        ({"protocol_version": PROTOCOL_VERSION + 1}, "protocol"),
        ({"service": "other"}, "'other'"),
        ({"capabilities": ()}, "local_fallback"),
        (
            {
                "role": "cloud",
                "id": "edge-7",
                "capabilities": ("infer", "probe", "ctl"),
                "model_digest": "f" * 64,
            },
            "model",
        ),
    ]
    for changes, word in cases:
        refused = register(**changes)
        assert not refused.accepted and word in refused.reason, (changes, refused)
    refusals = [e for e in view(session, cfg, "events") if e.kind == "registration_refused"]
    assert len(refusals) == 4


def test_bad_publications_are_logged_and_dropped(
    routed: Fleet, no_crash_logged: pytest.LogCaptureFixture
) -> None:
    robot, cfg = routed.robot, routed.cfg
    robot.session.put(keys.tele(cfg.fleet, ROBOT), GARBAGE)
    robot.session.put(keys.tele_probe(cfg.fleet, ROBOT), encode_raw({"v": 7, "t": "probe_report"}))
    # A record about another robot on this robot's key is refused too.
    stray = robot.record("edge-1", 0.02, robot="robot-2")
    robot.session.put(keys.tele(cfg.fleet, ROBOT), stray.to_wire())
    for _ in range(5):
        robot.frame_done("edge-1", 0.02)
    wait_view(
        routed.observer, cfg, "robots", lambda rows: _window_len(rows) == 5, "the good frames"
    )
    warnings = [r.getMessage() for r in no_crash_logged.records if r.levelno == logging.WARNING]
    assert any("telemetry" in w and "msgpack" in w for w in warnings), warnings
    assert any("probe report" in w and "7" in w for w in warnings), warnings
    assert any("robot-2" in w for w in warnings), warnings


def _window_len(rows: tuple[object, ...]) -> int:
    lengths = [getattr(r, "window_len", 0) for r in rows if getattr(r, "id", None) == ROBOT]
    return lengths[0] if lengths else 0


def test_a_deployment_answering_garbage_is_skipped(
    fleet: tuple[Path, FleetConfig],
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
    no_crash_logged: pytest.LogCaptureFixture,
) -> None:
    """edge-1 (initial_policy's choice) answers its ctl with garbage: the switch records why and
    the robot is routed to edge-2 instead."""
    _, cfg = fleet
    start_registry(cfg)
    digest = model_digest(cfg)
    FakeDeployment(peer(cfg), cfg, "edge-1", digest=digest, ctl_answer=GARBAGE)
    FakeDeployment(peer(cfg), cfg, "edge-2", digest=digest)
    robot = FakeRobot(peer(cfg), cfg)
    change = robot.wait_route("assigned", lambda c: c.deployment is not None)
    assert isinstance(change, RouteChange) and change.deployment == "edge-2"
    failed = [e for e in view(peer(cfg), cfg, "events") if e.kind == "ack_failed"]
    assert failed and "bad reply" in failed[0].reason and "edge-1" in failed[0].reason
