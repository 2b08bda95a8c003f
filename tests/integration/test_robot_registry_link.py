"""The robot's registry link over real Zenoh sessions on loopback, against an in-test registry: its
liveliness token (followed by a real `MembershipView`, as the robot daemon does) and queryables on
`reg/register` and `reg/reroute` answering with real wire messages.

What must hold: while no registry is up the link says so, naming the endpoint; when one appears
it registers (protocol, capabilities, model digest) and takes the route from the reply; when it
goes the link says so and keeps the route. Routes only move forward in epochs, another robot's
route is ignored, and garbage on the route key is one warning. A reroute is asked only while a
registry is up, at most once per interval, and its answer is applied. `stop()` wakes at once a
watcher that waits without a timeout for the registry to go (it waits on the link's condition
variable, which `stop()` notifies).
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh

from common import keys
from common.daemon import Daemon
from common.membership import MembershipView
from common.throttled_log import ThrottledLog
from common.wire import ErrorCode, ErrorReply
from common.wire.registry import (
    CAP_LOCAL_FALLBACK,
    NO_CAPACITY_REASON,
    PROTOCOL_VERSION,
    RegisterReply,
    RegisterRequest,
    RerouteRequest,
    RouteChange,
)
from common.wire.telemetry import FallbackReason
from robotd.frame_path.registry_link import RegistryLink
from tests.integration.conftest import Router
from tests.integration.test_robotd import fleet_config

FLEET = "link-it"
ROBOT = "robot-1"
DIGEST = "d" * 64
WAIT_S = 10.0
# stop() must not wait out a registration or a slice: the watcher wakes on the condition.
STOP_WITHIN_S = 0.5


def route(epoch: int, deployment: str | None = "edge-1", robot: str = ROBOT) -> RouteChange:
    return RouteChange(robot=robot, deployment=deployment, epoch=epoch, reason="test", at=0.0)


class LogWatch(logging.Handler):
    """Collects the robot's log lines; `wait_for(text)` blocks until one contains `text`."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []
        self._changed = threading.Condition()

    def emit(self, record: logging.LogRecord) -> None:
        with self._changed:
            self.lines.append(record.getMessage())
            self._changed.notify_all()

    def wait_for(self, text: str, timeout_s: float = WAIT_S) -> str:
        def found() -> str | None:
            return next((line for line in self.lines if text in line), None)

        with self._changed:
            if not self._changed.wait_for(lambda: found() is not None, timeout_s):
                pytest.fail(f"no log line with {text!r} within {timeout_s} s: {self.lines}")
            line = found()
            assert line is not None
            return line


@pytest.fixture
def log_watch() -> Iterator[LogWatch]:
    handler = LogWatch()
    logger = logging.getLogger("robotd")
    previous = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    yield handler
    logger.removeHandler(handler)
    logger.setLevel(previous)


@dataclass
class FakeRegistry:
    """Queryables on `reg/register` and `reg/reroute` with scripted answers; the token is
    declared by `up()` and undeclared by `down()`."""

    session: zenoh.Session
    register_reply: RegisterReply
    reroute_reply: bytes
    registrations: list[RegisterRequest] = field(default_factory=list)
    reroutes: list[RerouteRequest] = field(default_factory=list)
    registered: threading.Event = field(default_factory=threading.Event)
    rerouted: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self._held = [
            self.session.declare_queryable(keys.reg_register(FLEET), self._on_register),
            self.session.declare_queryable(keys.reg_reroute(FLEET), self._on_reroute),
        ]
        self._token: zenoh.LivelinessToken | None = None

    def up(self) -> None:
        self._token = self.session.liveliness().declare_token(keys.alive_registry(FLEET, "reg"))

    def down(self) -> None:
        if self._token is not None:
            self._token.undeclare()
            self._token = None

    def close(self) -> None:
        self.down()
        for item in self._held:
            item.undeclare()

    def _on_register(self, query: zenoh.Query) -> None:
        assert query.payload is not None
        self.registrations.append(RegisterRequest.from_wire(query.payload.to_bytes()))
        query.reply(query.key_expr, self.register_reply.to_wire())
        self.registered.set()

    def _on_reroute(self, query: zenoh.Query) -> None:
        assert query.payload is not None
        self.reroutes.append(RerouteRequest.from_wire(query.payload.to_bytes()))
        query.reply(query.key_expr, self.reroute_reply)
        self.rerouted.set()


@dataclass
class Linked:
    link: RegistryLink
    registry: FakeRegistry
    session: zenoh.Session


