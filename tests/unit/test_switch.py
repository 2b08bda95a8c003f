"""The epoch-fenced switch protocol over a fake transport (real RIB, in a temporary file)."""

from __future__ import annotations

import random
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from common.wire.registry import CtlOp, CtlReply, CtlRequest, DeploymentState, RouteChange
from registry.latency import LatencyBound, Stat
from registry.rib import Rib
from registry.scheduler import Reason, RouteDecision, Scheduler
from registry.switch import Switcher, SwitchOutcome, TransportError, carry_out

ROBOT = "robot-1"
_STATE = {CtlOp.SERVICE: DeploymentState.SERVICE, CtlOp.STANDBY: DeploymentState.STANDBY}


def _route(robot: str, deployment: str | None, epoch: int, reason: str) -> tuple[object, ...]:
    return (robot, deployment, epoch, reason)


def _published(transport: FakeTransport) -> list[tuple[object, ...]]:
    """What was published, without the wall-clock stamp."""
    return [(c.robot, c.deployment, c.epoch, c.reason) for c in transport.published]


@dataclass
class FakeDeployment:
    """A cloud daemon's state machine for the ctl key, with its epoch fencing rule."""

    name: str
    # ack: apply and answer | timeout: never sees it | lost_reply: applies, answer lost |
    # refuse: answers ok=False | error: transport fails | stale: answers with an older epoch |
    # wrong_state: acks with another state
    mode: str = "ack"
    service_only: bool = False  # the failure mode hits service requests only
    epochs: dict[str, int] = field(default_factory=dict)
    states: dict[str, DeploymentState] = field(default_factory=dict)

    def handle(self, req: CtlRequest) -> CtlReply | None:
        if self.service_only and req.op is not CtlOp.SERVICE:
            return self._apply(req, "ack")
        return self._apply(req, self.mode)

    def _reply(
        self,
        req: CtlRequest,
        state: DeploymentState | None,
        epoch: int,
        *,
        ok: bool = True,
        reason: str = "",
    ) -> CtlReply:
        return CtlReply(
            ok=ok,
            deployment=self.name,
            op=req.op,
            robot=req.robot,
            epoch=epoch,
            state=state,
            reason=reason,
        )

    def _apply(self, req: CtlRequest, mode: str) -> CtlReply | None:
        assert req.robot is not None
        if mode == "timeout":
            return None
        if mode == "error":
            raise TransportError(f"no route to {self.name}")
        if mode == "refuse":
            return self._reply(req, _STATE[req.op], req.epoch, ok=False, reason="busy")
        known = self.epochs.get(req.robot, 0)
        fresh = req.epoch > known if req.op is CtlOp.SERVICE else req.epoch >= known
        if not fresh:
            # Like a cloud daemon: a refusal reports its own state and epoch for the robot.
            state = self.states.get(req.robot)
            return self._reply(req, state, known, ok=False, reason="stale epoch")
        self.epochs[req.robot] = req.epoch
        self.states[req.robot] = _STATE[req.op]
        if mode == "lost_reply":
            return None
        if mode == "stale":
            return self._reply(req, _STATE[req.op], req.epoch - 1)
        if mode == "wrong_state":
            return self._reply(req, DeploymentState.DRAINING, req.epoch)
        return self._reply(req, _STATE[req.op], req.epoch)


class FakeTransport:
    """Records every call with what the RIB held at that moment."""

    def __init__(self, rib: Rib, deployments: list[FakeDeployment]) -> None:
        self.rib = rib
        self.deployments = {d.name: d for d in deployments}
        self.log: list[tuple[object, ...]] = []
        self.published: list[RouteChange] = []
        self.publish_error: str | None = None

    def _route_now(self) -> tuple[str | None, int]:
        route = self.rib.route(ROBOT)
        return (route.deployment, route.epoch) if route else (None, 0)

    def send_ctl(self, deployment: str, request: CtlRequest, timeout_s: float) -> CtlReply | None:
        assert timeout_s > 0
        self.log.append(("ctl", deployment, request.op.value, request.epoch, self._route_now()))
        return self.deployments[deployment].handle(request)

    def publish_route(self, change: RouteChange) -> None:
        self.log.append(("publish", change.deployment, change.epoch, self._route_now()))
        if self.publish_error:
            raise TransportError(self.publish_error)
        self.published.append(change)


