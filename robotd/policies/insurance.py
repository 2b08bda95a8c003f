"""Whether an insurance local run is worth its robot time, on a robot whose CPU counts.

A hedged frame whose local run is expected to lose to the reply (an update period's frame, an
exploring one) runs it as insurance: it starts once the reply is overdue, and serves the frame
only if the reply comes later than the start plus the run's own time L. Until the reply stops
it, the run keeps the robot computing, which on a robot that reports its CPU is counted in the
objective at `robot_rate` per second (docs/policies.md, "Exploration's robot time is counted").

Once a reply is overdue, how much later it comes is taken as memoryless with the mean m of the
overdue replies seen (`lateness_s`, an EWMA). A run started then costs `robot_rate`·m·(1 − e^(−L/m))
in expectation and saves `wait_rate`·m·e^(−L/m), so it is worth starting when L < m·ln((wait_rate +
robot_rate) / robot_rate): m·ln 2 with the default objective. On the testbed's 0.1-core robot the
whole model takes 0.2 s and an overdue reply on a loaded host comes some 50 ms later: insurance
runs started there only burnt CPU (5-11 ms a frame, the robot-CPU p95), and are left out. A link
that breaks makes replies late by seconds (timeouts teach the deadline), and insurance is back.
"""

from __future__ import annotations

import math

# Weight of a new overdue reply in the lateness average.
LATENESS_EWMA = 0.1


class Insurance:
    """The lateness of overdue replies and the rule above, for one policy."""

    def __init__(self, wait_rate: float, robot_rate: float) -> None:
        total = wait_rate + robot_rate
        self._factor = math.log(total / robot_rate) if robot_rate > 0 else math.inf
        self.lateness_s: float | None = None
        """Mean time by which an overdue reply was later than overdue, seconds (None: none yet)."""

    def observe(self, waited_s: float, overdue_s: float) -> None:
        """A reply (or the deadline) came `waited_s` after the request; it was overdue from
        `overdue_s`."""
        late = waited_s - overdue_s
        if late <= 0:
            return
        m = self.lateness_s
        self.lateness_s = late if m is None else m + LATENESS_EWMA * (late - m)

    def worth(self, local_s: float) -> bool:
        """Whether a local run of `local_s` started when the reply is overdue pays for its
        robot time (True until an overdue reply was seen)."""
        m = self.lateness_s
        return m is None or local_s < m * self._factor