@pytest.fixture
def linked(
    zenoh_router: Router, open_peer: Callable[..., zenoh.Session]
) -> Iterator[Callable[..., Linked]]:
    """`linked(register_reply=..., reroute_reply=...)`: a link on the robot's own peer session,
    fed by a membership view of the registry as the daemon feeds it, and a fake registry on
    another peer (its token down until `registry.up()`)."""
    made: list[tuple[RegistryLink, MembershipView, FakeRegistry]] = []

    def make(
        register_reply: RegisterReply | None = None, reroute_reply: bytes | None = None
    ) -> Linked:
        owner = Daemon()
        session = open_peer()
        config = fleet_config(zenoh_router.endpoint, Path("unused.onnx"), fleet=FLEET)
        link = RegistryLink(
            session,
            config,
            ROBOT,
            model_digest=DIGEST,
            # The robot daemon's throttled lines go to a child of this logger.
            throttled=ThrottledLog(logging.getLogger("robotd"), label=lambda: ROBOT),
            guard=owner.guarded,
        )
        view = MembershipView(
            session,
            FLEET,
            roles=("registry",),
            on_change=lambda change: link.registry_changed(bool(change.alive_ids)),
        ).start()
        registry = FakeRegistry(
            open_peer(),
            register_reply
            or RegisterReply(accepted=True, reason="", protocol_version=PROTOCOL_VERSION),
            reroute_reply or route(1).to_wire(),
        )
        made.append((link, view, registry))
        return Linked(link, registry, session)

    yield make
    for link, view, registry in made:
        link.stop()
        view.close()
        registry.close()


def wait_reachable(link: RegistryLink) -> None:
    never = threading.Event()  # nothing interrupts this wait but its timeout
    assert link.wait_reachable(WAIT_S, never), "the registry's token was never seen"


def test_registers_when_the_registry_appears_and_keeps_the_route_when_it_goes(
    linked: Callable[..., Linked], zenoh_router: Router, log_watch: LogWatch
) -> None:
    reply = RegisterReply(
        accepted=True, reason="", protocol_version=PROTOCOL_VERSION, route=route(3)
    )
    setup = linked(register_reply=reply)
    link, registry = setup.link, setup.registry
    assert not link.reachable
    link.start(reported=False)
    line = log_watch.wait_for("not reachable")
    assert f"registry at {zenoh_router.endpoint} not reachable;" in line

    registry.up()
    assert link.wait_for_epoch(3, WAIT_S), "the route from the registration reply was not taken"
    assert link.route == ("edge-1", 3)
    assert registry.registered.is_set()
    request = registry.registrations[0]
    assert (request.role, request.id, request.model_digest) == ("robot", ROBOT, DIGEST)
    assert request.protocol_version == PROTOCOL_VERSION
    assert CAP_LOCAL_FALLBACK in request.capabilities
    log_watch.wait_for(f"registry reachable at {zenoh_router.endpoint}")

    registry.down()
    gone = log_watch.wait_for("registry gone")
    assert "keeping the route to edge-1 (epoch 3)" in gone
    assert link.route == ("edge-1", 3)


def test_a_refused_robot_is_an_error_line_and_keeps_no_route(
    linked: Callable[..., Linked], log_watch: LogWatch
) -> None:
    refusal = RegisterReply(
        accepted=False, reason="model digest differs", protocol_version=PROTOCOL_VERSION
    )
    setup = linked(register_reply=refusal)
    setup.registry.up()
    wait_reachable(setup.link)
    setup.link.start(reported=False)
    line = log_watch.wait_for("refused this robot")
    assert "model digest differs" in line
    assert setup.link.route == (None, 0)


def test_routes_only_move_forward_and_garbage_is_one_warning(
    linked: Callable[..., Linked], open_peer: Callable[..., zenoh.Session], log_watch: LogWatch
) -> None:
    setup = linked()
    link = setup.link
    assert link.apply_route(route(5))
    assert not link.apply_route(route(4, "edge-2"))  # older: a late message cannot undo a switch
    assert not link.apply_route(route(9, "edge-2", robot="robot-2"))  # another robot's
    assert link.route == ("edge-1", 5)
    assert link.apply_route(route(5, None))  # same epoch, no deployment: compute locally
    assert link.route == (None, 5)

    # Over the route key: garbage is dropped with one warning, the next message still counts.
    key = keys.route(FLEET, ROBOT)
    sub = setup.session.declare_subscriber(key, link.on_route)
    matched = threading.Event()
    publisher = open_peer().declare_publisher(key)
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None
    )
    try:
        assert matched.wait(WAIT_S), "the route subscriber was never matched"
        publisher.put(b"\xc1 garbage")
        publisher.put(route(6).to_wire())
        assert link.wait_for_epoch(6, WAIT_S)  # after the garbage: one publisher keeps order
    finally:
        listener.undeclare()
        publisher.undeclare()
        sub.undeclare()
    assert link.route == ("edge-1", 6)
    bad = [line for line in log_watch.lines if "ignoring a bad route message" in line]
    assert len(bad) == 1 and bad[0].startswith(f"{ROBOT}: ")


