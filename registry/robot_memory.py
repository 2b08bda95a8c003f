"""What the scheduler remembers per robot between rounds, and how that memory ages.

Per robot (`RobotMemoryEntry`): when it last moved, when the triggers that wait (violation, busy,
better) started, when an attempt to move it found no taker, whether it was told there is no
capacity, and the deployments it left: for being slow (`left_at`: penalized until their probes
have met the bound for `recovery_s`; a deployment that goes away is forgotten, as one that comes
back is a fresh process) or for `busy` (`left_busy`: not a target of a move by choice for
`flap_window_s`). Per deployment, when a robot last moved there for `busy` (the arrival gap).

The scheduler (`registry.scheduler`) reads and updates the waiting triggers itself; this module
keeps what a carried-out switch leaves behind and ages the penalties.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

from registry.latency import LatencyBound, WindowStats


class _Liveness(Protocol):
    @property
    def alive(self) -> bool: ...


def recent_profile(stats: WindowStats | None, now: float, max_age_s: float) -> WindowStats | None:
    """`stats` if it has a sample younger than `max_age_s`, else None."""
    if stats is None or stats.count < 1 or now - stats.last_at > max_age_s:
        return None
    return stats


@dataclass
class RobotMemoryEntry:
    """One robot's memory (see the module docstring); times from the scheduler's clock."""

    last_switch_at: float | None = None
    violation_since: float | None = None
    busy_since: float | None = None
    better_since: float | None = None
    better_target: str | None = None
    failed_at: float | None = None
    violation_move_at: float | None = None
    left_at: dict[str, float] = field(default_factory=dict)
    left_busy: dict[str, float] = field(default_factory=dict)
    good_since: dict[str, float] = field(default_factory=dict)
    # The robot was told it has no route for want of capacity: not told again each round.
    no_capacity: bool = False


class RobotMemory:
    """Every robot's `RobotMemoryEntry`, the busy arrivals per deployment, and the penalties'
    aging."""

    def __init__(
        self,
        bound: LatencyBound,
        *,
        flap_window_s: float,
        recovery_s: float,
        min_probe_samples: int,
        profile_max_age_s: float,
    ) -> None:
        self._bound = bound
        self._flap_window_s = flap_window_s
        self._recovery_s = recovery_s
        self._min_probe_samples = min_probe_samples
        self._profile_max_age_s = profile_max_age_s
        self._robots: dict[str, RobotMemoryEntry] = {}
        # deployment -> when a robot was last moved there for `busy` (the arrival gap).
        self.busy_arrivals: dict[str, float] = {}

    def state(self, robot: str) -> RobotMemoryEntry:
        """The robot's memory, made empty on first use."""
        st = self._robots.get(robot)
        if st is None:
            st = self._robots[robot] = RobotMemoryEntry()
        return st

    def moved(
        self,
        robot: str,
        from_deployment: str | None,
        to_deployment: str | None,
        now: float,
        *,
        busy: bool,
        violation: bool,
        penalizing: bool,
        no_capacity: bool,
    ) -> None:
        """A switch was carried out: `busy` (left for busy), `violation` (for the bound),
        `penalizing` (left for being slow), `no_capacity` (refused a route for want of room)."""
        st = self.state(robot)
        st.last_switch_at = now
        st.violation_since = None
        st.busy_since = None
        st.better_since = None
        st.better_target = None
        st.failed_at = None
        st.no_capacity = to_deployment is None and no_capacity
        if busy:
            if from_deployment is not None:
                st.left_busy[from_deployment] = now
            if to_deployment is not None:
                self.busy_arrivals[to_deployment] = now
        if violation:
            st.violation_move_at = now
        if from_deployment is not None and penalizing:
            st.left_at[from_deployment] = now
            st.good_since.pop(from_deployment, None)
        if to_deployment is not None:
            # A forced move may have had to pick a penalized deployment: it is the route now.
            st.left_at.pop(to_deployment, None)
            st.left_busy.pop(to_deployment, None)
            st.good_since.pop(to_deployment, None)

    def failed(self, robot: str, now: float) -> None:
        """No candidate took the robot."""
        self.state(robot).failed_at = now

    def forget(self, robot: str) -> None:
        """Drop the memory of a robot that left the fleet."""
        self._robots.pop(robot, None)

    def penalized(self, robot: str) -> frozenset[str]:
        """Deployments the robot left for being slow and that have not recovered yet."""
        st = self._robots.get(robot)
        return frozenset(st.left_at) if st else frozenset()

    def avoided(self, st: RobotMemoryEntry, deployment: str, now: float) -> bool:
        """Whether a move by choice must not go to `deployment`: left for being slow and not
        recovered, or left for `busy` within flap_window_s."""
        if deployment in st.left_at:
            return True
        left = st.left_busy.get(deployment)
        if left is None:
            return False
        if now - left < self._flap_window_s:
            return True
        del st.left_busy[deployment]
        return False

    def update_recovery(
        self,
        st: RobotMemoryEntry,
        by_id: Mapping[str, _Liveness],
        profiles: Mapping[str, WindowStats],
        now: float,
    ) -> None:
        """Lift the penalty of each deployment whose probes have met the bound, from samples
        taken after the robot left it, for `recovery_s`."""
        for dep, left_at in list(st.left_at.items()):
            view = by_id.get(dep)
            if view is None or not view.alive:
                # Gone: a deployment that comes back is a fresh process and starts clean.
                del st.left_at[dep]
                st.good_since.pop(dep, None)
                continue
            stats = recent_profile(profiles.get(dep), now, self._profile_max_age_s)
            good = (
                stats is not None
                and stats.count >= self._min_probe_samples
                and stats.last_at > left_at
                and stats.value(self._bound.stat) <= self._bound.seconds
            )
            if not good:
                st.good_since.pop(dep, None)
                continue
            since = st.good_since.setdefault(dep, now)
            if now - since >= self._recovery_s:
                del st.left_at[dep]
                del st.good_since[dep]
