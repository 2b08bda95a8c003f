"""A kinematic unicycle with the paper's limits, for the closed-loop simulation.

The linear speed follows the command at most ``a_max`` faster and ``a_brake`` slower per second
(the paper's maximum acceleration and brake); the turn rate is clamped to ±ω_max and follows at
once. The pose integrates the two over a step on the arc they describe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from nav.render import Pose
from nav.shared_control import Command, RobotLimits


@dataclass
class UnicycleRobot:
    """Pose and speeds of the robot; :meth:`step` moves it by ``dt`` under a command."""

    pose: Pose
    limits: RobotLimits
    v_mps: float = 0.0
    w_radps: float = 0.0

    def step(self, command: Command, dt_s: float) -> Pose:
        lim = self.limits
        target = min(max(command.v_mps, -lim.v_max_mps), lim.v_max_mps)
        speeding_up = abs(target) > abs(self.v_mps) and target * self.v_mps >= 0
        rate = lim.a_max_mps2 if speeding_up else lim.a_brake_mps2
        change = target - self.v_mps
        v_new = self.v_mps + max(-rate * dt_s, min(rate * dt_s, change))
        self.w_radps = min(max(command.w_radps, -lim.w_max_radps), lim.w_max_radps)
        distance = 0.5 * (self.v_mps + v_new) * dt_s
        self.v_mps = v_new
        turn = self.w_radps * dt_s
        p = self.pose
        heading = p.theta + turn / 2  # the chord of the arc points half-way through the turn
        chord = distance if abs(turn) < 1e-9 else distance * math.sin(turn / 2) / (turn / 2)
        self.pose = Pose(
            p.x + chord * math.cos(heading), p.y + chord * math.sin(heading), p.theta + turn
        )
        return self.pose
