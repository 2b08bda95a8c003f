"""ElasticAction (policy `elastic`) and μLinUCB from Autodidactic Neurosurgeon (policy `ans`).

Both estimate the cloud-side cost y of each offloading action a as α̂ᵀv_a, with the context
v_a = [MB sent, share of the model left to the cloud, 1] (so α̂ learns seconds per MB, the cloud's
time for the whole model and the fixed round-trip cost; with segments among the actions a fourth
feature, MB returned: `robotd.policies.segment_actions`), and choose

    a_t = argmin_a  E_a^c + α̂ᵀv_a − β·E_P·sqrt((1−σ_t)·v_aᵀQ⁻¹v_a),   P scored by E_P^c,

where E^c is the robot-side cost (`RobotCostModel`), σ_t the key-frame weight of the frame's
entropy and β is relative to the pure-robot cost E_P so one default fits fast and slow robots.
On forced-sampling frames the choice is restricted to offloading actions. Only offloaded frames
update the regression.

`elastic` adds what ElasticROS adds to μLinUCB:
- change detection: `change_frames` residuals in a row, same sign, each off by more than
  `change_tolerance` of the prediction, on actions the model knows (their prediction rests on
  about `known_samples` observations or more), start a parameter-update period. Old evidence is
  dropped (Q, p are reset and the misses that revealed the change are replayed) and the actions
  are restricted in one direction: slower than predicted → only actions sending no more data
  than the one that missed (and P); faster → only actions sending at least as much. The period
  ends after `fit_frames` fitting predictions in a row, or when the mean relative residual of
  the last `fit_frames` is within half the tolerance (on a link whose times come in steps,
  single residuals of ±30% are noise, and "in a row" would hardly ever happen). Inside a
  restricted period, `change_frames` misses in a row *against* its direction, on actions that
  already fitted in it, start a period the other way: the link that fell while only actions
  sending more (and not P) were allowed is noticed. A run starts in an unrestricted period
  (nothing is known yet).
- hedging: an exploring frame — one whose action differs from what the estimates alone would
  choose, because it is a forced frame or because its confidence bonus won — and every offloaded
  frame of an update period, is also computed on the robot and served by the faster path;
  exploration then costs CPU and bandwidth, not latency. The local run starts
  `Decision.hedge_after_s` after the request: one expected to beat the reply at the latest
  moment that still finishes it when the greedy choice would have served the frame; one expected
  to lose to it once the reply is overdue. A local run that cannot beat the expected reply then
  does not compete with the offload for the robot's CPU.
- robot probes (`robotd.policies.robot_probes`): when the robot has not been timed for
  `robot_probe_frames` frames (its actions run less than `SHORT_RUN_SHARE` of the model there,
  e.g. cut 0 with a JPEG encode), the next offloaded frame is hedged at once, so a robot that got
  faster again is noticed. Without hedging the probe serves the frame on the robot (P) instead,
  and each probe that finds the estimate right doubles the interval to the next (up to
  `ROBOT_PROBE_MAX_FACTOR` times), as these probes cost latency; one that finds it wrong is
  confirmed by a probe on the next frame.
- confirmation: after a single miss the next frame is a forced frame (so it samples the cloud,
  hedged if the policy would not otherwise offload), and a change is confirmed within
  `change_frames` frames rather than `change_frames` forced intervals.
- take-up: an offloading action whose observation (its robot part as estimated plus the cloud
  part observed) costs less than (1 − `takeover_margin`) of the current choice's estimate is
  sampled again on the next frame (hedged), and `takeover_samples` such observations in a row
  start an update period on its evidence (the "faster" direction). Change detection only counts
  misses on actions the model knows; an action that rests on a few samples, e.g. the cloud after
  a bad phase while the robot served every frame, would otherwise be learned one forced sample
  at a time, its old samples outweighing the new ones for hundreds of frames. The rule needs no
  count of samples: it only compares what the action just cost with what is being served.
- hint: while P serves, an unknown explored action answering faster than predicted makes the next
  frame sample the action that was cheapest at its best (`_hint_cheaper`), so take-up can judge
  the action worth taking rather than whichever had the largest confidence bonus.

A frame the cloud did not answer teaches y = the time the robot waited (its deadline): a dead or
congested route then looks expensive instead of unknown, and the miss feeds change detection.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from robotd.policies.base import (
    BYTES_PER_MB,
    PURE_ROBOT,
    CutTable,
    Decision,
    FrameContext,
    Outcome,
    Policy,
)
from robotd.policies.objective import Objective, cloud_cost
from robotd.policies.params import AnsParams, ElasticParams
from robotd.policies.ridge import RidgeEstimator, quadratic_features
from robotd.policies.robot_probes import RobotProbes
from robotd.policies.robotcost import SHORT_RUN_SHARE, RobotCostModel
from robotd.policies.schedule import ForcedSchedule
from robotd.policies.segment_actions import action_contexts

# Relative residuals are taken against at least this prediction (objective units), so a
# near-zero prediction does not turn every residual into a miss.
MIN_PREDICTION = 1e-3
# A failed attempt with no reported wait is charged this multiple of its prediction.
UNKNOWN_WAIT_FACTOR = 2.0
# An update period ends when the mean relative residual of its last fit_frames observations is
# within this share of change_tolerance.
FIT_BIAS_SHARE = 0.5
# Learned bytes of an action change its context only when they moved by more than this share.
BYTES_CHANGE_SHARE = 0.02
# Action costs within this share of the whole model's time count as equal when dominated
# actions are left out (`CutTable.undominated`).
DOMINANCE_SLACK = 0.05


class ElasticPolicy(Policy):
    """ElasticAction; with change detection, restriction and hedging off it is μLinUCB (`ans`)."""

    name = "elastic"

    def __init__(
        self, cuts: CutTable, params: ElasticParams, objective: Objective, name: str = "elastic"
    ) -> None:
        if params.prune_dominated:
            cuts = cuts.undominated(DOMINANCE_SLACK)
        super().__init__(cuts)
        self.name = name
        self.params = params
        self.objective = objective
        mb = cuts.bytes / BYTES_PER_MB
        # [MB sent, cloud share, 1], and MB returned when segments are among the actions.
        self.contexts = action_contexts(cuts)
        # Bytes sent per action, learned online: a JPEG's size follows the content.
        self._bytes: list[float] = cuts.bytes.tolist()
        self._ridge = RidgeEstimator(self.contexts, params.gamma)
        self._robot = RobotCostModel(cuts, objective, params)
        self._wait_rate = objective.wait_rate
        self._radio_rate = objective.radio_rate
        self._schedule = ForcedSchedule(
            params.forced_schedule,
            params.forced_start_frames,
            params.forced_exponent,
            params.forced_every_frames,
        )
        self._position = cuts.positions()
        # Segments are never hedged; a failed one ran no tail (`CutTable.tails`).
        self._segment = [e is not None for e in cuts.ends]
        self._head_s = (cuts.prefix_s - cuts.tail_s).tolist()
        # Actions whose robot part is too short to time the robot (`RobotCostModel.observe`).
        self._untimed = (cuts.prefix_s < SHORT_RUN_SHARE * cuts.full_s).tolist()
        self._known_width = 1.0 / math.sqrt(params.known_samples)
        self._key_factor = math.sqrt(1.0 - params.sigma_key)
        self._nonkey_factor = math.sqrt(1.0 - params.sigma_nonkey)
        # Per-frame work runs on Python floats and lists: with 16 cuts and d = 3 a numpy call
        # costs more than the arithmetic it does (docs/policies.md, "Decision cost"). The one
        # numpy call left gives every action's base cost, quadratic form and prediction at once:
        #   [V 0 prefix_s bytes_cost; 0 W 0 0; V 0 0 0] @ [α̂; vec Q⁻¹; robot unit cost; 1],
        # with W_a = vec(v_a v_aᵀ).
        self._k = k = cuts.size
        d = self.contexts.shape[1]
        self._features = np.zeros((3 * k, d + d * d + 2))
        self._features[:k, :d] = self.contexts
        self._features[:k, -2] = cuts.prefix_s
        self._features[:k, -1] = objective.bytes * mb
        self._features[k : 2 * k, d : d + d * d] = quadratic_features(self.contexts)
        self._features[2 * k :, :d] = self.contexts
        self._base_features = self._features[:k]  # all a robot measurement changes
        self._coef = np.empty(self._features.shape[1])
        self._prefix_s: list[float] = cuts.prefix_s.tolist()
        self._suffix_s: list[float] = cuts.suffix_s.tolist()
        self._frame = 0
        # Direction restriction: None means every cut is allowed.
        self._mask: list[bool] | None = None
        self._p_allowed = True
        # A run starts in an (unrestricted) update period when change detection is on.
        self._updating = params.change_detection
        self._period_frames = 0
        self._fits = 0
        # Relative residuals of the period's last `fit_frames` observations: their mean decides
        # when predictions fit again (one by one, a noisy link would rarely fit in a row).
        self._recent: deque[float] = deque(maxlen=params.fit_frames)
        # The period's restriction: +1 slower (less data, P allowed), -1 faster, 0 none.
        self._direction = 0
        # Columns whose prediction fitted in this period (first: the one whose misses started
        # it): only their misses can reveal that conditions changed again.
        self._fitted: set[int] = set()
        self._streak: list[tuple[int, float]] = []
        self._streak_sign = 0
        self._confirm = False
        self.update_periods = 0
        # Take-up: per column, the cloud-side observations in a row that beat the current
        # choice by the margin; the column to sample on the next frame to confirm them.
        self._beating: dict[int, list[float]] = {}
        self._challenger: int | None = None
        self.takeovers = 0
        # Per column, the least cloud-side cost it was ever seen to take (`_hint_cheaper`).
        self._best_seen: dict[int, float] = {}
        self._next_hint = 0  # no hint before this frame
        # When to time the robot on a frame whose action runs nothing measurable there.
        self._probes = RobotProbes(params, self._robot, self._untimed)
        # Score parts, cut order: base = E^c + bytes cost + α̂ᵀv (inf where restricted away in
        # `_allowed_base`), width = sqrt(vᵀQ⁻¹v); score = base − sqrt(1−σ)·β·E_P·width, with
        # `_bonus_scale` = β·E_P; `_pred` = α̂ᵀv.
        self._base: list[float] = []
        self._pred: list[float] = []
        self._allowed_base: list[float] = []
        self._width: list[float] = []
        self._bonus_scale = 0.0
        self._best_key = self._best_nonkey = self._cheapest = (math.inf, 0)
        self._refresh(learned=True)

    # -- decisions -------------------------------------------------------------------------

    def decide(self, ctx: FrameContext) -> Decision:
        n = self._frame
        self._frame = n + 1
        robot = self._robot
        robot.tick()
        self._probes.tick()
        params = self.params
        best, j = self._best_key if ctx.entropy >= params.key_entropy else self._best_nonkey
        p_cost = robot.full_cost
        regular_p = self._p_allowed and p_cost <= best
        forced = self._confirm or self._schedule.is_forced(n)
        self._confirm = False
        challenger = self._challenger
        if challenger is not None:
            # Confirm a take-up candidate on this frame (it is allowed: a restriction starts
            # only with an update period, which clears the candidate).
            self._challenger = None
            j, forced = challenger, True
        if regular_p and not forced:
            return Decision(PURE_ROBOT, updating=self._updating, predicted_cost=p_cost)
        probe = self._probes.due(j)
        if not params.hedge:
            if probe and self._p_allowed and not forced:
                # Without hedging the robot is timed by serving the frame on it.
                self._probes.tried(on_p=True)
                return Decision(PURE_ROBOT, updating=self._updating, predicted_cost=p_cost)
            return self.cuts.decision_at(
                j, forced=forced, updating=self._updating, predicted_cost=self._base[j]
            )
        # Exploring = serving something else than the estimates alone would choose.
        cheapest, greedy = self._cheapest
        if self._p_allowed and p_cost <= cheapest:
            greedy = -1
        hedge = greedy != j or self._updating or probe
        if self._segment[j]:
            # Explored unhedged: a local race would run the whole suffix from the start cut,
            # while the reply still needs the tail (`Decision`); a probe waits for a cut.
            hedge = False
        after_s = 0.0
        if hedge:
            self._probes.tried()  # a hedged frame times the robot when its local run wins
            if not probe:
                after_s = self._hedge_after_s(j, greedy)
        return self.cuts.decision_at(
            j,
            hedge=hedge,
            forced=forced,
            updating=self._updating,
            predicted_cost=self._base[j],
            hedge_after_s=after_s,
            local_expected=hedge and greedy < 0,
        )

    def _hedge_after_s(self, j: int, greedy: int) -> float:
        """When a hedged frame of cut j starts its local run, in seconds after the request left.

        The local run is speculative: started at once it competes with the offload for the
        robot's CPU (and on a small CPU quota slows it). A local run expected to finish before
        the reply races it, starting at the latest moment that still finishes it by the time the
        greedy choice (`greedy`: a column, -1 for P) would have served the frame (at once when
        that is P: every cut's prefix and suffix make the whole model). A local run expected to
        lose to the reply is insurance: it starts when the reply is overdue (its prediction
        plus `change_tolerance`), unless the greedy bound asks for it later."""
        rate = self._wait_rate + self._radio_rate  # objective units per second of cloud wait
        if rate <= 0:
            return 0.0
        scale = self._robot.scale
        if greedy < 0:
            target_s = self.cuts.full_s * scale
        else:
            target_s = self._prefix_s[greedy] * scale + max(self._pred[greedy], 0.0) / rate
        slack_s = target_s - self._prefix_s[j] * scale - self._suffix_s[j] * scale
        local_s = self._suffix_s[j] * scale
        reply_s = max(self._pred[j], 0.0) / rate
        if reply_s >= local_s:
            return max(slack_s, 0.0)
        return max(slack_s, (1.0 + self.params.change_tolerance) * reply_s)

    # -- learning --------------------------------------------------------------------------

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        robot = self._robot
        if decision.action == PURE_ROBOT:
            self._probes.timed(robot.observe(outcome.prefix_s, self.cuts.full_s), on_p=True)
            self._refresh(learned=False)
            return
        j = self._position[(int(decision.action), decision.codec, decision.end)]
        self._learn_bytes(j, outcome.bytes_up)
        robot_s = self._prefix_s[j] if outcome.cloud_s is not None else self._head_s[j]
        self._probes.timed(robot.observe(outcome.prefix_s, robot_s))
        if outcome.local_s is not None:
            self._probes.timed(robot.observe(outcome.local_s, self._suffix_s[j]))
        if outcome.cloud_s is not None:
            target = cloud_cost(
                self._wait_rate, self._radio_rate, outcome.cloud_s, outcome.cloud_compute_s
            )
        elif outcome.waited_s is not None:
            target = cloud_cost(self._wait_rate, self._radio_rate, outcome.waited_s, None)
        else:
            target = UNKNOWN_WAIT_FACTOR * max(self._pred[j], MIN_PREDICTION)
        if target < self._best_seen.get(j, math.inf):
            self._best_seen[j] = target
        if self._take_up(j, target):
            pass  # the observation started an update period on this action's evidence
        elif self.params.change_detection:
            self._track(j, target)
        else:
            self._ridge.update(j, target)
        self._refresh(learned=True)

    def _learn_bytes(self, j: int, sent: int) -> None:
        """Follow the bytes action j really sends (EWMA): its context and byte cost move with
        them, once they moved by more than `BYTES_CHANGE_SHARE` (no work on every frame)."""
        if sent <= 0:
            return
        new = self._bytes[j] = self._bytes[j] + self.params.bytes_ewma * (sent - self._bytes[j])
        mb = new / BYTES_PER_MB
        if abs(mb - self.contexts[j, 0]) <= BYTES_CHANGE_SHARE * self.contexts[j, 0]:
            return
        self.contexts[j, 0] = mb
        self._ridge.set_context(j, self.contexts[j])
        k = self._k
        d = self.contexts.shape[1]
        self._features[j, 0] = mb
        self._features[j, -1] = self.objective.bytes * mb
        self._features[k + j, d : d + d * d] = quadratic_features(self.contexts[j : j + 1])[0]
        self._features[2 * k + j, 0] = mb

    def _track(self, j: int, target: float) -> None:
        """Update the regression and the change detector with one cloud-side observation."""
        params = self.params
        pred = self._pred[j]
        residual = target - pred
        scale = max(abs(pred), MIN_PREDICTION)
        tolerance = params.change_tolerance * scale
        sign = 1 if residual > 0 else -1
        if sign < 0 and abs(residual) > tolerance and self._width[j] > self._known_width:
            # A surprise on an action the model does not know: change detection ignores it
            # (below), the hint does not (a known action's misses are confirmed there).
            self._hint_cheaper(j, target)
        if self._updating:
            missed = abs(residual) > tolerance
            if self._reversed(j, sign, missed, target):
                return
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
                self._leave_update()
            return
        # Only an action the model knows well can reveal a change; a surprise on an action still
        # being explored is ordinary learning.
        known = self._width[j] <= self._known_width
        if known and abs(residual) > tolerance:
            if sign != self._streak_sign:
                self._streak.clear()
                self._streak_sign = sign
            self._streak.append((j, target))
            if len(self._streak) >= params.change_frames:
                self._enter_update(j, sign, self._streak)
                return
            self._confirm = params.confirm_misses
        else:
            self._streak.clear()
            self._streak_sign = 0
        self._ridge.update(j, target)

    def _hint_cheaper(self, j: int, target: float) -> None:
        """Column j answered faster than predicted while P serves every frame: offloading may
        have got cheaper (a bad phase ended), but j itself need not be the action to take (an
        explored action far from competitive). Sample on the next frame the action that was
        cheapest at its best: its robot part plus the least cloud part it was ever seen to
        take (an action never seen: its prediction shrunk as j's answer shrank), if that beat P
        by `takeover_margin`. The take-up rule then judges it on its own answers. The sample
        is hedged; on a link that is still bad it only confirms the estimate."""
        margin = self.params.takeover_margin
        if margin <= 0.0 or self._challenger is not None or self._frame < self._next_hint:
            return
        if self._direction != 0:
            return  # a restricted period is learning the new conditions afresh: no hints
        p_cost, greedy = self._current()
        if greedy >= 0:
            return
        ratio = max(target, 0.0) / max(self._pred[j], MIN_PREDICTION)
        seen = self._best_seen
        best_case = [
            b - y + (seen[a] if a in seen else y * ratio)
            for a, (b, y) in enumerate(zip(self._allowed_base, self._pred, strict=False))
        ]
        best = min(best_case)
        candidate = best_case.index(best)
        # Only an action that at its best beat P by the margin is worth a sample; j itself
        # is not asked for again (its own answers already teach the regression, and samples
        # of it in a row would make ordinary misses look like a change).
        if candidate != j and best < (1.0 - margin) * p_cost:
            self._challenger = candidate
            # At most one hint per forced interval: on a link that is still bad, every hinted
            # sample costs a hedged frame (and, paced, delays the frames behind it).
            self._next_hint = self._frame + self._schedule.interval(self._frame)

    def _current(self) -> tuple[float, int]:
        """(estimated cost, column) of what the estimates alone choose now; column -1: P."""
        current, greedy = self._cheapest
        p_cost = self._robot.full_cost
        if self._p_allowed and p_cost <= current:
            return p_cost, -1
        return current, greedy

    def _take_up(self, j: int, target: float) -> bool:
        """Take-up rule: True when this observation of column j, with the ones before it in a
        row, beat the current choice by `takeover_margin` and started an update period on j's
        evidence; a first beating observation asks for j on the next frame."""
        params = self.params
        margin = params.takeover_margin
        if margin <= 0.0 or not params.change_detection:
            return False
        current, greedy = self._current()
        beating = self._beating.setdefault(j, [])
        # The robot part and the bytes as estimated (base − prediction), the cloud part seen.
        observed = self._base[j] - self._pred[j] + target
        if greedy == j or observed >= (1.0 - margin) * current:
            beating.clear()
            return False
        beating.append(target)
        if len(beating) < params.takeover_samples:
            self._challenger = j
            return False
        misses = [(j, y) for y in beating]
        self._beating.clear()
        self._challenger = None
        self._enter_update(j, -1, misses, only_p_out=greedy < 0)
        self.takeovers += 1
        return True

    def _reversed(self, j: int, sign: int, missed: bool, target: float) -> bool:
        """Inside a restricted update period: `change_frames` misses in a row against its
        direction (slower while only actions sending more are allowed, e.g. the link fell
        during a period that excludes P; or faster while only actions sending less are), on
        actions whose prediction already fitted in this period (the first: the one whose misses
        started it), start a period the other way. True when that happened (the observation then
        went into the new period). Misses in the period's own direction are left to the
        regression: restarting on them would discard what the period has learned."""
        if self._direction == 0 or j not in self._fitted:
            return False  # unrestricted, or an action still being learned: not a miss nor a fit
        if not missed or sign == self._direction:
            self._streak.clear()
            self._streak_sign = 0
            return False
        if sign != self._streak_sign:
            self._streak.clear()
            self._streak_sign = sign
        self._streak.append((j, target))
        if len(self._streak) < self.params.change_frames:
            return False
        self._enter_update(j, sign, self._streak)
        return True

    def _enter_update(
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
        if self.params.direction_restriction:
            sizes = np.array(self._bytes)
            anchor = sizes[j]
            if only_p_out:
                self._mask = [True] * self._k
                self._p_allowed = False
            elif sign > 0:
                self._mask = (sizes <= anchor).tolist()
                self._p_allowed = True
            else:
                self._mask = (sizes >= anchor).tolist()
                self._p_allowed = False
            self._direction = sign
        self._fitted = {j}
        self._updating = True
        self._period_frames = 0
        self._fits = 0
        self._recent.clear()
        self._beating.clear()
        self._challenger = None
        self.update_periods += 1

    def _leave_update(self) -> None:
        self._updating = False
        self._mask = None
        self._p_allowed = True
        self._direction = 0
        self._fitted.clear()
        self._fits = 0
        self._recent.clear()
        self._streak.clear()
        self._streak_sign = 0

    def _refresh(self, learned: bool) -> None:
        """Recompute the score parts after an observation (`learned`: the regression changed)."""
        robot = self._robot
        coef = self._ridge.coefficients()
        coef += (robot.unit_cost, 1.0)
        self._coef[:] = coef
        if not learned:
            self._base = base = self._base_features.dot(self._coef).tolist()
        else:
            values = self._features.dot(self._coef).tolist()
            k = self._k
            self._base = base = values[:k]
            quad = values[k : 2 * k]
            try:
                self._width = list(map(math.sqrt, quad))
            except ValueError:  # round-off can leave a tiny negative form once Q is large
                self._width = [math.sqrt(x) if x > 0.0 else 0.0 for x in quad]
            self._pred = values[2 * k :]
        mask = self._mask
        self._allowed_base = (
            base
            if mask is None
            else [b if ok else math.inf for b, ok in zip(base, mask, strict=True)]
        )
        self._bonus_scale = self.params.beta * robot.full_cost
        self._choose()

    def _choose(self) -> None:
        """The best score for key and for other frames, and the cheapest action. The scores
        change only in `_refresh`, and σ takes two values: each frame's choice is ready before
        the frame comes, so `decide` costs the same for 4 actions or 64."""
        self._best_key = self._best(self._key_factor)
        self._best_nonkey = self._best(self._nonkey_factor)
        cheapest = min(self._allowed_base)
        self._cheapest = (cheapest, self._allowed_base.index(cheapest))

    def _best(self, factor: float) -> tuple[float, int]:
        """(lowest score, its column; the first of equal ones) for frames of this sqrt(1−σ)."""
        c = factor * self._bonus_scale
        # Equal lengths by construction (strict=True would cost a check on every refresh).
        scores = [b - c * w for b, w in zip(self._allowed_base, self._width, strict=False)]
        best = min(scores)
        return best, scores.index(best)

    # -- introspection ---------------------------------------------------------------------

    def sigma(self, entropy: float) -> float:
        """σ of a frame: the step function of its normalized entropy (key frames explore less)."""
        p = self.params
        return p.sigma_key if entropy >= p.key_entropy else p.sigma_nonkey

    @property
    def robot_probes(self) -> int:
        """Frames served on the robot (P) to time it, without hedging."""
        return self._probes.count

    @property
    def updating(self) -> bool:
        """True inside a parameter-update period."""
        return self._updating

    def allowed_actions(self) -> list[str]:
        """Labels of the actions the direction restriction currently allows (all of them
        outside a period)."""
        labels = self.cuts.labels
        cuts = [labels[i] for i in range(self._k) if self._mask is None or self._mask[i]]
        return [*cuts, PURE_ROBOT] if self._p_allowed else cuts

    def predicted_cloud_cost(self) -> dict[str, float]:
        """α̂ᵀv_a for every offloading action, by label (objective units)."""
        return dict(zip(self.cuts.labels, self._pred, strict=False))

    def learned_bytes(self) -> dict[str, float]:
        """The bytes each offloading action is expected to send, by label."""
        return dict(zip(self.cuts.labels, self._bytes, strict=False))

    def state(self) -> dict[str, Any]:
        return {
            "policy": self.name,
            "frame": self._frame,
            "alpha": list(self._ridge.alpha),
            "samples": self._ridge.samples,
            "updating": self._updating,
            "update_periods": self.update_periods,
            "takeovers": self.takeovers,
            "direction": self._direction,
            "robot_speed_ratio": self._robot.ratio,
            "robot_probes": self._probes.count,
        }


def elastic_params_for_ans(params: AnsParams) -> ElasticParams:
    """The ElasticAction parameters that make it μLinUCB: no detection, restriction or hedging."""
    return ElasticParams(
        **params.model_dump(),
        change_detection=False,
        direction_restriction=False,
        hedge=False,
        confirm_misses=False,
        takeover_margin=0.0,
        robot_probe_frames=0,
    )
