"""What the registry measures about routes: latency windows, consecutive timeouts, loads.

Telemetry and probe reports arrive on Zenoh callback threads; the control loop reads (to decide)
and so do the RIB views (to show). Everything here sits behind one lock of its own, held only for
dictionary work, never for I/O or a decision: a callback never waits on the RIB or a switch, and
the registry daemon's other state needs no lock for it.

Both sources measure the same thing, the remote part of a frame (docs/registry.md, "Measures fed
to the windows"): a frame answered by a deployment counts `transfer_s + cloud_s` in that
deployment's telemetry window; a frame that timed out on the route's deployment counts at least
the deadline there, and the robot's consecutive failures on that route grow (a frame that found
nobody serving its key counts as a failure, not as a sample); a probe report counts the robot's
`expected_latency_s` when it gives one, else the probe's round trip. When a robot reaches
`timeout_count` consecutive failures on its route, `record_telemetry` says so once, until the
route changes or a frame gets through.

Each robot's route is cached here (the control loop sets it, `set_route`) so that a failure is
counted against the deployment that was meant to serve it. Windows are persisted with `save`
(only those that changed since, each with the wall clock of its newest sample) and come back with
`restore`, keeping their age: the scheduler ignores probe windows older than its limit, across a
restart too. Loads from probe reports are written to the RIB by `flush_loads`, not on every report.

`busy` replies are a scheduling signal too: of the last `busy_window` frames a robot offloaded to
its route's deployment, the scheduler sees how many were refused `busy` (`RobotMeasures.busy`
out of `offloaded`); the count restarts when the route changes.

A robot to be placed also sees how many robots are routed to each deployment
(`RobotMeasures.routed`): counted as routes are set, so a robot placed earlier in the same round
counts at once, where the deployments' reported loads are seconds old.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from common.wire.telemetry import FallbackReason, ProbeReport, TelemetryRecord
from registry.latency import LatencyWindows, Profiles, Source, WindowKey, WindowStats
from registry.rib import Rib

# Fallback reasons that count as consecutive failures of the route: the deployment did not answer
# in time (also a latency sample), or nobody serves the robot's key at all (no sample).
ROUTE_FAILURES = frozenset({FallbackReason.TIMEOUT, FallbackReason.NO_ROUTE})

Route = tuple[str | None, int]
"""(deployment, epoch) of a robot's route; (None, 0) when it has none."""

NO_ROUTE: Route = (None, 0)

DEFAULT_BUSY_WINDOW = 20
"""Frames offloaded to the route's deployment over which the share refused `busy` is counted."""


@dataclass(frozen=True)
class RobotMeasures:
    """What the scheduler needs about one robot: the telemetry window of its route, its
    consecutive failures (and the deployment they were against), its probe profiles, and of its
    last frames offloaded to its route (`offloaded`) how many were refused `busy`. `routed`: the
    robots routed to each deployment, for a robot without a route (empty for the others)."""

    telemetry: WindowStats | None
    timeouts_on: str | None
    timeouts: int
    profiles: Profiles
    busy: int = 0
    offloaded: int = 0
    routed: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class RobotStatus:
    """What the robots view shows about one robot."""

    telemetry: WindowStats | None
    action: str | None
    timeouts: int
    last_telemetry: float | None


@dataclass(frozen=True)
class ProbeProfile:
    """One probe window's statistics, with the wall clock of its newest sample."""

    robot: str
    deployment: str
    stats: WindowStats
    updated_at: float | None