def test_no_capacity_is_logged_once_per_change(
    linked: Callable[..., Linked], log_watch: LogWatch
) -> None:
    link = linked().link

    def refused(epoch: int) -> RouteChange:
        return RouteChange(
            robot=ROBOT, deployment=None, epoch=epoch, reason=NO_CAPACITY_REASON, at=0.0
        )

    def told() -> int:
        return sum("no deployment has room: computing locally" in line for line in log_watch.lines)

    assert link.apply_route(refused(1)) and link.route == (None, 1)
    assert link.apply_route(refused(2))  # told again (a restarted registry): no second line
    assert told() == 1
    assert link.apply_route(route(3))  # placed once a deployment has room
    assert link.apply_route(refused(4))  # its deployment lost while every other is full
    assert told() == 2


def test_reroute_only_while_the_registry_is_up_at_most_once_per_interval(
    linked: Callable[..., Linked],
) -> None:
    setup = linked(reroute_reply=route(9, "edge-2").to_wire())
    link, registry = setup.link, setup.registry
    link.apply_route(route(4))
    assert not link.request_reroute(FallbackReason.TIMEOUT, 3)  # no registry: nobody to ask

    registry.up()
    wait_reachable(link)
    assert link.request_reroute(FallbackReason.TIMEOUT, 3)
    assert link.wait_for_epoch(9, WAIT_S), "the reroute's answer was not applied"
    assert link.route == ("edge-2", 9)
    asked = registry.reroutes[0]
    assert (asked.robot, asked.deployment, asked.epoch) == (ROBOT, "edge-1", 4)
    assert (asked.reason, asked.consecutive_timeouts) == (FallbackReason.TIMEOUT, 3)
    assert not link.request_reroute(FallbackReason.TIMEOUT, 4)  # within the interval
    assert len(registry.reroutes) == 1


def test_a_reroute_the_registry_cannot_serve_leaves_the_route(
    linked: Callable[..., Linked],
) -> None:
    refusal = ErrorReply.make(ErrorCode.NOT_SERVING, "no other deployment is alive").to_wire()
    setup = linked(reroute_reply=refusal)
    setup.link.apply_route(route(4))
    setup.registry.up()
    wait_reachable(setup.link)
    assert setup.link.request_reroute(FallbackReason.TIMEOUT, 3)
    assert setup.registry.rerouted.wait(WAIT_S)
    # Absence cannot be waited for: give the refusal a moment to arrive and be ignored.
    assert not setup.link.wait_for_epoch(5, 0.3)
    assert setup.link.route == ("edge-1", 4)


def blocked_in(thread: threading.Thread, function: str, timeout_s: float = WAIT_S) -> bool:
    """Whether `thread` is (within `timeout_s`) inside `function`, as its stack shows."""
    deadline = time.monotonic() + timeout_s
    while thread.is_alive() and time.monotonic() < deadline:
        frame = sys._current_frames().get(thread.ident or 0)
        while frame is not None:
            if frame.f_code.co_name == function:
                return True
            frame = frame.f_back
        thread.join(0.01)  # returns early only if the thread ends
    return False


def test_stop_wakes_a_watcher_waiting_for_the_registry_to_go(
    linked: Callable[..., Linked], log_watch: LogWatch
) -> None:
    reply = RegisterReply(
        accepted=True, reason="", protocol_version=PROTOCOL_VERSION, route=route(2)
    )
    setup = linked(register_reply=reply)
    setup.registry.up()
    wait_reachable(setup.link)
    setup.link.start(reported=False)
    assert setup.link.wait_for_epoch(2, WAIT_S)
    watchers = [t for t in threading.enumerate() if t.name == f"registry-watch-{ROBOT}"]
    assert len(watchers) == 1
    # Registered: the watcher now waits, without a timeout, for the registry to go.
    assert blocked_in(watchers[0], "_wait_registry"), "the watcher never settled into its wait"
    started = time.monotonic()
    setup.link.stop()
    took_s = time.monotonic() - started
    assert not watchers[0].is_alive()
    assert took_s < STOP_WITHIN_S, f"stop() took {took_s:.2f} s"
    assert not any("registry gone" in line for line in log_watch.lines)
