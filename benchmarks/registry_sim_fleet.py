"""The simulated fleet of benchmarks/registry_sim.py: the registry's control loop, no Zenoh.

What runs is the registry's own control loop (`registry.control_loop.ControlLoop`), whose
scheduler, switch protocol (`Switcher`), sqlite RIB (a real file, WAL), measurements and
registrar are the real ones, and whose Zenoh parts are replaced: a `SimNetwork` stands in for
`ZenohTransport` (deployments answer `ctl` with the cloud daemon's epoch rules, route changes
reach the robots at once) and a `SimProber` for the probe pool. The simulation calls what the
daemon's Zenoh callbacks and main loop call: membership changes and probe outcomes go through the
loop's `handle`, telemetry and probe reports into its measurements, and every tick
(`SCHEDULER_TICK_S`) one scheduling round (`schedule_all`), with the load refresh at the daemon's
interval and the profile save paced as the daemon paces it (`registry.profile_saver`): the
figures are those of the daemon's own code, not of a copy of its wiring that could drift from it.

The fleet. Robots and deployments sit at random points of a unit square; the remote part of a
frame is a network share growing with distance, plus the deployment's compute time scaled by its
utilization, plus log-normal noise. Every robot publishes telemetry at `telemetry_hz` (10 Hz) and
probes every live deployment every `probe_interval_s` (2 s, the robot daemon's interval; robots
are spread over the interval). Churn, per member and simulated second, scaled by `churn` (0:
none): a deployment dies with probability 1/900 and comes back after 10 s (a restarted process:
its epochs and states start empty); a deployment slows down by 150 ms for 30 s with probability
1/600; a robot leaves with probability 1/600 and, 10 s later, a new robot (new id, new place)
takes its slot. The latency bound is a median of 100 ms over 20 frames. Time is simulated (a
seeded random generator, bounded loops); only the registry's own work is timed, on the wall clock.
"""

from __future__ import annotations

import gc
import hashlib
import logging
import math
import os
import random
import resource
import statistics
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from common import keys
from common.config import FleetConfig, fleet_from_dict
from common.keys import Role
from common.membership import MemberChange
from common.throttled_log import ThrottledLog
from common.wire.registry import (
    CAP_CTL,
    CAP_INFER,
    CAP_PROBE,
    PROTOCOL_VERSION,
    CtlOp,
    CtlReply,
    CtlRequest,
    DeploymentState,
    ProbeReply,
    RouteChange,
)
from common.wire.telemetry import ProbeReport, TelemetryRecord
from registry.control_loop import ControlLoop, Evaluate
from registry.daemon import (
    LOAD_REFRESH_INTERVAL_S,
    PROFILE_SAVE_INTERVAL_S,
    SCHEDULER_TICK_S,
    RegistryDaemon,
)
from registry.measurements import Measurements
from registry.prober import Probed
from registry.registration import Registrar, fleet_model_digest
from registry.rib import Rib
from registry.scheduler import Scheduler
from registry.switch import Switcher
from registry.views import RibViews

try:
    from registry.profile_saver import PacedSaver
except ImportError:  # a --baseline-src revision from before paced saves: a whole save per interval
    PacedSaver = None  # type: ignore[assignment,misc]
from robotd.frame_path.probes import PROBE_INTERVAL_S

# A baseline's registry/ (--baseline-src) may be found beside this one's profile_saver module,
# while its Measurements cannot save in slices.
PACED = PacedSaver is not None and hasattr(Measurements, "unsaved")

