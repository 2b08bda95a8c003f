"""When ElasticAction times the robot: robot probes (`robot_probe_frames`).

An action whose robot part is too short to time the robot (cut 0 with a JPEG encode: under
`robotcost.SHORT_RUN_SHARE` of the model) leaves the robot-cost estimate stale. When the robot has
not been timed for `robot_probe_frames` frames, the next offloaded frame is hedged at once, so a
robot that got faster again is noticed. Without hedging the probe serves the frame on the robot
(P) instead, and each probe that finds the estimate right doubles the interval to the next (up to
`ROBOT_PROBE_MAX_FACTOR` times), as these probes cost latency; one that finds it wrong is confirmed
by a probe on the next frame.
"""

from __future__ import annotations

from collections.abc import Sequence

from robotd.policies.params import ElasticParams
from robotd.policies.robotcost import RobotCostModel

# Without hedging, a robot probe serves a frame on the robot (P). Each probe that finds the
# estimate right doubles the interval to the next, up to this multiple of robot_probe_frames.
ROBOT_PROBE_MAX_FACTOR = 4


class RobotProbes:
    """The robot-probe schedule of one ElasticAction policy (see the module docstring)."""

    def __init__(
        self, params: ElasticParams, robot: RobotCostModel, untimed: Sequence[bool]
    ) -> None:
        self._params = params
        self._robot = robot
        self._untimed = untimed  # per column: its robot part is too short to time the robot
        # Frames since the robot was last timed or a probe was tried, the current interval
        # (grows while unhedged probes find the estimate right), and whether a probe was already
        # tried for the measurement that is awaiting confirmation.
        self._since = 0
        self._interval = params.robot_probe_frames
        self._suspect_probed = False
        self._on_p = False
        self.count = 0
        """Frames served on the robot (P) to time it."""

    def tick(self) -> None:
        """A frame begins."""
        self._since += 1

    def due(self, j: int) -> bool:
        """Time the robot: cut j runs nothing measurable there, and the robot's speed is stale
        (or, when hedging, a surprising measurement awaits confirmation)."""
        if not self._untimed[j] or self._params.robot_probe_frames == 0:
            return False
        if self._params.hedge and self._robot.suspect and not self._suspect_probed:
            return True
        return self._since >= self._interval

    def tried(self, *, on_p: bool = False) -> None:
        """A probe is made this frame (`on_p`: by serving it on the robot, without hedging)."""
        self._since = 0
        if self._robot.suspect:
            self._suspect_probed = True
        if on_p:
            self._on_p = True

    def timed(self, miss: int | None, *, on_p: bool = False) -> None:
        """After a robot measurement (`miss`: `RobotCostModel.observe`'s answer); `on_p`: of a
        frame served on the robot, which was a probe if one was tried by serving it there."""
        p_probe = on_p and self._on_p
        if on_p:
            self._on_p = False
        if miss is None:
            return
        self._since = 0
        self._suspect_probed = False
        if p_probe:
            self.count += 1
            base = self._params.robot_probe_frames
            if miss == 0:  # the estimate was right: probe less often
                self._interval = min(2 * self._interval, ROBOT_PROBE_MAX_FACTOR * base)
            elif self._robot.suspect:  # a surprise: confirm it on the next frame
                self._interval = 1
            else:
                self._interval = base
