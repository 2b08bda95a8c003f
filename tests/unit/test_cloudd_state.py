"""The cloud daemon's per-robot state machine and the switch protocol's epoch rules."""

from __future__ import annotations

from cloudd.state import NO_EPOCH, RobotServiceState, StateTable
from common.wire.registry import DeploymentState

SERVICE = DeploymentState.SERVICE
STANDBY = DeploymentState.STANDBY
DRAINING = DeploymentState.DRAINING
ROBOT = "robot-1"


def serve(table: StateTable, epoch: int) -> None:
    verdict = table.decide_service(ROBOT, epoch)
    assert verdict.ok, verdict.reason
    table.apply(verdict)


def test_every_robot_starts_in_standby_without_an_epoch() -> None:
    table = StateTable(["robot-1", "robot-2"])
    assert table.snapshot() == {"robot-1": RobotServiceState(), "robot-2": RobotServiceState()}
    assert table.get("robot-9") == RobotServiceState(STANDBY, NO_EPOCH)
    assert table.get("robot-9").wire_epoch == 0
    assert table.serving_robots() == []


def test_service_declares_and_standby_undeclares() -> None:
    table = StateTable([ROBOT])
    verdict = table.decide_service(ROBOT, 1)
    assert verdict.ok and verdict.declare and not verdict.undeclare
    table.apply(verdict)
    assert table.get(ROBOT) == RobotServiceState(SERVICE, 1)
    assert table.serving_robots() == [ROBOT]

    verdict = table.decide_standby(ROBOT, 2)
    assert verdict.ok and verdict.undeclare and not verdict.declare
    table.apply(verdict)
    assert table.get(ROBOT) == RobotServiceState(STANDBY, 2)


def test_service_needs_a_newer_epoch_and_refusals_carry_our_state() -> None:
    table = StateTable([ROBOT])
    serve(table, 5)
    stale = table.decide_service(ROBOT, 4)
    assert not stale.ok and not stale.declare
    assert stale.after == RobotServiceState(SERVICE, 5)
    assert "stale epoch 4" in stale.reason and "epoch 5" in stale.reason
    table.apply(stale)
    assert table.get(ROBOT) == RobotServiceState(SERVICE, 5), "a refusal changes nothing"


def test_the_same_service_request_again_is_acknowledged_without_redeclaring() -> None:
    # A restarted registry re-sends its restored route with the same epoch.
    table = StateTable([ROBOT])
    serve(table, 3)
    again = table.decide_service(ROBOT, 3)
    assert again.ok and not again.declare and again.after == RobotServiceState(SERVICE, 3)


def test_late_service_after_the_fence_is_refused() -> None:
    # Regression guard for the switch protocol's fence: the registry sends standby(e) to a
    # candidate that did not ack service(e) in time; the late service(e) must not win.
    table = StateTable([ROBOT])
    table.apply(table.decide_standby(ROBOT, 7))
    late = table.decide_service(ROBOT, 7)
    assert not late.ok and late.after == RobotServiceState(STANDBY, 7)
    assert table.decide_service(ROBOT, 8).ok


def test_standby_needs_at_least_the_epoch_held() -> None:
    table = StateTable([ROBOT])
    serve(table, 5)
    assert not table.decide_standby(ROBOT, 4).ok
    same = table.decide_standby(ROBOT, 5)
    assert same.ok and same.undeclare


def test_standby_of_an_unknown_robot_is_accepted_and_remembered() -> None:
    table = StateTable()
    verdict = table.decide_standby("robot-7", 0)
    assert verdict.ok and not verdict.undeclare
    table.apply(verdict)
    assert table.get("robot-7") == RobotServiceState(STANDBY, 0)


def test_restore_undoes_an_applied_verdict() -> None:
    table = StateTable([ROBOT])
    verdict = table.decide_service(ROBOT, 2)
    table.apply(verdict)
    table.restore(verdict)
    assert table.get(ROBOT) == RobotServiceState()


def test_draining_keeps_serving_until_standby_and_takes_no_new_robot() -> None:
    table = StateTable([ROBOT, "robot-2"])
    serve(table, 4)
    assert table.drain_all() == [ROBOT]
    assert table.get(ROBOT) == RobotServiceState(DRAINING, 4)
    assert table.get(ROBOT).serving, "a draining robot is still served"
    refused = table.decide_service("robot-2", 1)
    assert not refused.ok and "draining" in refused.reason
    verdict = table.decide_standby(ROBOT, 5)
    assert verdict.ok and verdict.undeclare
    table.apply(verdict)
    assert table.serving_robots() == []


def test_draining_one_robot_refuses_its_service_until_standby() -> None:
    table = StateTable([ROBOT])
    serve(table, 1)
    assert table.drain_robot(ROBOT) == RobotServiceState(DRAINING, 1)
    assert not table.decide_service(ROBOT, 2).ok
    table.apply(table.decide_standby(ROBOT, 2))
    assert table.decide_service(ROBOT, 3).ok, "standby ends a robot's drain"
    assert table.drain_robot("robot-2") == RobotServiceState(), "draining a robot not served: no-op"
