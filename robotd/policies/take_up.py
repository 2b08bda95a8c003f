"""ElasticAction's take-up rule and hint: noticing that an action got cheaper than the choice.

- take-up: an offloading action whose observation (its robot part as estimated plus the cloud
  part observed) costs less than (1 − `takeover_margin`) of the current choice's estimate is
  sampled again on the next frame (hedged), and `takeover_samples` such observations in a row
  start an update period on its evidence (the "faster" direction). Change detection only counts
  misses on actions the model knows; an action that rests on a few samples, e.g. the cloud after
  a bad phase while the robot served every frame, would otherwise be learned one forced sample
  at a time, its old samples outweighing the new ones for hundreds of frames. The rule needs no
  count of samples: it only compares what the action just cost with what is being served.
- hint: while P serves, an unknown explored action answering faster than predicted makes the next
  frame sample the action that was cheapest at its best (`TakeUp.hint`), so take-up can judge
  the action worth taking rather than whichever had the largest confidence bonus.

The column to sample next (`challenger`) is read and cleared by the policy's `decide`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from robotd.policies.change_detector import MIN_PREDICTION, ChangeDetector
from robotd.policies.params import ElasticParams
from robotd.policies.schedule import ForcedSchedule


class TakeUp:
    """The take-up and hint state of one ElasticAction policy (see the module docstring)."""

    def __init__(
        self, params: ElasticParams, detector: ChangeDetector, schedule: ForcedSchedule
    ) -> None:
        self._params = params
        self._detector = detector
        self._schedule = schedule
        self._margin = params.takeover_margin
        # The rule starts update periods, so it needs change detection.
        self._enabled = self._margin > 0.0 and params.change_detection
        # Per column, the cloud-side observations in a row that beat the current choice by the
        # margin; the column to sample on the next frame to confirm them.
        self._beating: dict[int, list[float]] = {}
        self.challenger: int | None = None
        self.takeovers = 0
        # Per column, the least cloud-side cost it was ever seen to take (`hint`).
        self._best_seen: dict[int, float] = {}
        self._next_hint = 0  # no hint before this frame

    def forget(self) -> None:
        """An update period started: the candidates were judged against the old conditions."""
        self._beating.clear()
        self.challenger = None

    def observe(
        self, j: int, target: float, robot_part: float, choice: Callable[[], tuple[float, int]]
    ) -> bool:
        """Column j was seen to take `target` on the cloud side (`robot_part`: the rest of its
        cost, as estimated). Take-up rule: True when this observation, with the ones before it
        in a row, beat the current choice (`choice()`: its estimated cost and column, -1 for
        P) by `takeover_margin` and started an update period on j's evidence; a first beating
        observation asks for j on the next frame."""
        if target < self._best_seen.get(j, math.inf):
            self._best_seen[j] = target
        if not self._enabled:
            return False
        current, greedy = choice()
        observed = robot_part + target
        beating = self._beating.setdefault(j, [])
        if greedy == j or observed >= (1.0 - self._margin) * current:
            beating.clear()
            return False
        beating.append(target)
        if len(beating) < self._params.takeover_samples:
            self.challenger = j
            return False
        misses = [(j, y) for y in beating]
        self.forget()
        self._detector.enter(j, -1, misses, only_p_out=greedy < 0)
        self.takeovers += 1
        return True

    def hint(
        self,
        j: int,
        target: float,
        frame: int,
        current: tuple[float, int],
        allowed_base: Sequence[float],
        pred: Sequence[float],
    ) -> None:
        """Column j answered faster than predicted while P serves every frame (`current`: the
        estimates' choice, column -1 for P, and its cost; `allowed_base`, `pred`: per column,
        the cost and the cloud part as estimated): offloading may have got cheaper (a bad phase
        ended), but j itself need not be the action to take (an explored action far from
        competitive). Sample on the next frame the action that was cheapest at its best: its
        robot part plus the least cloud part it was ever seen to take (an action never seen:
        its prediction shrunk as j's answer shrank), if that beat P by `takeover_margin`. The
        take-up rule then judges it on its own answers. The sample is hedged; on a link that is
        still bad it only confirms the estimate."""
        margin = self._margin
        if margin <= 0.0 or self.challenger is not None or frame < self._next_hint:
            return
        if self._detector.direction != 0:
            return  # a restricted period is learning the new conditions afresh: no hints
        p_cost, greedy = current
        if greedy >= 0:
            return
        ratio = max(target, 0.0) / max(pred[j], MIN_PREDICTION)
        seen = self._best_seen
        best_case = [
            b - y + (seen[a] if a in seen else y * ratio)
            for a, (b, y) in enumerate(zip(allowed_base, pred, strict=False))
        ]
        best = min(best_case)
        candidate = best_case.index(best)
        # Only an action that at its best beat P by the margin is worth a sample; j itself
        # is not asked for again (its own answers already teach the regression, and samples
        # of it in a row would make ordinary misses look like a change).
        if candidate != j and best < (1.0 - margin) * p_cost:
            self.challenger = candidate
            # At most one hint per forced interval: on a link that is still bad, every hinted
            # sample costs a hedged frame (and, paced, delays the frames behind it).
            self._next_hint = frame + self._schedule.interval(frame)