class Measurements:
    """`Measurements(window, deadline_s=..., timeout_count=..., on_bad_sample=...)`: thread-safe.

    `on_bad_sample(where, problem)` hears of a sample refused by its window (NaN, negative), after
    the lock is released. `clock` stamps samples for the scheduler (monotonic); `wall_clock`
    stamps what is persisted or shown.
    """

    def __init__(
        self,
        window: int,
        *,
        deadline_s: float,
        timeout_count: int,
        on_bad_sample: Callable[[str, str], None],
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        busy_window: int = DEFAULT_BUSY_WINDOW,
    ) -> None:
        if busy_window < 1:
            raise ValueError(f"busy_window must be at least 1 frame, got {busy_window}")
        self.deadline_s = deadline_s
        self.busy_window = busy_window
        self.timeout_count = timeout_count
        self._on_bad_sample = on_bad_sample
        self._clock = clock
        self._wall_clock = wall_clock
        self._lock = threading.Lock()
        self._windows = LatencyWindows(window)
        self._sample_wall: dict[WindowKey, float] = {}  # wall clock of each window's newest sample
        # Changed since last saved, in the order they first changed (saves take the oldest).
        self._dirty: dict[WindowKey, None] = {}
        self._timeouts: dict[str, tuple[str, int]] = {}  # robot -> (deployment, consecutive)
        self._reroute_asked: set[str] = set()
        self._actions: dict[str, str] = {}
        self._last_telemetry: dict[str, float] = {}
        self._routes: dict[str, Route] = {}
        self._loads: dict[str, tuple[int, int | None]] = {}  # from probe reports, not yet saved
        # robot -> its last frames offloaded to its route, True for a `busy` refusal.
        self._busy: dict[str, deque[bool]] = {}
        # Robots present with a route: robot -> its deployments (a round-robin pool's every
        # member: each holds the robot's requests), and how many robots per deployment.
        self._counted: dict[str, tuple[str, ...]] = {}
        self._routed: Counter[str] = Counter()

    # -- feeding (Zenoh callback threads) --------------------------------------------------------
    def record_telemetry(self, rec: TelemetryRecord, key: str) -> bool:
        """Account for one frame published on `key`; True when the robot has just reached
        `timeout_count` consecutive failures on its route (its reroute is to be asked, once)."""
        now = self._clock()
        reroute = False
        problems: list[tuple[str, str]] = []
        with self._lock:
            robot = rec.robot
            self._actions[robot] = rec.action
            self._last_telemetry[robot] = self._wall_clock()
            if rec.cut is None:
                return False  # computed on the robot: says nothing about any deployment
            route = self._routes.get(robot, NO_ROUTE)[0]
            remote_s = rec.transfer_s + rec.cloud_s
            if route is not None and (rec.deployment == route or rec.deployment is None):
                self._note_busy(robot, rec)
            if not rec.fallback and rec.deployment is not None:
                self._add(robot, rec.deployment, Source.TELEMETRY, remote_s, now, key, problems)
                if rec.deployment == route:
                    self._timeouts.pop(robot, None)
                    self._reroute_asked.discard(robot)
            elif rec.fallback and route is not None and rec.reason in ROUTE_FAILURES:
                if rec.reason is FallbackReason.TIMEOUT:
                    # A timeout took at least the deadline: the window sees it as that.
                    finite = remote_s if math.isfinite(remote_s) else 0.0
                    sample_s = max(self.deadline_s, finite)
                    self._add(robot, route, Source.TELEMETRY, sample_s, now, key, problems)
                on, count = self._timeouts.get(robot, (route, 0))
                count = count + 1 if on == route else 1
                self._timeouts[robot] = (route, count)
                if count >= self.timeout_count and robot not in self._reroute_asked:
                    self._reroute_asked.add(robot)
                    reroute = True
        self._report(problems)
        return reroute

    def _note_busy(self, robot: str, rec: TelemetryRecord) -> None:
        """Count one frame offloaded to the route in the robot's busy window (the lock is held):
        answered, or refused `busy`. Other failures say nothing about room at the deployment."""
        busy = rec.fallback and rec.reason is FallbackReason.BUSY
        if not busy and (rec.fallback or rec.deployment is None):
            return
        window = self._busy.get(robot)
        if window is None:
            window = self._busy[robot] = deque(maxlen=self.busy_window)
        window.append(busy)

    def record_probe_report(self, rep: ProbeReport, key: str) -> None:
        """Account for one probe report published on `key`."""
        if not rep.ok:
            return  # no measurement; a dead deployment shows in liveliness, a slow one in time
        value = rep.expected_latency_s if rep.expected_latency_s is not None else rep.rtt_s
        problems: list[tuple[str, str]] = []
        with self._lock:
            if value is not None:
                self._add(
                    rep.robot, rep.deployment, Source.PROBE, value, self._clock(), key, problems
                )
            if rep.load is not None:
                self._loads[rep.deployment] = (rep.load, rep.capacity)
        self._report(problems)

    def _add(
        self,
        robot: str,
        deployment: str,
        source: Source,
        value: float,
        at: float,
        key: str,
        problems: list[tuple[str, str]],
    ) -> None:
        """Record one sample (the lock is held); a bad number goes to `problems`, not the window."""
        try:
            self._windows.add(robot, deployment, source, value, at)
        except ValueError as exc:
            problems.append((f"{source.value} on {key}", str(exc)))
            return
        wkey = (robot, deployment, source)
        self._sample_wall[wkey] = self._wall_clock()
        self._dirty[wkey] = None

    def _report(self, problems: list[tuple[str, str]]) -> None:
        for where, problem in problems:
            self._on_bad_sample(where, problem)

    # -- routes and membership (control loop) ----------------------------------------------------
    def route(self, robot: str) -> Route:
        """The robot's route as last set (NO_ROUTE when none)."""
        with self._lock:
            return self._routes.get(robot, NO_ROUTE)

    def set_route(
        self, robot: str, deployment: str | None, epoch: int, pool: Sequence[str] | None = ()
    ) -> None:
        """The robot's route changed or was confirmed (`pool`: a round-robin pool's members,
        `deployment` first; None: a restored route of a robot not back yet, counted on no
        deployment until a round sees it). On a change of deployment its failures are forgotten
        and the new deployment's telemetry window cleared: samples from an earlier stay there
        must not count now."""
        with self._lock:
            before = self._routes.get(robot)
            self._routes[robot] = (deployment, epoch)
            self._count(robot, None if pool is None else deployment, pool or ())
            if before is None or before[0] != deployment:
                if deployment is not None:
                    self._windows.window(robot, deployment, Source.TELEMETRY).clear()
                self._timeouts.pop(robot, None)
                self._reroute_asked.discard(robot)
                self._busy.pop(robot, None)

    def _count(self, robot: str, deployment: str | None, pool: Sequence[str] = ()) -> None:
        """Count `robot` on `deployment` (on every member of its `pool`) from now on, on none
        for None (the lock is held)."""
        members = () if deployment is None else tuple(dict.fromkeys((deployment, *pool)))
        if self._counted.get(robot, ()) == members:
            return  # counted there already (every round asks again for every robot)
        for before in self._counted.pop(robot, ()):
            self._routed[before] -= 1
            if self._routed[before] <= 0:
                del self._routed[before]
        if members:
            self._counted[robot] = members
            self._routed.update(members)

    def force_timeouts(self, robot: str, deployment: str, reported: int) -> None:
        """The robot asked to leave `deployment` after `reported` consecutive timeouts: count at
        least `timeout_count`, so the scheduler moves it as it would after telemetry."""
        with self._lock:
            self._timeouts[robot] = (deployment, max(reported, self.timeout_count))

    def forget_robot(self, robot: str) -> None:
        """A robot left: its windows and failures go (its last action stays on show)."""
        with self._lock:
            self._windows.drop_robot(robot)
            self._forget_saved(lambda wkey: wkey[0] == robot)
            self._timeouts.pop(robot, None)
            self._reroute_asked.discard(robot)
            self._busy.pop(robot, None)
            self._count(robot, None)

    def forget_deployment(self, deployment: str) -> None:
        """A deployment left: a returning process starts clean."""
        with self._lock:
            self._windows.drop_deployment(deployment)
            self._forget_saved(lambda wkey: wkey[1] == deployment)
            self._loads.pop(deployment, None)

    def _forget_saved(self, dropped: Callable[[WindowKey], bool]) -> None:
        self._dirty = {wkey: None for wkey in self._dirty if not dropped(wkey)}

    # -- reading ---------------------------------------------------------------------------------
    def for_scheduler(
        self, robot: str, route: str | None, pool: Sequence[str] = ()
    ) -> RobotMeasures:
        """The robot's measures as the scheduler takes them, `route` being its deployment and
        `pool` its round-robin pool (the RIB's: the robot is counted there from now on, so a
        robot that came back counts again)."""
        with self._lock:
            self._count(robot, route, pool)
            # Copied only for a robot to be placed: the others' decisions do not read it.
            routed = dict(self._routed) if route is None else {}
            telemetry = self._windows.stats(robot, route, Source.TELEMETRY) if route else None
            timeouts_on, timeouts = self._timeouts.get(robot, (None, 0))
            profiles = self._windows.profiles(robot, Source.PROBE)
            window = self._busy.get(robot)
            busy = sum(window) if window else 0
            offloaded = len(window) if window else 0
        return RobotMeasures(telemetry, timeouts_on, timeouts, profiles, busy, offloaded, routed)

    def robot_status(self, robot: str, route: str | None) -> RobotStatus:
        """What the robots view shows of the robot, `route` being its deployment."""
        with self._lock:
            return RobotStatus(
                telemetry=(self._windows.stats(robot, route, Source.TELEMETRY) if route else None),
                action=self._actions.get(robot),
                timeouts=self._timeouts.get(robot, (None, 0))[1],
                last_telemetry=self._last_telemetry.get(robot),
            )

    def probe_profiles(self) -> list[ProbeProfile]:
        """Every non-empty probe window, by robot then deployment."""
        with self._lock:
            items = [
                (wkey, window.stats(), self._sample_wall.get(wkey))
                for wkey, window in self._windows.items()
                if wkey[2] is Source.PROBE
            ]
        return [
            ProbeProfile(robot, deployment, stats, updated_at)
            for (robot, deployment, _), stats, updated_at in sorted(items, key=lambda i: i[0][:2])
            if stats is not None
        ]

    # -- persistence -----------------------------------------------------------------------------
    def restore(self, rib: Rib) -> None:
        """Routes and windows from the RIB, at startup. Each window keeps its age (its newest
        sample's wall clock, mapped onto `clock`); one the windows refuse is left empty."""
        routes, profiles = rib.routes(), rib.profiles()
        now, now_wall = self._clock(), self._wall_clock()
        with self._lock:
            for route in routes:
                self._routes[route.robot] = (route.deployment, route.epoch)
                self._count(route.robot, route.deployment)
            for row in profiles:
                try:
                    source = Source(row.source)
                except ValueError:
                    continue
                at = now - max(0.0, now_wall - row.updated_at)
                window = self._windows.window(row.robot, row.deployment, source)
                try:
                    window.extend(row.samples, at)
                except ValueError:
                    window.clear()
                    continue
                self._sample_wall[(row.robot, row.deployment, source)] = row.updated_at

    def routes_known(self) -> int:
        """How many robots have a route (restored or set)."""
        with self._lock:
            return len(self._routes)

    @property
    def unsaved(self) -> int:
        """Windows changed since they were last saved."""
        with self._lock:
            return len(self._dirty)

    def save(self, rib: Rib, limit: int | None = None) -> int:
        """Persist the windows changed since they were last saved (at most `limit` of them,
        those changed first); returns how many were written."""
        with self._lock:
            if limit is None or limit >= len(self._dirty):
                dirty, self._dirty = list(self._dirty), {}
            else:
                dirty = list(itertools.islice(self._dirty, max(0, limit)))
                for wkey in dirty:
                    del self._dirty[wkey]
            rows: list[tuple[str, str, str, tuple[float, ...], float | None]] = []
            for wkey in dirty:
                robot, deployment, source = wkey
                samples = self._windows.samples(robot, deployment, source)
                if samples:
                    rows.append((robot, deployment, source.value, samples, self._sample_wall[wkey]))
        # One transaction for them all: at 1,000 robots x 100 deployments that is 100,000 rows.
        return rib.save_profiles(rows)

    def flush_loads(self, rib: Rib) -> None:
        """Write the loads reported since the last flush to the RIB (live deployments whose
        load or capacity changed)."""
        with self._lock:
            loads, self._loads = self._loads, {}
        if loads:
            rib.update_deployment_loads(loads)
