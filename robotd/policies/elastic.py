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
- change detection (`robotd.policies.change_detector`): misses in a row on actions the model knows
  start a parameter-update period, which drops old evidence and restricts the actions to one
  direction (less data and P when the cloud got slower, at least as much data when it got
  faster) until predictions fit again; after a single miss the next frame is a forced frame, so
  a change is confirmed within `change_frames` frames.
- hedging: an exploring frame — one whose action differs from what the estimates alone would
  choose, because it is a forced frame or because its confidence bonus won — and every offloaded
  frame of an update period, is also computed on the robot and served by the faster path;
  exploration then costs CPU and bandwidth, not latency. The local run starts
  `Decision.hedge_after_s` after the request: one expected to beat the reply at the latest
  moment that still finishes it when the greedy choice would have served the frame; one expected
  to lose to it once the reply is overdue. A local run that cannot beat the expected reply then
  does not compete with the offload for the robot's CPU. A segment is never hedged: it is
  explored on the cloud alone (and a robot probe due on it waits for a whole suffix).
- robot probes (`robotd.policies.robot_probes`): when the robot has not been timed for
  `robot_probe_frames` frames (its actions run less than `SHORT_RUN_SHARE` of the model there,
  e.g. cut 0 with a JPEG encode), the next offloaded frame is hedged at once, so a robot that got
  faster again is noticed. Without hedging the probe serves the frame on the robot (P) instead,
  and each probe that finds the estimate right doubles the interval to the next (up to
  `ROBOT_PROBE_MAX_FACTOR` times), as these probes cost latency; one that finds it wrong is
  confirmed by a probe on the next frame.
- exploration's robot time: on a robot that reports its CPU (`Outcome.cpu_s`), a lost hedged
  probe is priced at `robot_rate` times the time its local run kept the robot busy and the
  probes are spaced to cost at most `PROBE_COST_SHARE` of the frames (the latency a probe adds
  to its frame included) and by how far P is from winning (`robot_probes`), a stopped
  local run bounds the robot's time from below, and an insurance local run is started only
  where overdue replies come late enough for it to pay (`robotd.policies.insurance`).
- take-up and hint (`robotd.policies.take_up`): an offloading action seen to cost less than
  (1 − `takeover_margin`) of the current choice is sampled again on the next frame, and
  `takeover_samples` such observations in a row start an update period on its evidence; while P
  serves, an unknown action answering faster than predicted makes the next frame sample the
  action that was cheapest at its best.

A frame the cloud did not answer teaches y = the time the robot waited (its deadline): a dead or
congested route then looks expensive instead of unknown, and the miss feeds change detection.

