"""Shared control: the joystick's command filtered against d_coll (the paper's Section III-C, D).

The joystick asks for (v_j, ω_j), a path of curvature K_j = ω_j/v_j. The newest obstacle
information, d_coll(K) from a frame taken at t_frame, gives the free arc along that path; the
robot has moved since, about v_j·(t_now − t_frame) (the paper's predictive correction), so

    s_j = d_coll(K_j) − v_j·(t_now − t_frame) − stop_margin,   v_max = sqrt(2·a_max·s_j)

and if v_max < v_j the robot gets v_c = v_max with ω_c = K_j·v_c: the same path, slower, so the
teleoperator does not feel the trajectory change. When no frame newer than T_dead (``deadline_s``)
has been seen — the cloud is late, or the last frame saw nothing and nothing came since — forward
speed is braked progressively (``deadline_decel_mps2``) to zero. The paper's v_max uses a_max,
the robot's maximum acceleration (8 m/s²), not its harder brake a_brake (10 m/s²): a stop is
then always within reach.

A frontal camera says nothing about what is behind or beside the robot: reverse motion and turns
on the spot (v_j ≤ 0) pass unchanged, as in the paper (the teleoperator sees the scene).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from common.errors import UserError
from nav.curvature import DcollProfile

# The paper's Erratic configuration (Section V-C).
PAPER_V_MAX_MPS = 0.4
PAPER_W_MAX_RADPS = 1.0
PAPER_A_MAX_MPS2 = 8.0
PAPER_A_BRAKE_MPS2 = 10.0
# Not given in the paper: a frame older than this is no longer trusted (option 4 of the paper at
# 640×480 updates at 2.6 Hz); then speed ramps down at a rate a person feels as braking.
DEFAULT_DEADLINE_S = 1.0
DEFAULT_DEADLINE_DECEL_MPS2 = 1.0


class Limit(str, Enum):
    """Why the command sent differs from the joystick's (or NONE)."""

    NONE = "none"
    OBSTACLE = "obstacle"
    DEADLINE = "deadline"


@dataclass(frozen=True)
class RobotLimits:
    """Kinematic limits of the robot (the paper's v_max, ω_max, a_max, a_brake)."""

    v_max_mps: float = PAPER_V_MAX_MPS
    w_max_radps: float = PAPER_W_MAX_RADPS
    a_max_mps2: float = PAPER_A_MAX_MPS2
    a_brake_mps2: float = PAPER_A_BRAKE_MPS2

    def __post_init__(self) -> None:
        _positive(self, ("v_max_mps", "w_max_radps", "a_max_mps2", "a_brake_mps2"))


@dataclass(frozen=True)
class AssistantParams:
    """How the assistant treats its obstacle information."""

    deadline_s: float = DEFAULT_DEADLINE_S
    deadline_decel_mps2: float = DEFAULT_DEADLINE_DECEL_MPS2
    # Free distance kept in front of the axle: the robot's front overhang plus a safety gap.
    stop_margin_m: float = 0.0
    # Half the robot's width: an obstacle this near the path beside it limits the speed too
    # (DcollProfile.within). 0 is the paper's footprint, the point at the axle centre.
    half_width_m: float = 0.0

    def __post_init__(self) -> None:
        _positive(self, ("deadline_s", "deadline_decel_mps2"))
        for name in ("stop_margin_m", "half_width_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise UserError(f"{name} must be ≥ 0, got {value}")


@dataclass(frozen=True)
class Command:
    """A velocity command: linear (m/s, forward > 0) and angular (rad/s, left > 0)."""

    v_mps: float
    w_radps: float


@dataclass(frozen=True)
class ControlDecision:
    """The command sent to the robot and why; ``free_m`` is s_j (None when not computed)."""

    command: Command
    limit: Limit
    free_m: float | None = None


class SharedControl:
    """Filters joystick commands with the newest d_coll(K). One per robot; not thread-safe."""

    def __init__(
        self, limits: RobotLimits | None = None, params: AssistantParams | None = None
    ) -> None:
        self.limits = limits or RobotLimits()
        self.params = params or AssistantParams()
        self._profile: DcollProfile | None = None
        self._t_frame = -math.inf
        # The last forward speed sent and when: the deadline ramp starts from it.
        self._v_sent = 0.0
        self._t_sent = -math.inf

    @property
    def frame_time(self) -> float:
        """Capture time of the frame behind the current obstacle information (−inf: none)."""
        return self._t_frame

    def observe(self, profile: DcollProfile, t_frame: float) -> bool:
        """Take d_coll from the frame captured at ``t_frame``; an older frame than the one held
        is ignored (False): results are never applied out of order."""
        if not math.isfinite(t_frame):
            raise UserError(f"frame time must be finite, got {t_frame}")
        if t_frame <= self._t_frame:
            return False
        self._profile = profile
        self._t_frame = t_frame
        return True

    def command(self, joystick: Command, t_now: float) -> ControlDecision:
        """The command to send at ``t_now`` for this joystick position."""
        v_j, w_j = joystick.v_mps, joystick.w_radps
        if not (math.isfinite(v_j) and math.isfinite(w_j) and math.isfinite(t_now)):
            raise UserError(f"joystick command and time must be finite: v={v_j} ω={w_j} t={t_now}")
        if v_j <= 0:
            return self._send(joystick, Limit.NONE, t_now)
        age = t_now - self._t_frame
        deadline = self.params.deadline_s
        if self._profile is None or age > deadline:
            since = max(self._t_sent, self._t_frame + deadline)
            v_ramp = max(0.0, self._v_sent - self.params.deadline_decel_mps2 * (t_now - since))
            if v_ramp < v_j:
                return self._send(_same_curvature(joystick, v_ramp), Limit.DEADLINE, t_now)
            return self._send(joystick, Limit.NONE, t_now)
        curvature = w_j / v_j
        ahead = self._profile.within(curvature, self.params.half_width_m)
        free = ahead - v_j * max(age, 0.0) - self.params.stop_margin_m
        v_allowed = math.sqrt(2.0 * self.limits.a_max_mps2 * max(free, 0.0))
        if v_allowed < v_j:
            return self._send(_same_curvature(joystick, v_allowed), Limit.OBSTACLE, t_now, free)
        return self._send(joystick, Limit.NONE, t_now, free)

    def _send(
        self, command: Command, limit: Limit, t_now: float, free: float | None = None
    ) -> ControlDecision:
        self._v_sent = max(command.v_mps, 0.0)
        self._t_sent = t_now
        return ControlDecision(command, limit, free)


def _same_curvature(joystick: Command, v_mps: float) -> Command:
    """(v, ω) on the joystick's path (K = ω_j/v_j, v_j > 0) at the lower speed v."""
    return Command(v_mps, joystick.w_radps * v_mps / joystick.v_mps)


def _positive(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (math.isfinite(value) and value > 0):
            raise UserError(f"{name} must be a positive number, got {value!r}")