FLEET = "sim"
SERVICE = "vision"
MODEL_DIGEST = "5e" * 32
DEFAULT_WARMUP_S = 20.0
DEFAULT_DURATION_S = 20.0
DEFAULT_TELEMETRY_HZ = 10.0
# The fleet's latency bound and frame deadline.
BOUND_MEDIAN_S = 0.1
WINDOW = 20
DEADLINE_S = 0.5
# The latency model: network share per unit of distance across the unit square, compute time.
NET_BASE_S = 0.004
NET_PER_UNIT_S = 0.12
CLOUD_S = 0.012
SLOW_EXTRA_S = 0.15
NOISE_SIGMA = 0.15
# Capacity of a deployment in robots served: a few times its fair share, so the fleet has room.
CAPACITY_SHARES = 3
MIN_CAPACITY = 4
# Churn, per member and simulated second (scaled by --churn): mean lifetimes and downtimes.
DEPLOYMENT_LIFE_S = 900.0
DEPLOYMENT_DOWN_S = 10.0
SLOW_EVERY_S = 600.0
SLOW_FOR_S = 30.0
ROBOT_SESSION_S = 600.0
ROBOT_AWAY_S = 10.0
# Robots join over the first seconds rather than all in the first tick.
ROBOT_RAMP_S = 5.0
# Wall clock of simulated time 0 (what the RIB stores).
WALL_EPOCH_S = 1.7e9
# A frame that timed out, as the robot reports it (the wire's reason value).
TIMEOUT_REASON: Any = "timeout"
ACTION_CUT = "cut:1"
ACTION_ROBOT = "P"
BYTES_UP = 150_000
BYTES_DOWN = 4_000
# The RIB's write methods, each one transaction (those of older revisions included).
RIB_WRITERS = (
    "record_event",
    "upsert_deployment",
    "set_deployment_alive",
    "set_deployment_draining",
    "update_deployment_load",
    "update_deployment_loads",
    "upsert_robot",
    "set_robot_alive",
    "reset_liveness",
    "set_deployment_state",
    "reserve_epoch",
    "set_route",
    "save_profile",
    "save_profiles",
)
MIB = 1024 * 1024


@dataclass(frozen=True)
class SimConfig:
    """One simulated fleet."""

    robots: int
    deployments: int
    warmup_s: float = DEFAULT_WARMUP_S
    duration_s: float = DEFAULT_DURATION_S
    seed: int = 0
    churn: float = 1.0
    telemetry_hz: float = DEFAULT_TELEMETRY_HZ
    probe_interval_s: float = PROBE_INTERVAL_S

    def __post_init__(self) -> None:
        if self.robots < 1 or self.deployments < 1:
            raise ValueError(f"need robots and deployments >= 1, got {self}")
        if self.warmup_s < 0 or self.duration_s < SCHEDULER_TICK_S or self.churn < 0:
            raise ValueError(
                f"warmup_s >= 0, duration_s >= one tick ({SCHEDULER_TICK_S} s), churn >= 0: {self}"
            )
        frames = self.telemetry_hz * SCHEDULER_TICK_S
        if frames < 1 or abs(frames - round(frames)) > 1e-9:
            raise ValueError(
                f"telemetry_hz must be a whole number of frames per {SCHEDULER_TICK_S} s tick,"
                f" got {self.telemetry_hz}"
            )
        if self.probe_interval_s < SCHEDULER_TICK_S:
            raise ValueError(f"probe_interval_s must be at least one tick, got {self}")


@dataclass(frozen=True)
class SizeResult:
    """The figures of one simulated fleet (see the module docstring)."""

    robots: int
    deployments: int
    rounds: int
    round_median_ms: float
    round_p95_ms: float
    round_max_ms: float
    decisions_per_s: float
    moves_per_s: float
    moves_by_reason: dict[str, float]
    """Route changes per second by the reason published with them (initial, violation, ...)."""
    rib_writes_per_s: float
    profiles_saved_per_s: float
    reports_per_s: float
    ingest_us_per_report: float
    refresh_max_ms: float
    save_max_ms: float
    core_share: float
    rounds_share: float
    ingest_share: float
    save_share: float
    gc_full_collections: int
    gc_max_pause_ms: float
    route_changes_digest: str
    peak_rss_mib: float
    rss_growth_mib: float
    wall_s: float


class SimClock:
    """Simulated time: the scheduler's monotonic clock and the RIB's wall clock."""

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def wall(self) -> float:
        return WALL_EPOCH_S + self.t