@pytest.fixture
def rib(tmp_path: Path) -> Iterator[Rib]:
    with Rib(tmp_path / "rib.sqlite") as r:
        for name in ("a", "b", "c"):
            r.upsert_deployment(
                name, service="detect", model_digest="sha256:aa", capacity=4, version="0.1.0"
            )
        r.upsert_robot(ROBOT, service="detect")
        yield r


def _fleet(rib: Rib, **modes: str) -> tuple[FakeTransport, dict[str, FakeDeployment]]:
    deps = {n: FakeDeployment(n, modes.get(n, "ack")) for n in ("a", "b", "c")}
    return FakeTransport(rib, list(deps.values())), deps


def _serve_a(rib: Rib, deps: dict[str, FakeDeployment], transport: FakeTransport) -> None:
    result = Switcher(rib, transport).switch(ROBOT, ["a"], reason="initial")
    assert result.changed and result.deployment == "a" and result.epoch == 1
    transport.log.clear()
    transport.published.clear()


def test_order_service_ack_then_persist_then_publish_then_old_standby(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    result = Switcher(rib, transport).switch(ROBOT, ["b"], reason="bound_violation")
    assert result.changed and (result.previous, result.deployment, result.epoch) == ("a", "b", 2)
    assert transport.log == [
        ("ctl", "b", "service", 2, ("a", 1)),  # asked while the route is still a
        ("publish", "b", 2, ("b", 2)),  # published after the route is persisted
        ("ctl", "a", "standby", 2, ("b", 2)),  # the old one steps down last
    ]
    assert _published(transport) == [_route(ROBOT, "b", 2, "bound_violation")]
    assert transport.published[0].at > 0
    states = {s.deployment: (s.state, s.epoch) for s in rib.deployment_states(robot=ROBOT)}
    assert states == {"a": (DeploymentState.STANDBY, 2), "b": (DeploymentState.SERVICE, 2)}
    assert deps["a"].states[ROBOT] is DeploymentState.STANDBY
    [route_event] = [e for e in rib.events(kind="route") if e.epoch == 2]
    assert route_event.reason == "bound_violation: a -> b"


def test_a_dead_old_deployment_is_not_asked_to_step_down(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    rib.set_deployment_alive("a", False, "token gone")
    result = Switcher(rib, transport).switch(ROBOT, ["b"], reason="deployment_lost")
    assert result.changed and result.deployment == "b"
    assert [entry[:3] for entry in transport.log] == [("ctl", "b", "service"), ("publish", "b", 2)]
    [a_state] = rib.deployment_states(robot=ROBOT, deployment="a")
    assert (a_state.state, a_state.epoch) == (DeploymentState.STANDBY, 2)


@pytest.mark.parametrize(
    ("mode", "outcome", "detail"),
    [
        ("timeout", SwitchOutcome.TIMEOUT, "no reply within 0.5 s"),
        ("lost_reply", SwitchOutcome.TIMEOUT, "no reply within 0.5 s"),
        ("refuse", SwitchOutcome.REFUSED, "busy"),
        ("error", SwitchOutcome.ERROR, "no route to b"),
        ("stale", SwitchOutcome.STALE, "ack for epoch 1, expected 2"),
        ("wrong_state", SwitchOutcome.STALE, "ack for state draining, expected service"),
    ],
)
def test_no_ack_falls_back_to_the_next_candidate_under_a_new_epoch(
    rib: Rib, mode: str, outcome: SwitchOutcome, detail: str
) -> None:
    transport, deps = _fleet(rib, b=mode)
    _serve_a(rib, deps, transport)
    result = Switcher(rib, transport).switch(ROBOT, ["b", "c"], reason="deployment_lost")
    assert (result.deployment, result.epoch) == ("c", 3)
    assert [(a.deployment, a.epoch, a.outcome, a.detail) for a in result.attempts] == [
        ("b", 2, outcome, detail),
        ("c", 3, SwitchOutcome.ACKED, ""),
    ]
    [failed] = rib.events(kind="ack_failed")
    assert (failed.deployment, failed.epoch) == ("b", 2)
    assert failed.reason == f"deployment_lost: {outcome.value}: {detail}"
    # After the route is out: the old one and the candidate that failed both get standby.
    steps = [(e[0], e[1], e[2]) for e in transport.log]
    assert steps[2:] == [
        ("publish", "c", 3),
        ("ctl", "a", "standby"),
        ("ctl", "b", "standby"),
    ]
    if mode == "lost_reply":
        # b did go to service before its reply was lost: the fence took it back down.
        assert deps["b"].states[ROBOT] is DeploymentState.STANDBY


def test_ack_for_another_robot_is_ignored(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)

    def confused(req: CtlRequest) -> CtlReply:
        return CtlReply(
            ok=True,
            deployment="b",
            op=req.op,
            robot="robot-2",
            epoch=req.epoch,
            state=DeploymentState.SERVICE,
        )

    deps["b"].handle = confused  # type: ignore[method-assign]
    result = Switcher(rib, transport).switch(ROBOT, ["b", "c"], reason="better")
    assert result.attempts[0].outcome is SwitchOutcome.STALE
    assert "robot-2" in result.attempts[0].detail
    assert result.deployment == "c"


def test_no_taker_keeps_a_live_old_route(rib: Rib) -> None:
    transport, deps = _fleet(rib, b="timeout", c="lost_reply")
    _serve_a(rib, deps, transport)
    result = Switcher(rib, transport).switch(ROBOT, ["b", "c"], reason="bound_violation")
    assert not result.changed
    assert (result.deployment, result.epoch) == ("a", 1)
    route = rib.route(ROBOT)
    assert route is not None and (route.deployment, route.epoch) == ("a", 1)
    assert transport.published == []
    [failed] = rib.events(kind="switch_failed")
    assert failed.reason == "bound_violation: no candidate acknowledged; route kept"
    # c applied service(3) but its ack was lost: fenced at the highest issued epoch.
    assert deps["c"].states[ROBOT] is DeploymentState.STANDBY
    assert deps["a"].states[ROBOT] is DeploymentState.SERVICE


def test_no_taker_with_a_dead_old_route_leaves_the_robot_local(rib: Rib) -> None:
    transport, deps = _fleet(rib, b="refuse")
    _serve_a(rib, deps, transport)
    rib.set_deployment_alive("a", False, "token gone")
    result = Switcher(rib, transport).switch(ROBOT, ["b"], reason="deployment_lost")
    assert result.changed and result.deployment is None and result.epoch == 3
    route = rib.route(ROBOT)
    assert route is not None and route.deployment is None and route.epoch == 3
    assert _published(transport) == [
        _route(ROBOT, None, 3, "deployment_lost: no deployment acknowledged")
    ]


def test_decision_with_no_target_drops_the_route(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    for name in ("a", "b", "c"):
        rib.set_deployment_alive(name, False, "token gone")
    result = Switcher(rib, transport).apply(RouteDecision(ROBOT, "a", None, Reason.DEPLOYMENT_LOST))
    assert result.changed and result.deployment is None
    assert _published(transport) == [_route(ROBOT, None, 2, "deployment_lost")]
    assert [e[0] for e in transport.log] == ["publish"]  # nobody alive to talk to


def test_a_robot_without_a_route_is_told_it_has_no_capacity(rib: Rib) -> None:
    transport, _deps = _fleet(rib)
    decision = RouteDecision(ROBOT, None, None, Reason.NO_CAPACITY)
    result = Switcher(rib, transport).apply(decision)
    assert result.changed and (result.previous, result.deployment, result.epoch) == (None, None, 1)
    assert _published(transport) == [_route(ROBOT, None, 1, "no_capacity")]
    assert [e[0] for e in transport.log] == ["publish"]  # no deployment to talk to
    [event] = rib.events(kind="route")
    assert event.reason == "no_capacity: local -> local"


def test_a_stale_decision_is_dropped(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    result = Switcher(rib, transport).apply(RouteDecision(ROBOT, "c", "b", Reason.BETTER, ("b",)))
    assert not result.changed and result.deployment == "a"
    assert "stale decision" in result.reason
    assert transport.log == []


def test_a_deployment_that_knows_a_newer_epoch_raises_ours(rib: Rib) -> None:
    # e.g. the RIB file was restored from an older copy: the cloud daemon has seen epoch 10.
    transport, deps = _fleet(rib)
    deps["b"].epochs[ROBOT] = 10
    deps["b"].states[ROBOT] = DeploymentState.STANDBY
    result = Switcher(rib, transport).switch(ROBOT, ["b"], reason="initial")
    assert (result.deployment, result.epoch) == ("b", 11)
    assert [(a.epoch, a.outcome) for a in result.attempts] == [
        (1, SwitchOutcome.REFUSED),
        (11, SwitchOutcome.ACKED),
    ]
    assert rib.events(kind="epoch_raised")[0].reason == "b knows epoch 10"
    assert rib.reserve_epoch(ROBOT) == 12


def test_epochs_keep_growing_across_a_registry_restart(tmp_path: Path) -> None:
    path = tmp_path / "rib.sqlite"
    deps = {n: FakeDeployment(n) for n in ("a", "b")}
    epochs = []
    for _ in range(3):  # three registry lifetimes over the same file and the same deployments
        with Rib(path) as r:
            r.reset_liveness()
            for n in deps:
                r.upsert_deployment(n, service="s", model_digest="d", capacity=1, version="1")
            transport = FakeTransport(r, list(deps.values()))
            route = r.route(ROBOT)
            target = "b" if route is not None and route.deployment == "a" else "a"
            result = Switcher(r, transport).switch(ROBOT, [target], reason="test")
            assert result.attempts[-1].outcome is SwitchOutcome.ACKED
            epochs.append(result.epoch)
    assert epochs == [1, 2, 3]


def test_a_failed_publish_is_recorded_and_the_switch_completes(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    transport.publish_error = "session closed"
    result = Switcher(rib, transport).switch(ROBOT, ["b"], reason="better")
    assert result.changed
    assert rib.events(kind="publish_failed")[0].reason == "session closed"
    assert deps["a"].states[ROBOT] is DeploymentState.STANDBY


def test_standby_failure_is_recorded(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    deps["a"].mode = "timeout"
    result = Switcher(rib, transport).switch(ROBOT, ["b"], reason="better")
    assert result.changed
    [failed] = rib.events(kind="standby_failed")
    assert (failed.deployment, failed.reason) == ("a", "timeout: no reply within 0.5 s")


def test_carry_out_tells_the_scheduler(rib: Rib) -> None:
    now = [0.0]
    sched = Scheduler(LatencyBound(Stat.MEDIAN, 0.1), clock=lambda: now[0])
    transport, deps = _fleet(rib, c="refuse")
    _serve_a(rib, deps, transport)
    moved = carry_out(
        sched,
        Switcher(rib, transport),
        RouteDecision(ROBOT, "a", "b", Reason.BOUND_VIOLATION, ("b",)),
    )
    assert moved.changed and sched.penalized(ROBOT) == {"a"}
    stuck = carry_out(
        sched, Switcher(rib, transport), RouteDecision(ROBOT, "b", "c", Reason.TIMEOUTS, ("c",))
    )
    assert not stuck.changed
    assert sched.memory.state(ROBOT).failed_at == 0.0


def test_anycast_invariant_under_random_failures() -> None:
    """After every switch, exactly the routed deployment serves the robot (seeded, 300 switches)."""
    rng = random.Random(42)
    names = ["a", "b", "c", "d"]
    with Rib(":memory:") as r:
        for n in names:
            r.upsert_deployment(n, service="s", model_digest="d", capacity=1, version="1")
        deps = {n: FakeDeployment(n, service_only=True) for n in names}
        transport = FakeTransport(r, list(deps.values()))
        switcher = Switcher(r, transport)
        last_epoch = 0
        for _ in range(300):
            for d in deps.values():
                d.mode = rng.choice(["ack", "ack", "timeout", "lost_reply", "refuse", "stale"])
            candidates = rng.sample(names, k=rng.randint(1, 3))
            result = switcher.switch(ROBOT, candidates, reason="test")
            # Standby always gets through here, so the invariant must hold exactly.
            serving = {n for n, d in deps.items() if d.states.get(ROBOT) is DeploymentState.SERVICE}
            route = r.route(ROBOT)
            routed = route.deployment if route else None
            assert serving == ({routed} if routed else set())
            assert result.epoch >= last_epoch
            last_epoch = result.epoch


def test_reassert_resends_service_at_the_same_epoch(rib: Rib) -> None:
    """A restarted registry confirms its restored route without a new epoch; a deployment that
    forgot the robot (restarted in standby) serves it again."""
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    deps["a"].epochs.clear()
    deps["a"].states.clear()
    result = Switcher(rib, transport).reassert(ROBOT)
    assert not result.changed and (result.deployment, result.epoch) == ("a", 1)
    assert result.attempts[-1].outcome is SwitchOutcome.ACKED
    assert deps["a"].states[ROBOT] is DeploymentState.SERVICE
    assert transport.published == []


def test_reassert_past_a_newer_epoch_moves_the_route_to_a_fresh_one(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    deps["a"].epochs[ROBOT] = 7  # the RIB file is older than the deployment's memory
    result = Switcher(rib, transport).reassert(ROBOT)
    assert result.changed and (result.deployment, result.epoch) == ("a", 8)
    route = rib.route(ROBOT)
    assert route is not None and (route.deployment, route.epoch) == ("a", 8)
    assert _published(transport) == [_route(ROBOT, "a", 8, "restore")]


def test_reassert_refused_at_the_same_epoch_takes_a_fresh_one(rib: Rib) -> None:
    # The deployment stood down at the route's epoch (a fence): the same epoch cannot serve.
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    deps["a"].states[ROBOT] = DeploymentState.STANDBY
    result = Switcher(rib, transport).reassert(ROBOT)
    assert result.changed and (result.deployment, result.epoch) == ("a", 2)
    assert [a.outcome for a in result.attempts] == [SwitchOutcome.REFUSED, SwitchOutcome.ACKED]
    assert deps["a"].states[ROBOT] is DeploymentState.SERVICE
    assert rib.events(kind="epoch_raised") == []


def test_reassert_without_an_answer_is_recorded_and_keeps_the_route(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    deps["a"].mode = "timeout"
    result = Switcher(rib, transport).reassert(ROBOT)
    assert not result.changed and result.attempts[-1].outcome is SwitchOutcome.TIMEOUT
    assert rib.events(kind="ack_failed")[-1].reason.startswith("restore: timeout")


def test_fence_puts_a_stray_server_in_standby(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    _serve_a(rib, deps, transport)
    deps["b"].states[ROBOT] = DeploymentState.SERVICE  # e.g. it missed its standby
    Switcher(rib, transport).fence(ROBOT, "b")
    assert deps["b"].states[ROBOT] is DeploymentState.STANDBY
    assert transport.log[-1][:4] == ("ctl", "b", "standby", 1)


def test_service_and_standby_carry_the_frames_in_flight_the_robot_announced(rib: Rib) -> None:
    transport, _deps = _fleet(rib)
    sent: list[CtlRequest] = []
    send = transport.send_ctl

    def record(deployment: str, request: CtlRequest, timeout_s: float) -> CtlReply | None:
        sent.append(request)
        return send(deployment, request, timeout_s)

    transport.send_ctl = record  # type: ignore[method-assign]
    announced = {ROBOT: 3}
    switcher = Switcher(rib, transport, in_flight=announced.get)
    switcher.switch(ROBOT, ["a"], reason="initial")
    switcher.switch(ROBOT, ["b"], reason="bound_violation")
    assert [(r.op.value, r.max_in_flight) for r in sent] == [
        ("service", 3),
        ("service", 3),
        ("standby", 3),
    ]
