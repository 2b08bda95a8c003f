"""A deployment's state for each robot (standby, service, draining) and the epoch rules.

The registry moves robots between deployments with an epoch-fenced switch (docs/registry.md); what
a deployment must do with each control request is decided here, without any I/O, so the rules can
be tested alone and the daemon only carries out a `Verdict`:

- `service(robot, e)` is accepted when e is newer than every epoch seen for the robot. The same
  epoch again while already in service is acknowledged once more (a registry re-sending its
  restored route); after a `standby(e)` it is refused, so a late `service` that lost the race
  against the registry's fence can never leave two deployments serving one robot.
- `standby(robot, e)` is accepted when e is at least the epoch held.
- A refusal carries the deployment's own state and epoch for the robot, so the registry can move
  its epochs past it.
- Draining (planned shutdown): robots in service become `draining` (still served, service key
  still declared, until the registry sends them to standby) and no robot is taken into service.

Every robot starts in standby with no epoch: a deployment never serves a robot on its own.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from common.wire.registry import DeploymentState

NO_EPOCH = -1
"""The epoch held for a robot no control request has named yet (any epoch is newer)."""

_SERVING = (DeploymentState.SERVICE, DeploymentState.DRAINING)


@dataclass(frozen=True)
class RobotServiceState:
    """One robot's state at this deployment and the epoch of the last accepted request."""

    state: DeploymentState = DeploymentState.STANDBY
    epoch: int = NO_EPOCH

    @property
    def serving(self) -> bool:
        """Whether the robot's service key is declared here (service or draining)."""
        return self.state in _SERVING

    @property
    def wire_epoch(self) -> int:
        """The epoch as replies carry it (0 before any request named the robot)."""
        return max(self.epoch, 0)


@dataclass(frozen=True)
class Verdict:
    """What to do with one control request: accept it (then `declare` or `undeclare` the robot's
    service key before acknowledging) or refuse it with `reason`. `after` is the robot's state
    once the verdict is applied (the current state for a refusal)."""

    ok: bool
    robot: str
    after: RobotServiceState
    before: RobotServiceState
    reason: str = ""

    @property
    def declare(self) -> bool:
        """The service key must be declared (the robot enters service)."""
        return self.ok and self.after.serving and not self.before.serving

    @property
    def undeclare(self) -> bool:
        """The service key must be undeclared (the robot leaves service)."""
        return self.ok and self.before.serving and not self.after.serving


class StateTable:
    """Per-robot states of one deployment. Not locked: the daemon serializes access."""

    def __init__(self, robots: Iterable[str] = ()) -> None:
        self._robots: dict[str, RobotServiceState] = {
            robot: RobotServiceState() for robot in robots
        }
        self.draining = False

    # -- reading ---------------------------------------------------------------------------
    def get(self, robot: str) -> RobotServiceState:
        """The robot's state (standby without an epoch for a robot never named)."""
        return self._robots.get(robot, RobotServiceState())

    def snapshot(self) -> dict[str, RobotServiceState]:
        """Every known robot's state."""
        return dict(self._robots)

    def serving_robots(self) -> list[str]:
        """Robots whose service key is declared here."""
        return [robot for robot, st in self._robots.items() if st.serving]

    # -- deciding --------------------------------------------------------------------------
    def decide_service(self, robot: str, epoch: int) -> Verdict:
        """The verdict on `service(robot, epoch)`."""
        current = self.get(robot)
        if self.draining or current.state is DeploymentState.DRAINING:
            who = "this deployment is" if self.draining else f"{robot} is"
            return self._refuse(robot, current, f"{who} draining: no robot taken into service")
        if epoch > current.epoch:
            return self._accept(robot, current, RobotServiceState(DeploymentState.SERVICE, epoch))
        if epoch == current.epoch and current.state is DeploymentState.SERVICE:
            return self._accept(robot, current, current)  # the same request again: idempotent
        return self._refuse(
            robot,
            current,
            f"stale epoch {epoch} for service: {robot} is {current.state.value} at epoch "
            f"{current.epoch} here (service needs a newer epoch)",
        )

    def decide_standby(self, robot: str, epoch: int) -> Verdict:
        """The verdict on `standby(robot, epoch)`."""
        current = self.get(robot)
        if epoch >= current.epoch:
            return self._accept(robot, current, RobotServiceState(DeploymentState.STANDBY, epoch))
        return self._refuse(
            robot,
            current,
            f"stale epoch {epoch} for standby: {robot} is {current.state.value} at epoch "
            f"{current.epoch} here",
        )

    # -- changing --------------------------------------------------------------------------
    def apply(self, verdict: Verdict) -> None:
        """Make an accepted verdict the robot's state (a refusal changes nothing)."""
        if verdict.ok:
            self._robots[verdict.robot] = verdict.after

    def restore(self, verdict: Verdict) -> None:
        """Undo an applied verdict (its service key could not be declared)."""
        if verdict.ok:
            self._robots[verdict.robot] = verdict.before

    def drain_robot(self, robot: str) -> RobotServiceState:
        """Mark one robot draining if it is in service; its state afterwards."""
        current = self.get(robot)
        if current.state is DeploymentState.SERVICE:
            current = RobotServiceState(DeploymentState.DRAINING, current.epoch)
            self._robots[robot] = current
        return current

    def drain_all(self) -> list[str]:
        """Planned shutdown: refuse new robots, mark the served ones draining; returns those."""
        self.draining = True
        return [robot for robot in list(self._robots) if self.drain_robot(robot).serving]

    @staticmethod
    def _accept(robot: str, before: RobotServiceState, after: RobotServiceState) -> Verdict:
        return Verdict(ok=True, robot=robot, after=after, before=before)

    @staticmethod
    def _refuse(robot: str, current: RobotServiceState, reason: str) -> Verdict:
        return Verdict(ok=False, robot=robot, after=current, before=current, reason=reason)
