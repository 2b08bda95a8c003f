"""When ElasticAction times the robot: robot probes (`robot_probe_frames`).

An action whose robot part is too short to time the robot (cut 0 with a JPEG encode: under
`robotcost.SHORT_RUN_SHARE` of the model) leaves the robot-cost estimate stale. When the robot has
not been timed for `robot_probe_frames` frames, the next offloaded frame is hedged at once, so a
robot that got faster again is noticed. Without hedging the probe serves the frame on the robot
(P) instead, and each probe that finds the estimate right doubles the interval to the next (up to
`ROBOT_PROBE_MAX_FACTOR` times), as these probes cost latency; one that finds it wrong is confirmed
by a probe on the next frame.

A hedged probe costs robot CPU instead: its local run of the whole model starts at once and runs
until the reply stops it, so on a robot that only sends JPEG frames a probe every 10 frames kept
the robot computing through a whole reply in one frame of ten (the robot-CPU p95 of `elastic`
was 3x a static policy's; docs/policies.md, "Robot CPU beyond a static policy"). That robot time
is counted in the objective, priced like any robot compute (`Objective.robot_rate`, the cost of a
second of it): a probe whose local run lost the race to the reply timed nothing and cost
`robot_rate` times the time from its start to the reply. The interval to the next probe then
keeps what lost probes cost within `PROBE_COST_SHARE` of what the frames between them cost (the
current choice's estimate), up to `PROBE_COST_MAX_FACTOR` times `robot_probe_frames`; a probe that
wins its race (P may be worth it) brings the interval back. Only a robot that reports its CPU
(`Outcome.cpu_s`, the robot daemon) is charged: the simulator models no CPU contention, and its
robot is probed every `robot_probe_frames` as before. A lost probe also costs the latency it
added to its own frame: on a 0.1-core robot the local run spends the quota whenever the
offload's threads wait, and each step of the offload then waits for the next CFS period (a
probe frame took 76-155 ms against 40 ms; docs/experiments.md, "A weak robot"). What the frame
cost beyond the prediction counts in the price.

A probe looks for a robot that got fast enough to change the choice: while P costs `r` times
the cheapest offloading action, only a robot `r` times faster would make P (or a cut with more
robot work) win. On a robot that reports its CPU, probes are spaced by that distance too
(`spacing`: `r` x `robot_probe_frames`, within the same cap), so a robot far from winning is
probed rarely from the start, before any probe was lost and priced; a measurement that surprised
is still confirmed on the next frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from robotd.policies.params import ElasticParams
from robotd.policies.robotcost import RobotCostModel

# Without hedging, a robot probe serves a frame on the robot (P). Each probe that finds the
# estimate right doubles the interval to the next, up to this multiple of robot_probe_frames.
ROBOT_PROBE_MAX_FACTOR = 4
# Lost hedged probes may cost at most this share of what the frames between them cost.
PROBE_COST_SHARE = 0.025
# ... which may stretch the interval up to this multiple of robot_probe_frames (P's distance
# too, `RobotProbes.spacing`).
PROBE_COST_MAX_FACTOR = 8


class RobotProbes:
    """The robot-probe schedule of one ElasticAction policy (see the module docstring)."""

    def __init__(
        self, params: ElasticParams, robot: RobotCostModel, untimed: Sequence[bool], rate: float
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
        # The decision of the last probe made by hedging, whose race is awaited (by identity:
        # a hedged frame served by the robot is observed after later frames were decided).
        self._awaited: object | None = None
        self._bounded = False  # the robot's time is only bounded from below: time it on P
        self._rate = rate  # objective units per second of robot compute
        self.count = 0
        """Frames served on the robot (P) to time it."""
        self.lost = 0
        """Hedged probes whose local run lost the race to the reply (they timed nothing)."""

    def tick(self) -> None:
        """A frame begins."""
        self._since += 1

    def due(self, j: int, p_ratio: float = 1.0) -> bool:
        """Time the robot: cut j runs nothing measurable there, and the robot's speed is stale
        (or a surprising measurement awaits confirmation). `p_ratio`: P's estimated cost over
        the cheapest offloading action's (`spacing`)."""
        if not self._untimed[j] or self._params.robot_probe_frames == 0:
            return False
        if self._robot.suspect:  # confirm the surprise now, whatever the spacing
            if self._params.hedge and not self._suspect_probed:
                return True
            return self._since >= self._interval
        return self._since >= max(self._interval, self.spacing(p_ratio))

    def spacing(self, p_ratio: float) -> int:
        """Frames between probes while P costs `p_ratio` times the cheapest offloading action:
        a robot needs to get that much faster for a probe to find something that changes the
        choice (module docstring)."""
        base = self._params.robot_probe_frames
        if not p_ratio > 1.0:  # P wins or ties (or nothing offloads: the ratio is nan)
            return base
        return math.ceil(base * min(p_ratio, PROBE_COST_MAX_FACTOR))

    def tried(self, *, on_p: bool = False) -> None:
        """The robot may be timed this frame: a hedged frame, or a probe served on the robot
        (`on_p`, without hedging)."""
        self._since = 0
        if self._robot.suspect:
            self._suspect_probed = True
        if on_p:
            self._on_p = True

    @property
    def wants_p(self) -> bool:
        """A stopped local run showed the robot slower than estimated (`bounded`): the next
        probe serves the frame on the robot, as a bound alone never tells how much slower."""
        return self._bounded

    def bounded(self, miss: int | None) -> None:
        """After a stopped local run (`RobotCostModel.observe_slower_than`'s answer)."""
        self.timed(miss)
        if miss is not None and miss > 0:
            self._bounded = True

    def hedged(self, decision: object) -> None:
        """`decision` is a probe made by hedging: its race is priced when it is observed."""
        self._awaited = decision

    @property
    def interval(self) -> int:
        """Frames from one probe to the next, now."""
        return self._interval

    def raced(
        self,
        decision: object,
        *,
        timed: bool,
        busy_s: float,
        cpu_known: bool,
        frame_cost: float,
        excess: float = 0.0,
    ) -> None:
        """After hedged frame `decision`: whether its local run finished (`timed`), how long
        it kept the robot computing before the reply stopped it (`busy_s`), whether the robot
        reports its CPU (`cpu_known`), the current choice's estimated cost per frame and what
        the frame's cloud part cost beyond its prediction (`excess`; objective units). Prices a
        lost probe (module docstring)."""
        if decision is not self._awaited:
            return
        self._awaited = None
        base = self._params.robot_probe_frames
        if timed:
            self._interval = base
            return
        self.lost += 1
        if not cpu_known:
            return
        cost = self._rate * max(busy_s, 0.0) + max(excess, 0.0)
        budget = PROBE_COST_SHARE * max(frame_cost, 1e-9)
        frames = math.ceil(cost / budget) if cost > 0 else base
        self._interval = min(max(base, frames), PROBE_COST_MAX_FACTOR * base)

    def timed(self, miss: int | None, *, on_p: bool = False) -> None:
        """After a robot measurement (`miss`: `RobotCostModel.observe`'s answer); `on_p`: of a
        frame served on the robot, which was a probe if one was tried by serving it there."""
        p_probe = on_p and self._on_p
        if on_p:
            self._on_p = False
        if miss is None:
            return
        self._bounded = False  # timed (a stopped run's bound sets it again in `bounded`)
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