@dataclass
class SimDeployment:
    """A cloud daemon as the registry sees it: ctl with its epoch rules, probe replies, load."""

    id: str
    x: float
    y: float
    capacity: int
    alive: bool = False
    down_until: float = 0.0
    slow_until: float = -math.inf
    epochs: dict[str, int] = field(default_factory=dict)
    states: dict[str, DeploymentState] = field(default_factory=dict)
    serving: set[str] = field(default_factory=set)

    def start(self) -> None:
        """A fresh process: every robot in standby, no epoch known."""
        self.alive = True
        self.epochs.clear()
        self.states.clear()
        self.serving.clear()

    def handle(self, req: CtlRequest) -> CtlReply:
        """`service`/`standby` at an epoch, refused (with its own epoch) when not fresh."""
        assert req.robot is not None
        robot = req.robot
        known = self.epochs.get(robot, 0)
        fresh = req.epoch > known if req.op is CtlOp.SERVICE else req.epoch >= known
        if not fresh:
            return CtlReply(
                ok=False,
                deployment=self.id,
                op=req.op,
                robot=robot,
                epoch=known,
                state=self.states.get(robot),
                reason="stale epoch",
            )
        state = DeploymentState.SERVICE if req.op is CtlOp.SERVICE else DeploymentState.STANDBY
        self.epochs[robot] = req.epoch
        self.states[robot] = state
        if state is DeploymentState.SERVICE:
            self.serving.add(robot)
        else:
            self.serving.discard(robot)
        return CtlReply(
            ok=True, deployment=self.id, op=req.op, robot=robot, epoch=req.epoch, state=state
        )

    def probe_reply(self) -> ProbeReply:
        return ProbeReply(
            deployment=self.id,
            protocol_version=PROTOCOL_VERSION,
            capabilities=(CAP_INFER, CAP_PROBE, CAP_CTL),
            service=SERVICE,
            model_digest=MODEL_DIGEST,
            states=dict(self.states),
            load=len(self.serving),
            capacity=self.capacity,
            epochs=dict(self.epochs),
        )


@dataclass
class SimRobot:
    """A robot: where it is, whether it is up, and the route it was last told."""

    id: str
    slot: int
    x: float
    y: float
    alive: bool = False
    joins_at: float = 0.0
    route: str | None = None
    frame: int = 0


class SimNetwork:
    """`SwitchTransport` without Zenoh: ctl answered by the simulated deployment at once (a dead
    one never answers: a timeout, without the wait), route changes delivered to the robot."""

    def __init__(self) -> None:
        self.deployments: dict[str, SimDeployment] = {}
        self.robots: dict[str, SimRobot] = {}
        self.published = 0
        self.by_reason: Counter[str] = Counter()
        # Every route change of the run, in order: two revisions that decide alike agree on it.
        self.changes = hashlib.sha256()

    def send_ctl(self, deployment: str, request: CtlRequest, timeout_s: float) -> CtlReply | None:
        dep = self.deployments.get(deployment)
        return dep.handle(request) if dep is not None and dep.alive else None

    def publish_route(self, change: RouteChange) -> None:
        self.published += 1
        self.by_reason[str(change.reason)] += 1
        line = f"{change.robot} {change.deployment} {change.epoch} {change.reason}\n"
        self.changes.update(line.encode())
        robot = self.robots.get(change.robot)
        if robot is not None:
            robot.route = change.deployment


class SimProber:
    """The probe pool without Zenoh: each probe is answered at once, its outcome queued."""

    def __init__(self, network: SimNetwork) -> None:
        self.network = network
        self.outcomes: list[Probed] = []

    def submit(self, deployment: str, *, refresh: bool) -> None:
        dep = self.network.deployments.get(deployment)
        if dep is not None and dep.alive:
            self.outcomes.append(Probed(deployment, dep.probe_reply(), "", refresh))
        else:
            self.outcomes.append(Probed(deployment, None, "no probe reply", refresh))

    def close(self) -> None:
        self.outcomes.clear()


