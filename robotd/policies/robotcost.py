"""The robot-side cost E^c of every action, learned online from measured robot times.

The profile gives the shape (how the model's time splits across cuts; the robot daemon profiles
on the robot itself, so it also gives the starting scale); the robot's measurements follow the
scale. Every timed run (a prefix, a local
suffix, the whole model) updates one EWMA of the robot's speed relative to the profile, so a CPU
drop seen on any action raises the estimate of all of them at once. Two measurements in a row that
miss the estimate by more than a tolerance in the same direction make it jump to them: a change of
CPU availability is adopted in two timed frames instead of an EWMA's slow convergence, and the
EWMA itself can stay smooth. Runs of a small share of the model only nudge the EWMA: under a CPU
quota their time is mostly scheduling delay, not work.

The first timed run gets no more weight than any other. A hedged local run races the offload for
the CPU and the first frame of a process pays for cold caches: on a 0.5-core robot the first
frame's local run took 0.23 s for a model that runs in 0.085 s. Adopted as the robot's speed, it
made P look 2.7x dearer than it is, and the robot offloaded at 0.13 s a frame for a dozen frames
until two more timed runs corrected it. Against the profile's scale it is one miss, held as a
suspect until a second confirms it.
"""

from __future__ import annotations

from robotd.policies.base import CutTable, FloatArray
from robotd.policies.objective import Objective
from robotd.policies.params import RobotCostParams

# Runs shorter than this on the profiling host carry too little signal to time (cut 0's prefix).
MIN_TIMED_S = 2e-4
# A run of less than this share of the whole model is a weak measurement of the robot's speed:
# on a CPU quota its time is mostly the wait for the next scheduling period (a prefix of 1% of the
# model can take as long as the whole model). Such runs move the estimate by the EWMA only, with
# a weight scaled down by their share, and never make it jump.
SHORT_RUN_SHARE = 0.25


class RobotCostModel:
    """Robot compute cost per action (objective units), from the profile and measured times."""

    def __init__(self, cuts: CutTable, objective: Objective, params: RobotCostParams) -> None:
        self._cuts = cuts
        self._rate = objective.robot_rate
        self._ewma = params.robot_ewma
        self._tolerance = params.robot_change_tolerance
        # Relative speed: measured / profiled seconds; the profile's own scale to begin with.
        self.ratio = 1.0
        # Short runs only nudge a scale that a real run has confirmed (see `observe`).
        self.timed = False
        self._suspect_sign = 0
        self._suspect_ratio = 0.0
        self.frames_since_timed = 0
        # Cost of one profiled second of robot compute; a prefix costs prefix_s·unit_cost.
        self.unit_cost = self._rate
        self.full_cost = cuts.full_s * self._rate

    @property
    def prefix_cost(self) -> FloatArray:
        """Robot cost of every prefix, in cut order (computed on demand)."""
        return self._cuts.prefix_s * self.unit_cost

    @property
    def scale(self) -> float:
        """Robot seconds per profiled second."""
        return self.ratio

    @property
    def suspect(self) -> bool:
        """True when the last timed run missed the estimate and awaits confirmation."""
        return self._suspect_sign != 0

    def tick(self) -> None:
        """Count a frame; timed runs reset the count (used to decide when to probe)."""
        self.frames_since_timed += 1

    def observe(self, measured_s: float | None, profiled_s: float) -> int | None:
        """Learn from a run that took `measured_s` on the robot and `profiled_s` when profiled.

        Returns None when the run does not time the robot (not run, or shorter than
        SHORT_RUN_SHARE of the model: it only nudges the estimate), else how it compared with the
        estimate before it: 0 within the tolerance, 1 slower, -1
        faster."""
        if measured_s is None or measured_s <= 0 or profiled_s < MIN_TIMED_S:
            return None
        share = profiled_s / self._cuts.full_s
        if share < SHORT_RUN_SHARE:
            # A short run only nudges an estimate and does not count as timing the robot: a JPEG
            # encode of 0.3 ms took 3 ms under a 0.5-core quota. Taken as the first estimate it
            # made P look 10x dearer than it is (so P was never tried); counted as timing, it kept
            # the robot probes away that would have seen P was cheap again.
            if not self.timed:
                return None
            sample = float(measured_s) / profiled_s
            self.ratio += self._ewma * (share / SHORT_RUN_SHARE) * (sample - self.ratio)
            self._rescale()
            return None
        self.frames_since_timed = 0
        self.timed = True
        # float(): a numpy scalar would make every later operation on the ratio slower.
        sample = float(measured_s) / profiled_s
        miss = sample / self.ratio - 1.0
        sign = 0 if abs(miss) <= self._tolerance else (1 if miss > 0 else -1)
        if sign != 0 and sign == self._suspect_sign:
            # Second miss in the same direction: the robot changed; adopt the new speed.
            self.ratio = 0.5 * (sample + self._suspect_ratio)
            self._suspect_sign = 0
        elif sign != 0:
            self._suspect_sign, self._suspect_ratio = sign, sample
        else:
            self._suspect_sign = 0
            self.ratio += self._ewma * (sample - self.ratio)
        self._rescale()
        return sign

    def observe_slower_than(self, busy_s: float, profiled_s: float) -> int | None:
        """Learn from a run that was stopped unfinished after `busy_s` on the robot (a hedged
        local run that lost its race to the reply) and takes `profiled_s` when profiled: the
        robot needs more than `busy_s` for it. A bound above the estimate by more than the
        tolerance is a miss like a measurement (`observe`); any other bound says nothing.
        A robot profiled at full speed and then given a tenth of a core, whose only local runs
        are probes the reply always stops, otherwise kept its profile's speed: its whole model
        looked 10x cheaper than it was, and the probes' deferral and price with it."""
        if (
            busy_s <= 0
            or profiled_s < MIN_TIMED_S
            or profiled_s < SHORT_RUN_SHARE * self._cuts.full_s
        ):
            return None
        if busy_s / profiled_s <= self.ratio * (1.0 + self._tolerance):
            return None
        return self.observe(busy_s, profiled_s)

    def _rescale(self) -> None:
        ratio = self.scale
        self.unit_cost = self._rate * ratio
        self.full_cost = self._cuts.full_s * self._rate * ratio
