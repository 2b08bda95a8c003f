"""ElasticAction's change detector: miss streaks, parameter-update periods, direction restriction.

`change_frames` residuals in a row, same sign, each off by more than `change_tolerance` of the
prediction, on actions the model knows (their prediction rests on about `known_samples`
observations or more), start a parameter-update period. Old evidence is dropped (Q, p are reset
and the misses that revealed the change are replayed) and the actions are restricted in one
direction: slower than predicted → only actions sending no more data than the one that missed
(and P); faster → only actions sending at least as much. The period ends after `fit_frames`
fitting predictions in a row, or when the mean relative residual of the last `fit_frames` is
within half the tolerance (on a link whose times come in steps, single residuals of ±30% are
noise, and "in a row" would hardly ever happen). Inside a restricted period, `change_frames`
misses in a row *against* its direction, on actions that already fitted in it, start a period the
other way: the link that fell while only actions sending more (and not P) were allowed is
noticed. A run starts in an unrestricted period (nothing is known yet).

Confirmation: after a single miss the next frame is a forced frame (`confirm`, read and cleared by
the policy's `decide`: it samples the cloud, hedged if the policy would not otherwise offload), so
a change is confirmed within `change_frames` frames rather than `change_frames` forced intervals.

The detector owns the regression's updates while change detection is on: an observation either
goes into the regression or, when it reveals a change, restarts it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np

from robotd.policies.params import ElasticParams
from robotd.policies.ridge import RidgeEstimator

# Relative residuals are taken against at least this prediction (objective units), so a
# near-zero prediction does not turn every residual into a miss.
MIN_PREDICTION = 1e-3
# An update period ends when the mean relative residual of its last fit_frames observations is
# within this share of change_tolerance.
FIT_BIAS_SHARE = 0.5


def miss_tolerance(params: ElasticParams, pred: float) -> tuple[float, float]:
    """(scale, tolerance) of a residual against prediction `pred`: relative residuals are taken
    against `scale`, and a residual off by more than `tolerance` (objective units) is a miss."""
    scale = max(abs(pred), MIN_PREDICTION)
    return scale, params.change_tolerance * scale


class ChangeDetector:
    """The change detector and direction restriction of one ElasticAction policy (see the module
    docstring). `mask` (None: every cut allowed), `p_allowed`, `updating`, `direction` and
    `confirm` are read by the policy on every frame."""

    def __init__(
        self, params: ElasticParams, ridge: RidgeEstimator, sizes: Sequence[float]
    ) -> None:
        self._params = params
        self._ridge = ridge
        self._sizes = sizes  # bytes each column sends, as the policy learns them (shared)
        # Direction restriction: None means every cut is allowed.
        self.mask: list[bool] | None = None
        self.p_allowed = True
        # A run starts in an (unrestricted) update period when change detection is on.
        self.updating = params.change_detection
        # The period's restriction: +1 slower (less data, P allowed), -1 faster, 0 none.
        self.direction = 0
        # A single miss asks for a forced frame next (cleared by the policy when it decides).
        self.confirm = False
        self.update_periods = 0
        self._period_frames = 0
        self._fits = 0
        # Relative residuals of the period's last `fit_frames` observations: their mean decides
        # when predictions fit again (one by one, a noisy link would rarely fit in a row).
        self._recent: deque[float] = deque(maxlen=params.fit_frames)
        # Columns whose prediction fitted in this period (first: the one whose misses started
        # it): only their misses can reveal that conditions changed again.
        self._fitted: set[int] = set()
        self._streak: list[tuple[int, float]] = []
        self._streak_sign = 0

    def observe(self, j: int, target: float, pred: float, known: bool) -> bool:
        """Update the regression and the detector with one cloud-side observation `target` of
        column j, predicted `pred` (`known`: the model knows j well). True when it started an
        update period."""
        params = self._params
        residual = target - pred
        # `miss_tolerance`, inlined: this runs on every offloaded frame.
        scale = max(abs(pred), MIN_PREDICTION)
        tolerance = params.change_tolerance * scale
        sign = 1 if residual > 0 else -1
        if self.updating:
            missed = abs(residual) > tolerance
            if self._reversed(j, sign, missed, target):
                return True
            if not missed:
                self._fitted.add(j)
            self._ridge.update(j, target)
            self._period_frames += 1
            self._fits = self._fits + 1 if abs(residual) <= tolerance else 0
            recent = self._recent
            recent.append(residual / scale)
            # Fitting again: fit_frames predictions in a row within the tolerance, or (on a
            # noisy link, where single residuals often miss) the mean residual of the last
            # fit_frames well inside it; leaving on a bias just inside the tolerance would let
            # the next residuals on the same bias start another period.
            fits = self._fits >= params.fit_frames or (
                len(recent) >= params.fit_frames
                and abs(sum(recent)) <= FIT_BIAS_SHARE * params.change_tolerance * len(recent)
            )
            if fits or self._period_frames >= params.max_update_frames:
                self.leave()
            return False
        # Only an action the model knows well can reveal a change; a surprise on an action still
        # being explored is ordinary learning.
        if known and abs(residual) > tolerance:
            if sign != self._streak_sign:
                self._streak.clear()
                self._streak_sign = sign
            self._streak.append((j, target))
            if len(self._streak) >= params.change_frames:
                self.enter(j, sign, self._streak)
                return True
            self.confirm = params.confirm_misses
        else:
            self._streak.clear()
            self._streak_sign = 0
        self._ridge.update(j, target)
        return False

    def _reversed(self, j: int, sign: int, missed: bool, target: float) -> bool:
        """Inside a restricted update period: `change_frames` misses in a row against its
        direction (slower while only actions sending more are allowed, e.g. the link fell
        during a period that excludes P; or faster while only actions sending less are), on
        actions whose prediction already fitted in this period (the first: the one whose misses
        started it), start a period the other way. True when that happened (the observation then
        went into the new period). Misses in the period's own direction are left to the
        regression: restarting on them would discard what the period has learned."""
        if self.direction == 0 or j not in self._fitted:
            return False  # unrestricted, or an action still being learned: not a miss nor a fit
        if not missed or sign == self.direction:
            self._streak.clear()
            self._streak_sign = 0
            return False
        if sign != self._streak_sign:
            self._streak.clear()
            self._streak_sign = sign
        self._streak.append((j, target))
        if len(self._streak) < self._params.change_frames:
            return False
        self.enter(j, sign, self._streak)
        return True

    def enter(
        self, j: int, sign: int, evidence: list[tuple[int, float]], only_p_out: bool = False
    ) -> None:
        """Start a parameter-update period after the action in column j missed repeatedly
        (`evidence`: the (column, observation) pairs that revealed it; `only_p_out`: a take-up
        of j over P, whose period leaves P out and every cut in)."""
        misses = list(evidence)
        self._streak.clear()
        self._streak_sign = 0
        # Old evidence describes the old conditions; the misses are the first of the new ones.
        self._ridge.reset()
        for row, y in misses:
            self._ridge.update(row, y)
        if self._params.direction_restriction:
            sizes = np.array(self._sizes)
            anchor = sizes[j]
            if only_p_out:
                self.mask = [True] * len(sizes)
                self.p_allowed = False
            elif sign > 0:
                self.mask = (sizes <= anchor).tolist()
                self.p_allowed = True
            else:
                self.mask = (sizes >= anchor).tolist()
                self.p_allowed = False
            self.direction = sign
        self._fitted = {j}
        self.updating = True
        self._period_frames = 0
        self._fits = 0
        self._recent.clear()
        self.update_periods += 1

    def leave(self) -> None:
        """End the update period: every action is allowed again."""
        self.updating = False
        self.mask = None
        self.p_allowed = True
        self.direction = 0
        self._fitted.clear()
        self._fits = 0
        self._recent.clear()
        self._streak.clear()
        self._streak_sign = 0