class RibWrites:
    """Counts the RIB's write transactions: each call of a public write method (outermost only,
    a write calling another is one transaction)."""

    def __init__(self, rib: Rib) -> None:
        self.count = 0
        self._depth = 0
        for name in RIB_WRITERS:
            method = getattr(rib, name, None)
            if method is not None:
                setattr(rib, name, self._counted(method))

    def _counted(self, method: Callable[..., Any]) -> Callable[..., Any]:
        def counted(*args: Any, **kwargs: Any) -> Any:
            if self._depth == 0:
                self.count += 1
            self._depth += 1
            try:
                return method(*args, **kwargs)
            finally:
                self._depth -= 1

        return counted


def _fleet_config() -> FleetConfig:
    return fleet_from_dict(
        {
            "fleet": FLEET,
            "service": SERVICE,
            "model": "zoo:resnet",
            "latency_bound": {"stat": "median", "seconds": BOUND_MEDIAN_S, "window": WINDOW},
            "deadline_s": DEADLINE_S,
        }
    )


def _bad_sample(where: str, problem: str) -> None:
    raise RuntimeError(f"the simulation fed a bad sample ({where}): {problem}")


def _rss_mib() -> float:
    with open("/proc/self/statm", encoding="ascii") as statm:
        pages = int(statm.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / MIB


@dataclass
class _Tally:
    """What is counted over the measured window."""

    rounds_s: list[float] = field(default_factory=list)
    evaluated: int = 0
    events_s: float = 0.0
    ingest_s: float = 0.0
    reports: int = 0
    refresh_s: list[float] = field(default_factory=list)
    save_s: list[float] = field(default_factory=list)
    saved: int = 0


class GcPauses:
    """The cyclic garbage collector's pauses: how many full (oldest generation)
    collections ran and the longest pause of any collection, between `start()` and `stop()`.
    They land wherever an allocation crosses a threshold: inside rounds, reports and saves."""

    def __init__(self) -> None:
        self.full = 0
        self.max_pause_s = 0.0
        self._started = 0.0

    def _callback(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._started = time.perf_counter()
            return
        self.max_pause_s = max(self.max_pause_s, time.perf_counter() - self._started)
        if info["generation"] == 2:
            self.full += 1

    def start(self) -> None:
        gc.callbacks.append(self._callback)

    def stop(self) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)


class RegistrySim:
    """One simulated fleet around one registry daemon (its RIB in a temporary folder)."""

    def __init__(self, cfg: SimConfig, workdir: Path) -> None:
        self.cfg = cfg
        self.rng = random.Random(cfg.seed)
        self.clock = SimClock()
        self.network = SimNetwork()
        self.prober = SimProber(network=self.network)
        self.loop = self._control_loop(workdir / "rib.sqlite")
        self.rib = self.loop.rib
        self.writes = RibWrites(self.rib)
        capacity = max(MIN_CAPACITY, math.ceil(CAPACITY_SHARES * cfg.robots / cfg.deployments))
        for j in range(cfg.deployments):
            dep = SimDeployment(f"dep-{j:04d}", self.rng.random(), self.rng.random(), capacity)
            self.network.deployments[dep.id] = dep
        self.slots: list[SimRobot] = []
        for i in range(cfg.robots):
            robot = self._new_robot(i, 0, joins_at=self.rng.uniform(0.0, ROBOT_RAMP_S))
            self.slots.append(robot)
        self._frames_per_tick = round(cfg.telemetry_hz * SCHEDULER_TICK_S)
        self._probe_ticks = round(cfg.probe_interval_s / SCHEDULER_TICK_S)

    # -- the registry's control loop, without Zenoh --------------------------------------------
    def _control_loop(self, db_path: Path) -> ControlLoop:
        """What `RegistryDaemon.startup` makes, with the simulated network in Zenoh's place and
        the scheduler, the measurements and the RIB on simulated time."""
        fleet_cfg = _fleet_config()
        daemon = RegistryDaemon(fleet_cfg, db_path=db_path)  # its settings; never started
        measurements = Measurements(
            daemon.bound.window,
            deadline_s=fleet_cfg.deadline_s,
            timeout_count=daemon.params.timeout_count,
            on_bad_sample=_bad_sample,
            clock=self.clock.now,
            wall_clock=self.clock.wall,
        )
        rib = Rib(db_path, clock=self.clock.wall)
        network = cast(Any, self.network)
        # The views are built as the daemon's are: part of what a RIB of this size costs.
        registrar = Registrar(FLEET, rib, SERVICE, fleet_model_digest(fleet_cfg))
        self.views = RibViews(
            FLEET, rib, measurements, registrar, daemon.bound, fleet_cfg.deadline_s
        )
        return ControlLoop(
            fleet_cfg,
            rib=rib,
            transport=network,
            switcher=Switcher(rib, network, sender=daemon.id, clock=self.clock.wall),
            registrar=registrar,
            prober=cast(Any, self.prober),
            pools=None,  # an anycast fleet
            scheduler=Scheduler(daemon.bound, daemon.params, clock=self.clock.now),
            measurements=measurements,
            throttled=ThrottledLog(logging.getLogger("registry.daemon")),
            started_at=0.0,
            restore_grace_s=0.0,
        )

    def close(self) -> None:
        self.rib.close()

    # -- membership ----------------------------------------------------------------------------
    def _new_robot(self, slot: int, generation: int, *, joins_at: float) -> SimRobot:
        robot = SimRobot(
            f"robot-{slot:05d}-g{generation}",
            slot,
            self.rng.random(),
            self.rng.random(),
            joins_at=joins_at,
        )
        self.network.robots[robot.id] = robot
        return robot

    def _member(self, role: Role, member: str, alive: bool) -> None:
        change = MemberChange(
            role=role.value, id=member, alive=alive, seed=False, alive_ids=frozenset()
        )
        self.loop.handle(change)

    def _start_deployment(self, dep: SimDeployment) -> None:
        dep.start()
        self._member(Role.CLOUD, dep.id, True)  # the daemon submits a registration probe

    def _kill_deployment(self, dep: SimDeployment) -> None:
        dep.alive = False
        dep.down_until = self.clock.t + DEPLOYMENT_DOWN_S
        self._member(Role.CLOUD, dep.id, False)

    def _churn(self, first: bool) -> None:
        """Once per simulated second: members die, come back, slow down, leave and join."""
        now, rate, rng = self.clock.t, self.cfg.churn, self.rng
        deployments = list(self.network.deployments.values())
        for dep in deployments:
            if first:
                self._start_deployment(dep)
            elif dep.alive:
                alive = sum(1 for d in deployments if d.alive)
                if alive > 1 and rng.random() < rate / DEPLOYMENT_LIFE_S:
                    self._kill_deployment(dep)
                elif now >= dep.slow_until and rng.random() < rate / SLOW_EVERY_S:
                    dep.slow_until = now + SLOW_FOR_S
            elif now >= dep.down_until:
                self._start_deployment(dep)
        for i, robot in enumerate(self.slots):
            if robot.alive and rng.random() < rate / ROBOT_SESSION_S:
                robot.alive = False
                self._member(Role.ROBOT, robot.id, False)
                generation = int(robot.id.rsplit("-g", 1)[1]) + 1
                self.slots[i] = self._new_robot(i, generation, joins_at=now + ROBOT_AWAY_S)
                del self.network.robots[robot.id]

    def _join_robots(self) -> None:
        now = self.clock.t
        for robot in self.slots:
            if not robot.alive and now >= robot.joins_at:
                robot.alive = True
                self._member(Role.ROBOT, robot.id, True)

    # -- what robots publish -------------------------------------------------------------------
    def _latency_s(self, robot: SimRobot, dep: SimDeployment) -> tuple[float, float]:
        """(network share, remote part of a frame) of `robot` through `dep`, now."""
        net = NET_BASE_S + NET_PER_UNIT_S * math.hypot(robot.x - dep.x, robot.y - dep.y)
        cloud = CLOUD_S * (1 + len(dep.serving) / dep.capacity)
        if self.clock.t < dep.slow_until:
            cloud += SLOW_EXTRA_S
        noise = self.rng.lognormvariate(0.0, NOISE_SIGMA)
        return net * noise, (net + cloud) * noise

    def _telemetry(self, tally: _Tally) -> None:
        measurements = self.loop.measurements
        wall = self.clock.wall()
        for robot in self.slots:
            if not robot.alive:
                continue
            for _ in range(self._frames_per_tick):
                rec = self._frame(robot, wall)
                start = time.perf_counter()
                reroute = measurements.record_telemetry(rec, keys.tele(FLEET, robot.id))
                tally.ingest_s += time.perf_counter() - start
                tally.reports += 1
                if reroute:
                    self._handle(Evaluate(robot.id), tally)

    def _frame(self, robot: SimRobot, wall: float) -> TelemetryRecord:
        robot.frame += 1
        dep = self.network.deployments.get(robot.route) if robot.route is not None else None
        transfer_s = cloud_s = 0.0
        fallback, reason, answered = False, None, None
        action = ACTION_CUT
        if dep is None:
            action = ACTION_ROBOT
        elif dep.alive:
            transfer_s, remote_s = self._latency_s(robot, dep)
            cloud_s, answered = remote_s - transfer_s, dep.id
        else:
            fallback, reason, transfer_s = True, TIMEOUT_REASON, DEADLINE_S
        return TelemetryRecord(
            robot=robot.id,
            frame=robot.frame,
            action=action,
            bytes_up=BYTES_UP,
            bytes_down=BYTES_DOWN,
            prefix_s=0.01,
            transfer_s=transfer_s,
            cloud_s=cloud_s,
            suffix_local_s=0.0,
            latency_s=0.01 + transfer_s + cloud_s,
            robot_cpu_s=0.01,
            energy_j=0.1,
            deployment=answered,
            fallback=fallback,
            reason=reason,
            at=wall,
        )

    def _probes(self, tick: int, tally: _Tally) -> None:
        """The robots whose turn it is probe every live deployment."""
        measurements = self.loop.measurements
        wall = self.clock.wall()
        live = [d for d in self.network.deployments.values() if d.alive]
        for robot in self.slots:
            if not robot.alive or (robot.slot + tick) % self._probe_ticks:
                continue
            key = keys.tele_probe(FLEET, robot.id)
            for dep in live:
                rtt_s, remote_s = self._latency_s(robot, dep)
                report = ProbeReport(
                    robot=robot.id,
                    deployment=dep.id,
                    ok=True,
                    at=wall,
                    rtt_s=rtt_s,
                    load=len(dep.serving),
                    capacity=dep.capacity,
                    expected_latency_s=remote_s,
                )
                start = time.perf_counter()
                measurements.record_probe_report(report, key)
                tally.ingest_s += time.perf_counter() - start
                tally.reports += 1

    # -- the control loop ----------------------------------------------------------------------
    def _handle(self, event: Any, tally: _Tally) -> None:
        start = time.perf_counter()
        self.loop.handle(event)
        tally.events_s += time.perf_counter() - start

    def _probed(self, tally: _Tally) -> None:
        while self.prober.outcomes:
            outcomes, self.prober.outcomes = self.prober.outcomes, []
            for outcome in outcomes:
                self._handle(outcome, tally)

    def run(self) -> SizeResult:
        cfg = self.cfg
        rss_start = _rss_mib()
        wall_start = time.perf_counter()
        per_s = round(1 / SCHEDULER_TICK_S)
        refresh_ticks = round(LOAD_REFRESH_INTERVAL_S / SCHEDULER_TICK_S)
        save_ticks = round(PROFILE_SAVE_INTERVAL_S / SCHEDULER_TICK_S)
        saver = (
            None
            if not PACED
            else PacedSaver(
                self.loop.measurements,
                self.rib,
                tick_s=SCHEDULER_TICK_S,
                interval_s=PROFILE_SAVE_INTERVAL_S,
            )
        )
        warmup_ticks = round(cfg.warmup_s / SCHEDULER_TICK_S)
        ticks = warmup_ticks + round(cfg.duration_s / SCHEDULER_TICK_S)
        tally = _Tally()
        writes_at = published_at = 0
        by_reason_at: Counter[str] = Counter()
        pauses = GcPauses()
        for tick in range(ticks):
            self.clock.t = tick * SCHEDULER_TICK_S
            if tick == warmup_ticks:
                tally = _Tally()
                writes_at, published_at = self.writes.count, self.network.published
                by_reason_at = Counter(self.network.by_reason)
                pauses.start()
            if tick % per_s == 0:
                self._churn(first=tick == 0)
            self._join_robots()
            self._probed(tally)
            self._telemetry(tally)
            self._probes(tick, tally)
            start = time.perf_counter()
            self.loop.schedule_all()
            tally.rounds_s.append(time.perf_counter() - start)
            tally.evaluated += sum(1 for r in self.slots if r.alive)
            if tick % refresh_ticks == refresh_ticks - 1:
                start = time.perf_counter()
                self.loop.refresh_deployments()
                self._probed(tally)
                tally.refresh_s.append(time.perf_counter() - start)
            if saver is not None:  # as the daemon's loop: a share after every round
                start = time.perf_counter()
                tally.saved += saver.tick(self.clock.t)
                tally.save_s.append(time.perf_counter() - start)
            elif tick % save_ticks == save_ticks - 1:
                start = time.perf_counter()
                tally.saved += self.loop.measurements.save(self.rib)
                tally.save_s.append(time.perf_counter() - start)
        pauses.stop()
        span_s = cfg.duration_s
        rounds = tally.rounds_s
        busy_s = (
            sum(rounds) + tally.events_s + tally.ingest_s + sum(tally.refresh_s) + sum(tally.save_s)
        )
        peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        return SizeResult(
            robots=cfg.robots,
            deployments=cfg.deployments,
            rounds=len(rounds),
            round_median_ms=statistics.median(rounds) * 1e3,
            round_p95_ms=_p95(rounds) * 1e3,
            round_max_ms=max(rounds) * 1e3,
            decisions_per_s=tally.evaluated / sum(rounds) if sum(rounds) > 0 else math.inf,
            moves_per_s=(self.network.published - published_at) / span_s,
            moves_by_reason={
                reason: (count - by_reason_at[reason]) / span_s
                for reason, count in sorted(self.network.by_reason.items())
                if count > by_reason_at[reason]
            },
            rib_writes_per_s=(self.writes.count - writes_at) / span_s,
            profiles_saved_per_s=tally.saved / span_s,
            reports_per_s=tally.reports / span_s,
            ingest_us_per_report=tally.ingest_s / max(1, tally.reports) * 1e6,
            refresh_max_ms=max(tally.refresh_s, default=0.0) * 1e3,
            save_max_ms=max(tally.save_s, default=0.0) * 1e3,
            core_share=busy_s / span_s,
            rounds_share=sum(rounds) / span_s,
            ingest_share=tally.ingest_s / span_s,
            save_share=sum(tally.save_s) / span_s,
            gc_full_collections=pauses.full,
            gc_max_pause_ms=pauses.max_pause_s * 1e3,
            route_changes_digest=self.network.changes.hexdigest()[:16],
            peak_rss_mib=peak_rss,
            rss_growth_mib=peak_rss - rss_start,
            wall_s=time.perf_counter() - wall_start,
        )


def _p95(values: Sequence[float]) -> float:
    ordered = sorted(values)
    return ordered[max(0, math.ceil(0.95 * len(ordered)) - 1)]


def simulate(cfg: SimConfig) -> SizeResult:
    """Run one simulated fleet in this process and return its figures."""
    with tempfile.TemporaryDirectory(prefix="registry-sim-") as tmp:
        sim = RegistrySim(cfg, Path(tmp))
        try:
            return sim.run()
        finally:
            sim.close()
