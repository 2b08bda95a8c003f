"""The latency-bounded scheduler: decides which deployment should serve each robot.

Pure decision logic, no I/O: the registry daemon hands it a snapshot (the robot's route and
telemetry window, the live deployments with their load, the robot's probe profiles) and gets back
a `RouteDecision` or None. It keeps a little memory per robot (when a violation started, when the
robot last moved, which deployments it left for being slow: `registry.robot_memory`) so that it
can apply hysteresis; time comes from an injectable clock so tests run instantly.

Triggers, in order:
1. the robot has no route and a deployment is available (`initial`);
2. the serving deployment's liveliness token is gone (`deployment_lost`) or it drains (`drain`);
3. the robot reports `timeout_count` consecutive timeouts against its deployment (`timeouts`);
4. the latency bound is violated by the robot's telemetry window for `hysteresis_s` without a break
   (`bound_violation`);
5. more than `busy_share` of the robot's last frames offloaded to its deployment (at least
   `busy_min_frames` of them) were refused `busy`, for `hysteresis_s` without a break (`busy`);
6. another deployment is predicted better by `better_margin` for `improve_hold_s` (`better`).
1–3 act at once; 4–6 wait out `min_dwell_s` after the robot's last move.

A move for `busy` goes only to a deployment with room to spare: not full, at most
`1 - busy_headroom` of its capacity taken, and no other robot moved there for `busy` within
`busy_arrival_gap_s` (loads are sampled every few seconds: without the gap a whole round's busy
robots would pile onto the same deployment before its load shows them). The deployment left for
`busy` is not a target of a move by choice (`busy`, `bound_violation`, `better`) for
`flap_window_s`, so robots that found room do not drift back and forth. A move for `better`
needs the same room to spare (a gain in latency is not worth crowding a deployment, which the
`busy` trigger or placement by load would then undo), and so does one for `timeouts` once the
deployment has answered the robot on its route (late then, not out of reach).

Choice: among live, non-draining deployments of the robot's service, those whose recent probe
profile (load-adjusted) meets the bound rank first, lowest predicted latency first; then the others
(the best available); full deployments and those left for a violation rank last, the latter until
their probes have met the bound for `recovery_s`. Forced moves take the first of that ranking, and
rank by every recent probe profile, also one thinner than `min_probe_samples`: when the robot has
to leave now, a deployment measured twice at 34 ms is a better bet than one measured three times
at 67 ms, and either is better than one never measured (the probes of a robot that started a few
seconds ago are thin for every deployment). A move for a violation or an improvement is a choice,
not a necessity: it counts only profiles of at least `min_probe_samples`, and also needs a target
predicted better than the current by `better_margin`, and otherwise stays. For a violation
"current" is the robot's telemetry (probe windows lag behind a sudden delay); a second violation
within `flap_window_s` of the last move for one also needs the target to beat the current
deployment's own probe profile. For an improvement it is the current deployment's probe profile
(like for like), else the telemetry. With no live deployment the robot gets no route and computes
locally.

Admission: a robot to be placed (no route, or its deployment lost) when every usable deployment is
`full` is not piled onto one: it gets no route (`no_capacity`, so it is told why; it finishes every
frame itself, as without a route) once, and is placed by a later round's `initial` as soon as a
deployment has room. A deployment of unknown capacity is never full.

Placement by load (`initial`), from a robot's first registration: a deployment's committed load
is its reported load or the robots routed to it (`RobotView.routed`), whichever is more: a robot
takes a request slot as soon as it is routed, while a reported load is seconds old, so a round
that places several robots would pile them all onto the deployment that reported room. Targets
whose committed load is below `1 - busy_headroom` of their capacity (the busy trigger's room to
spare) come first: those predicted to meet the bound first, then the one with the most headroom
(the least committed share of its capacity), then by rank. So robots spread across deployments
from the start, not onto the first until it is crowded. Every target with less headroom than
the choice (or no room to spare) is `crowded` in the decision, so the initial policy's preference
(applied after the scheduler, `registry.round_inputs.prefer_initial`) only breaks ties: it never
sends a robot where another deployment has more room. With room nowhere the targets are ordered
by committed share, those meeting the bound first. The placement is a robot's first route, so it
does not start the dwell time; later moves keep their hysteresis (a `better` move needs room to
spare as well, so it does not undo the spread by crowding one deployment).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from enum import Enum

from common.wire.registry import NO_CAPACITY_REASON
from registry.latency import LatencyBound, Profiles, WindowStats
from registry.robot_memory import RobotMemory, RobotMemoryEntry, recent_profile

DEFAULT_MIN_DWELL_S = 3.0
DEFAULT_TIMEOUT_COUNT = 3
DEFAULT_IMPROVE_HOLD_S = 5.0
DEFAULT_RECOVERY_S = 5.0
DEFAULT_PROFILE_MAX_AGE_S = 10.0
DEFAULT_MIN_SAMPLES = 5
DEFAULT_MIN_PROBE_SAMPLES = 3
DEFAULT_LOAD_WEIGHT = 1.0
DEFAULT_RETRY_BACKOFF_S = 1.0
DEFAULT_FLAP_WINDOW_S = 60.0
DEFAULT_BUSY_SHARE = 0.05
DEFAULT_BUSY_MIN_FRAMES = 10
DEFAULT_BUSY_HEADROOM = 0.25
DEFAULT_BUSY_ARRIVAL_GAP_S = 2.0


class Reason(str, Enum):
    """Why the scheduler moves a robot."""

    INITIAL = "initial"
    DEPLOYMENT_LOST = "deployment_lost"
    DRAIN = "drain"
    TIMEOUTS = "timeouts"
    BOUND_VIOLATION = "bound_violation"
    BETTER = "better"
    BUSY = "busy"
    # Not a move but a refusal to place: every deployment is full (the wire's reason string).
    NO_CAPACITY = NO_CAPACITY_REASON


# Triggers that cannot wait: the robot is (or will soon be) without a working deployment.
FORCED_REASONS = frozenset({Reason.INITIAL, Reason.DEPLOYMENT_LOST, Reason.DRAIN, Reason.TIMEOUTS})
# Leaving for these reasons marks the old deployment as bad until its probes recover.
PENALIZING_REASONS = frozenset({Reason.BOUND_VIOLATION, Reason.TIMEOUTS})


@dataclass(frozen=True)
class SchedulerParams:
    """Tuning of the scheduler beyond the latency bound itself (defaults in docs/registry.md)."""

    min_dwell_s: float = DEFAULT_MIN_DWELL_S
    timeout_count: int = DEFAULT_TIMEOUT_COUNT
    improve_hold_s: float = DEFAULT_IMPROVE_HOLD_S
    recovery_s: float = DEFAULT_RECOVERY_S
    profile_max_age_s: float = DEFAULT_PROFILE_MAX_AGE_S
    min_samples: int = DEFAULT_MIN_SAMPLES
    min_probe_samples: int = DEFAULT_MIN_PROBE_SAMPLES
    load_weight: float = DEFAULT_LOAD_WEIGHT
    retry_backoff_s: float = DEFAULT_RETRY_BACKOFF_S
    flap_window_s: float = DEFAULT_FLAP_WINDOW_S
    busy_share: float = DEFAULT_BUSY_SHARE
    busy_min_frames: int = DEFAULT_BUSY_MIN_FRAMES
    busy_headroom: float = DEFAULT_BUSY_HEADROOM
    busy_arrival_gap_s: float = DEFAULT_BUSY_ARRIVAL_GAP_S

    def __post_init__(self) -> None:
        for name in (
            "min_dwell_s",
            "improve_hold_s",
            "recovery_s",
            "load_weight",
            "retry_backoff_s",
            "flap_window_s",
            "busy_arrival_gap_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"scheduler {name} must be a number >= 0, got {value!r}")
        if not (math.isfinite(self.profile_max_age_s) and self.profile_max_age_s > 0):
            raise ValueError(
                f"scheduler profile_max_age_s must be > 0, got {self.profile_max_age_s!r}"
            )
        for name in ("busy_share", "busy_headroom"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value < 1):
                raise ValueError(f"scheduler {name} must be a share in [0, 1), got {value!r}")
        for name in ("timeout_count", "min_samples", "min_probe_samples", "busy_min_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"scheduler {name} must be at least 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class DeploymentView:
    """What the scheduler needs to know about one deployment."""

    id: str
    service: str
    alive: bool = True
    draining: bool = False
    load: int = 0
    capacity: int = 0  # 0: unknown, no load adjustment
    model_digest: str | None = None

    @property
    def utilization(self) -> float:
        """Load over capacity (0 when the capacity is unknown)."""
        return self.load / self.capacity if self.capacity > 0 else 0.0

    @property
    def full(self) -> bool:
        """True when every worker and queue slot is taken (it would answer `busy`)."""
        return self.capacity > 0 and self.load >= self.capacity

    def has_room(self, headroom: float) -> bool:
        """Not full, and at most `1 - headroom` of the capacity taken (unknown capacity: no
        load reported, so nothing says it is short of room)."""
        return not self.full and self.load <= self.capacity * (1 - headroom)


class DeploymentTable:
    """The deployments as one scheduling round sees them, indexed once.

    A round hands the same table to every robot's evaluation: indexing a list of deployments for
    each robot made a round grow with robots x deployments (docs/scale.md). `evaluate` also takes
    a plain sequence and indexes it itself.
    """

    __slots__ = ("by_id", "views")

    def __init__(self, views: Iterable[DeploymentView]) -> None:
        self.views: tuple[DeploymentView, ...] = tuple(views)
        self.by_id: dict[str, DeploymentView] = {d.id: d for d in self.views}


@dataclass(frozen=True)
class RobotView:
    """What the scheduler needs to know about one robot.

    `telemetry` is the window of frames answered by the serving deployment; `timeouts` counts the
    robot's consecutive timeouts against `timeouts_on` (None: its current route); of its last
    `offloaded` frames to its route, `busy` were refused for want of room. `routed` counts the
    robots routed to each deployment now (this one excluded), for a robot to be placed; it may be
    empty otherwise.
    """

    id: str
    service: str
    route: str | None
    telemetry: WindowStats | None = None
    timeouts: int = 0
    timeouts_on: str | None = None
    model_digest: str | None = None
    busy: int = 0
    offloaded: int = 0
    routed: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class RouteDecision:
    """Move `robot` from `from_deployment` to `to_deployment` (None: compute locally).

    `candidates` lists acceptable targets best first (`to_deployment` first) so the switch protocol
    can fall back to the next one when a deployment does not acknowledge. `crowded` (an initial
    placement only) names the candidates with less room than the choice (or none to spare for one
    more robot): the initial policy's preference may pick among the others only.
    """

    robot: str
    from_deployment: str | None
    to_deployment: str | None
    reason: Reason
    candidates: tuple[str, ...] = ()
    predicted_s: float | None = None
    crowded: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class _Candidate:
    deployment: DeploymentView
    predicted_s: float | None
    meets: bool
    penalized: bool
    # Predicted from a recent profile thinner than min_probe_samples: good enough to rank the
    # targets of a forced move, not to move a robot that is being served.
    thin: bool = False

    @property
    def tier(self) -> int:
        if self.penalized or self.deployment.full:
            return 2
        return 0 if self.meets else 1

    @property
    def confident_s(self) -> float | None:
        """The prediction when it rests on at least min_probe_samples probes, else None."""
        return None if self.thin else self.predicted_s

    def sort_key(self) -> tuple[int, bool, float, bool, float, str]:
        # Known latency before unknown; then lower predicted latency (a thick profile before a
        # thin one at the same value), lower load, stable by id.
        pred = self.predicted_s if self.predicted_s is not None else math.inf
        return (
            self.tier,
            self.predicted_s is None,
            pred,
            self.thin,
            self.deployment.utilization,
            self.deployment.id,
        )


class Scheduler:
    """Latency-bounded deployment choice with hysteresis; see the module docstring."""

    def __init__(
        self,
        bound: LatencyBound,
        params: SchedulerParams | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.bound = bound
        self.params = params if params is not None else SchedulerParams()
        self._clock = clock
        # Per robot: moves, waiting triggers, deployments left (`registry.robot_memory`).
        self.memory = RobotMemory(
            bound,
            flap_window_s=self.params.flap_window_s,
            recovery_s=self.params.recovery_s,
            min_probe_samples=self.params.min_probe_samples,
            profile_max_age_s=self.params.profile_max_age_s,
        )

    # -- memory --------------------------------------------------------------------------------
    def record_switch(
        self, robot: str, from_deployment: str | None, to_deployment: str | None, reason: Reason
    ) -> None:
        """Tell the scheduler a switch was carried out (the switch protocol may pick a fallback)."""
        why = Reason(reason)
        self.memory.moved(
            robot,
            from_deployment,
            to_deployment,
            self._clock(),
            busy=why is Reason.BUSY,
            violation=why is Reason.BOUND_VIOLATION,
            penalizing=why in PENALIZING_REASONS,
            no_capacity=why is Reason.NO_CAPACITY,
        )

    def record_failure(self, robot: str) -> None:
        """Tell the scheduler no candidate took the robot: back off before deciding again."""
        self.memory.failed(robot, self._clock())

    def forget(self, robot: str) -> None:
        """Drop the memory of a robot that left the fleet."""
        self.memory.forget(robot)

    def penalized(self, robot: str) -> frozenset[str]:
        """Deployments the robot left for being slow and that have not recovered yet."""
        return self.memory.penalized(robot)

    # -- decision --------------------------------------------------------------------------------
    def evaluate(
        self,
        robot: RobotView,
        deployments: Sequence[DeploymentView] | DeploymentTable,
        profiles: Mapping[str, WindowStats],
    ) -> RouteDecision | None:
        """Decide whether `robot` should move; `profiles` are its probe windows per deployment.

        Only a forced move ranks every deployment. A robot that stays (nearly every robot, nearly
        every round) costs the few deployments whose probe statistic could beat its limit, found
        by ascending statistic (`Profiles.ascending`: kept with the snapshot, so it is sorted
        once per change of the robot's probes, not once per round).
        """
        now = self._clock()
        st = self.memory.state(robot.id)
        table = (
            deployments
            if isinstance(deployments, DeploymentTable)
            else DeploymentTable(deployments)
        )
        snapshot = profiles if isinstance(profiles, Profiles) else Profiles(profiles)
        self.memory.update_recovery(st, table.by_id, snapshot, now)

        current = table.by_id.get(robot.route) if robot.route is not None else None
        if robot.route is not None:
            st.no_capacity = False  # placed since it was told (a placement is not recorded)
        forced: Reason | None = None
        if robot.route is None:
            forced = Reason.INITIAL
        elif current is None or not current.alive:
            forced = Reason.DEPLOYMENT_LOST
        elif current.draining:
            forced = Reason.DRAIN
        elif robot.timeouts >= self.params.timeout_count and robot.timeouts_on in (
            None,
            robot.route,
        ):
            forced = Reason.TIMEOUTS

        if (
            st.failed_at is not None
            and now - st.failed_at < self.params.retry_backoff_s
            and forced is not Reason.DEPLOYMENT_LOST
        ):
            # The last attempt found no taker; retrying at once would hammer the same deployments.
            return None
        if forced is not None:
            st.violation_since = None
            st.busy_since = None
            st.better_since = None
            return self._forced(robot, forced, self._rank(robot, table, snapshot, st, now), st)

        assert current is not None  # forced covers every route without a live deployment
        targets = _Targets(self, robot, current, table, snapshot, st, now)
        if self._violating(robot):
            st.better_since = None
            if st.violation_since is None:
                st.violation_since = now
            if now - st.violation_since >= self.bound.hysteresis_s and self._dwelt(st, now):
                own = self._candidate(robot, current, snapshot, st, now).confident_s
                recent = (
                    st.violation_move_at is not None
                    and now - st.violation_move_at < self.params.flap_window_s
                )
                return self._on_violation(robot, current, targets, own, recent)
            return None
        st.violation_since = None
        if self._refused_busy(robot):
            st.better_since = None
            if st.busy_since is None:
                st.busy_since = now
            if now - st.busy_since >= self.bound.hysteresis_s and self._dwelt(st, now):
                return self._on_busy(robot, current, table, snapshot, st, now)
            return None
        st.busy_since = None
        reference = self._reference(robot, current, snapshot, st, now)
        return self._on_improvement(robot, current, targets, reference, st, now)

    def _forced(
        self, robot: RobotView, reason: Reason, ranked: list[_Candidate], st: RobotMemoryEntry
    ) -> RouteDecision | None:
        targets = [c for c in ranked if c.deployment.id != robot.route]
        if reason is Reason.TIMEOUTS and robot.offloaded:
            # Its deployment is alive and has answered it on this route, so it is late, not out
            # of reach: a target without room would be late too, and robots went back and forth
            # between two overloaded ones (docs/scale.md).
            targets = [c for c in targets if c.deployment.has_room(self.params.busy_headroom)]
        if (
            reason in (Reason.INITIAL, Reason.DEPLOYMENT_LOST)
            and targets
            and all(c.deployment.full for c in targets)
        ):
            # Admission: a full deployment would answer `busy` to this robot's frames and slow
            # the robots it serves; the robot computes locally until a deployment has room.
            if robot.route is None and st.no_capacity:
                return None  # already told; a later round places it when one has room
            return RouteDecision(robot.id, robot.route, None, Reason.NO_CAPACITY)
        if targets and reason is Reason.INITIAL:
            return self._place(robot, targets)
        if targets:
            return _move(robot.id, robot.route, targets, reason)
        if reason is Reason.DEPLOYMENT_LOST:
            # Nothing else alive: drop the route so the robot computes locally.
            return RouteDecision(robot.id, robot.route, None, reason)
        # No route and nothing to offer, or the only deployment drains / times out: stay put.
        return None

    def _place(self, robot: RobotView, targets: list[_Candidate]) -> RouteDecision:
        """An initial placement by load (module docstring): the targets with room for one more
        robot first, those meeting the bound first, then the most headroom first; every target
        with less room than the choice is named crowded in the decision."""
        share = 1 - self.params.busy_headroom
        room: list[_Candidate] = []
        crowded: list[_Candidate] = []
        for c in targets:
            roomy = c.tier <= 1 and _room_to_place(
                c.deployment, _committed(robot, c.deployment), share
            )
            (room if roomy else crowded).append(c)

        def by_load(c: _Candidate) -> tuple[int, float, tuple[int, bool, float, bool, float, str]]:
            # Tier (meets the bound), committed share (least first), then rank.
            return (c.tier, _committed_share(robot, c.deployment), c.sort_key())

        # With room nowhere, the least committed first too: otherwise every robot of a round
        # would go to the first in rank (the one that met the bound or had the lowest id).
        room.sort(key=by_load)
        crowded.sort(key=by_load)
        order = room + crowded
        first = by_load(order[0])[:2]
        # Ties with the choice (same tier, same share) are the initial policy's to break.
        tied = {c.deployment.id for c in room if by_load(c)[:2] == first}
        decision = _move(robot.id, robot.route, order, Reason.INITIAL)
        return replace(
            decision, crowded=tuple(c.deployment.id for c in order if c.deployment.id not in tied)
        )

    def _on_violation(
        self,
        robot: RobotView,
        current: DeploymentView,
        targets: _Targets,
        own_probe_s: float | None,
        recent_violation_move: bool,
    ) -> RouteDecision | None:
        # Targets that meet the bound rank first, then the best available. Either way a target has
        # to be predicted better than what the robot sees by `better_margin`: moving between two
        # equally marginal deployments trades one violation for another and back.
        observed = self._observed(robot)
        assert observed is not None  # only called while violating
        limit = observed * (1 - self.bound.better_margin)
        if recent_violation_move:
            # A second violation soon after moving for one hints that the deployment is not the
            # bottleneck (the robot's uplink, or probes that are cheaper than frames). Demand like
            # for like: the target must also beat the current deployment's own probe profile.
            if own_probe_s is None:
                return None
            limit = min(limit, own_probe_s * (1 - self.bound.better_margin))
        if targets.best(limit, max_tier=1) is None:
            return None
        ranked = targets.ranked(limit, max_tier=1)
        if not ranked:
            return None
        return _move(robot.id, current.id, ranked, Reason.BOUND_VIOLATION)

    def _on_busy(
        self,
        robot: RobotView,
        current: DeploymentView,
        table: DeploymentTable,
        profiles: Profiles,
        st: RobotMemoryEntry,
        now: float,
    ) -> RouteDecision | None:
        # Any deployment with room beats frames finished on the robot, but one predicted to meet
        # the bound ranks first: _rank orders by tier, then prediction, then utilization.
        gap = self.params.busy_arrival_gap_s
        ranked = [
            c
            for c in self._rank(robot, table, profiles, st, now)
            if c.deployment.id != current.id
            and c.tier <= 1
            and not self.memory.avoided(st, c.deployment.id, now)
            and c.deployment.has_room(self.params.busy_headroom)
            and now - self.memory.busy_arrivals.get(c.deployment.id, -math.inf) >= gap
        ]
        if not ranked:
            return None
        return _move(robot.id, current.id, ranked, Reason.BUSY)

    def _on_improvement(
        self,
        robot: RobotView,
        current: DeploymentView,
        targets: _Targets,
        reference: float | None,
        st: RobotMemoryEntry,
        now: float,
    ) -> RouteDecision | None:
        if reference is None:
            st.better_since = None
            return None
        limit = reference * (1 - self.bound.better_margin)
        # A gain in latency is not worth crowding a deployment: the targets need the room a
        # placement needs (or placement by load and this rule would move robots back and forth).
        headroom = self.params.busy_headroom
        found = targets.best(limit, max_tier=0, headroom=headroom)
        if found is None:
            st.better_since = None
            st.better_target = None
            return None
        best = found.deployment.id
        if st.better_target != best or st.better_since is None:
            st.better_since = now
            st.better_target = best
        if now - st.better_since < self.params.improve_hold_s or not self._dwelt(st, now):
            return None
        ranked = targets.ranked(limit, max_tier=0, headroom=headroom)
        if not ranked:
            return None
        return _move(robot.id, current.id, ranked, Reason.BETTER)

    # -- helpers ---------------------------------------------------------------------------------
    def _dwelt(self, st: RobotMemoryEntry, now: float) -> bool:
        return st.last_switch_at is None or now - st.last_switch_at >= self.params.min_dwell_s

    def _reference(
        self,
        robot: RobotView,
        current: DeploymentView,
        profiles: Mapping[str, WindowStats],
        st: RobotMemoryEntry,
        now: float,
    ) -> float | None:
        """The current deployment's latency on the same scale as the candidates' predictions.

        Its own probe profile when fresh (like for like: probes are smaller than frames, so
        telemetry against probes would always favour moving), else the robot's telemetry.
        """
        own = self._candidate(robot, current, profiles, st, now).confident_s
        return own if own is not None else self._observed(robot)

    def _observed(self, robot: RobotView) -> float | None:
        tele = robot.telemetry
        if tele is None or tele.count < self.params.min_samples:
            return None
        return tele.value(self.bound.stat)

    def _refused_busy(self, robot: RobotView) -> bool:
        """More than busy_share of enough recent frames to the route were refused `busy`."""
        return (
            robot.offloaded >= self.params.busy_min_frames
            and robot.busy > self.params.busy_share * robot.offloaded
        )

    def _violating(self, robot: RobotView) -> bool:
        observed = self._observed(robot)
        return observed is not None and observed > self.bound.seconds

    def _candidate(
        self,
        robot: RobotView,
        dep: DeploymentView,
        profiles: Mapping[str, WindowStats],
        st: RobotMemoryEntry,
        now: float,
    ) -> _Candidate:
        stats = recent_profile(profiles.get(dep.id), now, self.params.profile_max_age_s)
        predicted = None
        if stats is not None:
            # Load-aware: a busier deployment queues more; scale by its utilization.
            predicted = stats.value(self.bound.stat) * (
                1 + self.params.load_weight * dep.utilization
            )
        return _Candidate(
            deployment=dep,
            predicted_s=predicted,
            meets=predicted is not None and predicted <= self.bound.seconds,
            penalized=self.memory.avoided(st, dep.id, now),
            thin=stats is not None and stats.count < self.params.min_probe_samples,
        )

    def _rank(
        self,
        robot: RobotView,
        table: DeploymentTable,
        profiles: Mapping[str, WindowStats],
        st: RobotMemoryEntry,
        now: float,
    ) -> list[_Candidate]:
        ranked = [
            self._candidate(robot, d, profiles, st, now) for d in table.views if _usable(robot, d)
        ]
        return sorted(ranked, key=_Candidate.sort_key)


def _usable(robot: RobotView, dep: DeploymentView) -> bool:
    """Whether `dep` may serve `robot` at all: alive, not draining, its service, its model."""
    return (
        dep.alive
        and not dep.draining
        and dep.service == robot.service
        and (
            robot.model_digest is None
            or dep.model_digest is None
            or dep.model_digest == robot.model_digest
        )
    )


def no_room_for(robot: RobotView, deployments: Iterable[DeploymentView]) -> bool:
    """Admission's test (trigger 1 with every target full): some deployment could serve `robot`
    and every one that could is full. The registration reply asks it of a robot not placed yet,
    so that a robot refused for capacity learns it at once, not one round later."""
    usable = [d for d in deployments if _usable(robot, d)]
    return bool(usable) and all(d.full for d in usable)


def _committed(robot: RobotView, dep: DeploymentView) -> int:
    """The load `dep` is committed to: its reported load, or the robots routed to it when more
    (each holds a request slot as soon as it is routed; the report is seconds old)."""
    return max(dep.load, robot.routed.get(dep.id, 0))


def _committed_share(robot: RobotView, dep: DeploymentView) -> float:
    """Committed load over capacity (0 when the capacity is unknown)."""
    return _committed(robot, dep) / dep.capacity if dep.capacity > 0 else 0.0


def _room_to_place(dep: DeploymentView, committed: int, share: float) -> bool:
    """Whether one more robot fits on `dep`: its committed load below `share` of its capacity
    (unknown capacity: nothing says it is short of room)."""
    return dep.capacity <= 0 or committed < dep.capacity * share


class _Targets:
    """Where a robot that is not forced to move could go: deployments other than its current
    one, usable, neither penalized nor full, with a confident prediction below a limit, at most
    `max_tier` (0: meeting the bound). `ranked` lists them all in rank order, as a decision
    needs them (the switch falls back along the list); `best` finds only the first of that list,
    visiting deployments by ascending probe statistic and stopping as soon as no later one can
    come first: a prediction is the statistic scaled up by load, never down, so a statistic at
    the limit, above the bound (for tier 0) or above the best prediction so far ends the search.
    Among these candidates the rank is by prediction, then utilization, then id (the tier follows
    the prediction: meeting the bound is a prediction at most the bound).
    """

    __slots__ = ("_current", "_now", "_profiles", "_robot", "_scheduler", "_st", "_table")

    def __init__(
        self,
        scheduler: Scheduler,
        robot: RobotView,
        current: DeploymentView,
        table: DeploymentTable,
        profiles: Profiles,
        st: RobotMemoryEntry,
        now: float,
    ) -> None:
        self._scheduler = scheduler
        self._robot = robot
        self._current = current
        self._table = table
        self._profiles = profiles
        self._st = st
        self._now = now

    def _accepts(
        self, c: _Candidate, limit: float, max_tier: int, headroom: float | None = None
    ) -> bool:
        return (
            c.deployment.id != self._current.id
            and c.tier <= max_tier
            and c.confident_s is not None
            and c.confident_s < limit
            and (headroom is None or c.deployment.has_room(headroom))
        )

    def ranked(
        self, limit: float, max_tier: int, headroom: float | None = None
    ) -> list[_Candidate]:
        """Every target, best first (ranks every deployment); with `headroom`, only those
        with that share of their capacity free."""
        sched = self._scheduler
        every = sched._rank(self._robot, self._table, self._profiles, self._st, self._now)
        return [c for c in every if self._accepts(c, limit, max_tier, headroom)]

    def best(self, limit: float, max_tier: int, headroom: float | None = None) -> _Candidate | None:
        """The first of `ranked(limit, max_tier, headroom)`, or None when there is none."""
        sched, bound = self._scheduler, self._scheduler.bound
        best: _Candidate | None = None
        for value, dep_id in self._profiles.ascending(bound.stat):
            if value >= limit or (max_tier == 0 and value > bound.seconds):
                break
            if best is not None and best.predicted_s is not None and value > best.predicted_s:
                break
            if dep_id == self._current.id:
                continue  # never a target; usually the robot's best, so met on every round
            dep = self._table.by_id.get(dep_id)
            if (
                dep is None
                or sched.memory.avoided(self._st, dep_id, now=self._now)
                or dep.full
                or (headroom is not None and not dep.has_room(headroom))
                or not _usable(self._robot, dep)
            ):
                # A penalized or full deployment ranks in tier 2, never a target here; one
                # without the headroom asked for is refused by `_accepts`: both are skipped
                # before a candidate is built (on a loaded fleet, most of the walk).
                continue
            c = sched._candidate(self._robot, dep, self._profiles, self._st, self._now)
            if self._accepts(c, limit, max_tier, headroom) and (
                best is None or c.sort_key() < best.sort_key()
            ):
                best = c
        return best


def _move(
    robot: str, from_deployment: str | None, ranked: list[_Candidate], reason: Reason
) -> RouteDecision:
    """Move `robot` to the first of `ranked` (not empty), the others as fallbacks in order."""
    return RouteDecision(
        robot=robot,
        from_deployment=from_deployment,
        to_deployment=ranked[0].deployment.id,
        reason=reason,
        candidates=tuple(c.deployment.id for c in ranked),
        predicted_s=ranked[0].predicted_s,
    )