Video actions (`h264`, `robotd.frame_path.video_streams`): a keyframe sends several times a
P-frame's bytes, and the robot's stream needs one after every frame served otherwise. Each video
action has two learned byte counts, its P-frames' (its context, as any action's bytes) and its
keyframes' (`robotd.policies.keyframes`), and the policy two sets of scores
(`robotd.policies.scores`), refreshed together: on a frame whose video frame would be a keyframe
(`FrameContext.keyframe`: the first after a switch, after frames served on the robot or lost)
the video actions are scored with their keyframe's bytes, so a return to the cloud is priced at
what it sends and exploration does not thrash between cloud and robot. A keyframe's cloud-side
cost is learned as its excess over the P-frame's prediction (`keyframes`); the regression,
change detection and take-up follow the P-frames, the stream's ordinary frames.
"""

from __future__ import annotations

import math
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
from robotd.policies.change_detector import MIN_PREDICTION, ChangeDetector, miss_tolerance
from robotd.policies.insurance import Insurance
from robotd.policies.keyframes import KeyframeCosts
from robotd.policies.objective import Objective, cloud_cost
from robotd.policies.params import AnsParams, ElasticParams
from robotd.policies.ridge import RidgeEstimator, quadratic_features
from robotd.policies.robot_probes import RobotProbes
from robotd.policies.robotcost import SHORT_RUN_SHARE, RobotCostModel
from robotd.policies.schedule import ForcedSchedule
from robotd.policies.scores import Scores
from robotd.policies.segment_actions import action_contexts, context_unit_bytes
from robotd.policies.take_up import TakeUp

# A failed attempt with no reported wait is charged this multiple of its prediction.
UNKNOWN_WAIT_FACTOR = 2.0
# Learned bytes of an action change its context only when they moved by more than this share.
BYTES_CHANGE_SHARE = 0.02
# Action costs within this share of the whole model's time count as equal when dominated
# actions are left out (`CutTable.undominated`).
DOMINANCE_SLACK = 0.05


class ElasticPolicy(Policy):
    """ElasticAction; with change detection, restriction and hedging off it is μLinUCB (`ans`)."""

    name = "elastic"
    # The regression's implementation (the decision-cost benchmark compares another one).
    ridge_type: type[RidgeEstimator] = RidgeEstimator

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
        # [bytes sent (in MB, or in keyframes with video actions: `context_unit_bytes`), cloud
        # share, 1], and MB returned when segments are among the actions.
        self.contexts = action_contexts(cuts)
        self._unit = context_unit_bytes(cuts)  # bytes per unit of the contexts' first column
        # Bytes sent per action, learned online: a JPEG's size follows the content.
        self._bytes: list[float] = cuts.bytes.tolist()
        self._ridge = self.ridge_type(self.contexts, params.gamma)
        # Video actions' keyframes, learned apart (the P-frames' bytes are `_bytes`).
        self._keyframes = KeyframeCosts(
            cuts, params, objective, self._ridge, self.contexts, self._bytes, self._unit
        )
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
        # Streaks, update periods and the direction restriction; take-up candidates and hints.
        self._detector = ChangeDetector(params, self._ridge, self._bytes)
        self._take_up = TakeUp(params, self._detector, self._schedule)
        # When to time the robot on a frame whose action runs nothing measurable there.
        self._probes = RobotProbes(params, self._robot, self._untimed, objective.robot_rate)
        self._cpu_counted = False  # the robot reports its CPU (Outcome.cpu_s)
        self._insurance = Insurance(objective.wait_rate, objective.robot_rate)
        # The scores of ordinary frames, and of those whose video frame would be a keyframe
        # (kept only with video actions); `_bonus_scale` = β·E_P.
        self._scores = Scores()
        self._kf_scores = Scores()
        self._score_sets: tuple[Scores, ...] = (
            (self._scores, self._kf_scores) if self._keyframes.video else (self._scores,)
        )
        self._bonus_scale = 0.0
        self._refresh(learned=True)

    # -- decisions -------------------------------------------------------------------------

    def decide(self, ctx: FrameContext) -> Decision:
        n = self._frame
        self._frame = n + 1
        robot = self._robot
        robot.tick()
        self._probes.tick()
        params = self.params
        detector = self._detector
        take_up = self._take_up
        updating = detector.updating
        p_allowed = detector.p_allowed
        # A frame where the video actions would send a keyframe: scored with its bytes, unless
        # a video action is the cheapest of all on ordinary frames. Its keyframe then starts a
        # stream that the next frames repay: priced frame by frame, a move from JPEG to h264
        # would never pay for its first frame.
        scores = self._scores
        if ctx.keyframe and self._keyframes.video:
            ordinary_cost, ordinary_best = scores.cheapest
            if ordinary_best not in self._keyframes.video or ordinary_cost >= robot.full_cost:
                scores = self._kf_scores
        best, j = scores.best_key if ctx.entropy >= params.key_entropy else scores.best_nonkey
        base, pred, cheapest_pair = scores.base, scores.pred, scores.cheapest
        p_cost = robot.full_cost
        regular_p = p_allowed and p_cost <= best
        forced = detector.confirm or self._schedule.is_forced(n)
        detector.confirm = False
        challenger = take_up.challenger
        if challenger is not None:
            # Confirm a take-up candidate on this frame (it is allowed: a restriction starts
            # only with an update period, which clears the candidate).
            take_up.challenger = None
            j, forced = challenger, True
        if regular_p and not forced:
            return Decision(PURE_ROBOT, updating=updating, predicted_cost=p_cost)
        # P's distance spaces the probes of a robot that reports its CPU (they cost it there).
        cheapest_cost = cheapest_pair[0]
        distance = p_cost / cheapest_cost if self._cpu_counted and cheapest_cost > 0 else 1.0
        probe = self._probes.due(j, distance)
        if probe and p_allowed and not forced and (not params.hedge or self._probes.wants_p):
            # Without hedging, or when stopped local runs only bounded the robot's time, the
            # robot is timed by serving the frame on it.
            self._probes.tried(on_p=True)
            return Decision(PURE_ROBOT, updating=updating, predicted_cost=p_cost)
        if not params.hedge:
            return self.cuts.decision_at(
                j, forced=forced, updating=updating, predicted_cost=base[j]
            )
        # Exploring = serving something else than the estimates alone would choose.
        cheapest, greedy = cheapest_pair
        if p_allowed and p_cost <= cheapest:
            greedy = -1
        hedge = greedy != j or updating or probe
        if self._segment[j]:
            # Explored unhedged: a local race would run the whole suffix from the start cut,
            # while the reply still needs the tail (`Decision`); a probe waits for a cut.
            hedge = False
        after_s = 0.0
        if hedge:
            self._probes.tried()  # a hedged frame times the robot when its local run wins
            if not probe:
                after_s = self._hedge_after_s(j, greedy, pred)
                if after_s == math.inf:  # insurance not worth its robot time: no local run
                    hedge, after_s = False, 0.0
        decision = self.cuts.decision_at(
            j,
            hedge=hedge,
            forced=forced,
            updating=updating,
            predicted_cost=base[j],
            hedge_after_s=after_s,
            local_expected=hedge and greedy < 0,
        )
        if probe:
            self._probes.hedged(decision)
        return decision

    def _hedge_after_s(self, j: int, greedy: int, pred: list[float]) -> float:
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
            target_s = self._prefix_s[greedy] * scale + max(pred[greedy], 0.0) / rate
        slack_s = target_s - self._prefix_s[j] * scale - self._suffix_s[j] * scale
        local_s = self._suffix_s[j] * scale
        reply_s = max(pred[j], 0.0) / rate
        if reply_s >= local_s:
            return max(slack_s, 0.0)
        overdue_s = (1.0 + self.params.change_tolerance) * reply_s
        if self._cpu_counted:
            # Its robot time is a cost there (robot_probes): not started where overdue replies
            # come too soon after for it to pay (`insurance`; inf: no local run), else once the
            # wait has cost what the run would (rent or buy: at most twice the better of two).
            if not self._insurance.worth(local_s):
                return math.inf
            overdue_s = max(overdue_s, local_s)
        return max(slack_s, overdue_s)

    # -- learning --------------------------------------------------------------------------

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        robot = self._robot
        if decision.action == PURE_ROBOT:
            self._probes.timed(robot.observe(outcome.prefix_s, self.cuts.full_s), on_p=True)
            self._refresh(learned=False)
            return
        j = self._position[(int(decision.action), decision.codec, decision.end)]
        keyframe = bool(outcome.keyframe) and j in self._keyframes.video
        if keyframe:
            self._keyframes.learn_bytes(j, outcome.bytes_up)
        else:
            self._learn_bytes(j, outcome.bytes_up)
        pred = self._kf_scores.pred if keyframe else self._scores.pred
        robot_s = self._prefix_s[j] if outcome.cloud_s is not None else self._head_s[j]
        self._probes.timed(robot.observe(outcome.prefix_s, robot_s))
        if outcome.local_s is not None:
            self._probes.timed(robot.observe(outcome.local_s, self._suffix_s[j]))
        if outcome.cpu_s is not None:
            self._count_cpu(j, outcome)
        if outcome.cloud_s is not None:
            target = cloud_cost(
                self._wait_rate, self._radio_rate, outcome.cloud_s, outcome.cloud_compute_s
            )
        elif outcome.waited_s is not None:
            target = cloud_cost(self._wait_rate, self._radio_rate, outcome.waited_s, None)
        else:
            target = UNKNOWN_WAIT_FACTOR * max(pred[j], MIN_PREDICTION)
        if decision.hedge:
            busy_s = (outcome.cloud_s or 0.0) - decision.hedge_after_s
            if outcome.local_s is None and outcome.cpu_s is not None:
                # The local run was stopped unfinished: the robot needs longer than that.
                self._probes.bounded(robot.observe_slower_than(busy_s, self._suffix_s[j]))
            self._probes.raced(
                decision,
                timed=outcome.local_s is not None,
                busy_s=busy_s,
                cpu_known=outcome.cpu_s is not None,
                frame_cost=self._current()[0],
                excess=target - pred[j],
            )
        scores = self._scores
        if keyframe:
            # A keyframe teaches its excess over the P-frame; the regression, change detection
            # and take-up follow the P-frames (the stream's ordinary frames).
            self._keyframes.learn_cost(j, target, scores.pred[j])
        elif self._take_up.observe(j, target, scores.base[j] - scores.pred[j], self._current):
            pass  # the observation started an update period on this action's evidence
        elif self.params.change_detection:
            self._track(j, target)
        else:
            self._ridge.update(j, target)
        self._refresh(learned=True)

    def _count_cpu(self, j: int, outcome: Outcome) -> None:
        """The robot reports its CPU: hedges' robot time counts (`robot_probes`, `insurance`);
        learn how late an overdue reply of column j came."""
        self._cpu_counted = True
        waited_s = outcome.cloud_s if outcome.cloud_s is not None else outcome.waited_s
        rate = self._wait_rate + self._radio_rate
        if waited_s is not None and rate > 0:
            overdue_s = (1.0 + self.params.change_tolerance) * max(self._scores.pred[j], 0.0) / rate
            self._insurance.observe(waited_s, overdue_s)

    def _learn_bytes(self, j: int, sent: int) -> None:
        """Follow the bytes action j really sends (EWMA): its context and byte cost move with
        them, once they moved by more than `BYTES_CHANGE_SHARE` (no work on every frame)."""
        if sent <= 0:
            return
        new = self._bytes[j] = self._bytes[j] + self.params.bytes_ewma * (sent - self._bytes[j])
        units = new / self._unit
        if abs(units - self.contexts[j, 0]) <= BYTES_CHANGE_SHARE * self.contexts[j, 0]:
            return
        self.contexts[j, 0] = units
        self._ridge.set_context(j, self.contexts[j])
        k = self._k
        d = self.contexts.shape[1]
        self._features[j, 0] = units
        self._features[j, -1] = self.objective.bytes * new / BYTES_PER_MB
        self._features[k + j, d : d + d * d] = quadratic_features(self.contexts[j : j + 1])[0]
        self._features[2 * k + j, 0] = units

    def _track(self, j: int, target: float) -> None:
        """Feed one cloud-side observation of column j to the change detector (which updates
        the regression); a surprise on an action the model does not know may hint at a cheaper
        one (`TakeUp.hint`; a known action's misses are confirmed by the detector)."""
        scores = self._scores
        pred = scores.pred[j]
        known = scores.width[j] <= self._known_width
        if not known and pred - target > miss_tolerance(self.params, pred)[1]:
            self._take_up.hint(j, target, self._frame, self._current(), scores.allowed, scores.pred)
        if self._detector.observe(j, target, pred, known):
            self._take_up.forget()  # candidates were judged against the old conditions

    def _current(self) -> tuple[float, int]:
        """(estimated cost, column) of what the estimates alone choose now; column -1: P."""
        current, greedy = self._scores.cheapest
        p_cost = self._robot.full_cost
        if self._detector.p_allowed and p_cost <= current:
            return p_cost, -1
        return current, greedy

    def _refresh(self, learned: bool) -> None:
        """Recompute the score parts after an observation (`learned`: the regression changed)."""
        robot = self._robot
        scores = self._scores
        coef = self._ridge.coefficients()
        coef += (robot.unit_cost, 1.0)
        self._coef[:] = coef
        if not learned:
            scores.base = self._base_features.dot(self._coef).tolist()
        else:
            values = self._features.dot(self._coef).tolist()
            k = self._k
            scores.base = values[:k]
            quad = values[k : 2 * k]
            try:
                scores.width = list(map(math.sqrt, quad))
            except ValueError:  # round-off can leave a tiny negative form once Q is large
                scores.width = [math.sqrt(x) if x > 0.0 else 0.0 for x in quad]
            scores.pred = values[2 * k :]
        if self._keyframes.video:
            self._keyframes.rescore(scores, self._kf_scores, learned)
        self._bonus_scale = self.params.beta * robot.full_cost
        self._choose()

    def _choose(self) -> None:
        """Each score set's best score for key and for other frames, and its cheapest action,
        under the current direction restriction (`Scores.choose`)."""
        mask = self._detector.mask
        key_bonus = self._key_factor * self._bonus_scale
        nonkey_bonus = self._nonkey_factor * self._bonus_scale
        for scores in self._score_sets:
            scores.choose(mask, key_bonus, nonkey_bonus)

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
        return self._detector.updating

    @property
    def update_periods(self) -> int:
        """Parameter-update periods started so far (the run's first, unrestricted one aside)."""
        return self._detector.update_periods

    @property
    def takeovers(self) -> int:
        """Update periods started by the take-up rule."""
        return self._take_up.takeovers

    def allowed_actions(self) -> list[str]:
        """Labels of the actions the direction restriction currently allows (all of them
        outside a period)."""
        labels = self.cuts.labels
        mask = self._detector.mask
        cuts = [labels[i] for i in range(self._k) if mask is None or mask[i]]
        return [*cuts, PURE_ROBOT] if self._detector.p_allowed else cuts

    def predicted_cloud_cost(self, *, keyframe: bool = False) -> dict[str, float]:
        """α̂ᵀv_a for every offloading action, by label (objective units); `keyframe`: on a
        frame whose video frame would be a keyframe (video actions at their keyframe's bytes)."""
        pred = self._kf_scores.pred if keyframe and self._keyframes.video else self._scores.pred
        return dict(zip(self.cuts.labels, pred, strict=False))

    def learned_bytes(self) -> dict[str, float]:
        """The bytes each offloading action is expected to send, by label (a video action's
        P-frames)."""
        return dict(zip(self.cuts.labels, self._bytes, strict=False))

    def learned_key_bytes(self) -> dict[str, float]:
        """The bytes each video action's keyframe is expected to send, by label."""
        labels = self.cuts.labels
        return {labels[j]: self._keyframes.key_bytes[j] for j in self._keyframes.video}

    def state(self) -> dict[str, Any]:
        return {
            "policy": self.name,
            "frame": self._frame,
            "alpha": list(self._ridge.alpha),
            "samples": self._ridge.samples,
            "updating": self._detector.updating,
            "update_periods": self.update_periods,
            "takeovers": self.takeovers,
            "direction": self._detector.direction,
            "robot_speed_ratio": self._robot.ratio,
            "robot_probes": self._probes.count,
            "robot_probes_lost": self._probes.lost,
            "robot_probe_interval": self._probes.interval,
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
