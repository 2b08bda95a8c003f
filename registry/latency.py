"""Latency windows: the last N samples per (robot, deployment, source) and their statistics.

The scheduler compares a statistic of a sliding window (median, mean, p95, max or stddev) against
the fleet's latency bound. Windows are small (20 samples by default), so statistics are computed by
sorting on demand and cached until the next sample: cheap enough to evaluate on every telemetry
message. Two sources feed windows: `telemetry` (frames the robot actually sent to its serving
deployment) and `probe` (the robot's low-rate probes of every deployment, standby included).

Both sources must measure the same thing (the remote part of a frame: transfer plus cloud time),
so that a probe profile and a telemetry window can be compared. Timestamps are in the scheduler's
clock.

At fleet scale (1,000 robots probing 100 deployments is 100,000 probe windows, each changing
every 2 s) the windows are indexed by robot, a robot's probe profiles are one immutable snapshot
(`Profiles`) kept until one of its windows changes, and a snapshot computes a deployment's
statistics only when they are looked up (docs/scale.md, "The registry at scale").
"""

from __future__ import annotations

import math
import numbers
from array import array
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import SupportsFloat

from common.errors import UserError

DEFAULT_WINDOW = 20
DEFAULT_HYSTERESIS_S = 1.0
DEFAULT_BETTER_MARGIN = 0.2
P95_QUANTILE = 0.95


class Stat(str, Enum):
    """A window statistic the latency bound may be placed on."""

    MEDIAN = "median"
    MEAN = "mean"
    P95 = "p95"
    MAX = "max"
    STDDEV = "stddev"


class Source(str, Enum):
    """Where a latency sample came from."""

    TELEMETRY = "telemetry"
    PROBE = "probe"


@dataclass(frozen=True)
class LatencyBound:
    """The fleet's latency bound, as the scheduler needs it.

    Mirrors the `latency_bound` section of the fleet config (the daemon maps the config onto it):
    the bound holds while `stat` of the last `window` samples is at most `seconds`.
    """

    stat: Stat | str
    seconds: float
    window: int = DEFAULT_WINDOW
    hysteresis_s: float = DEFAULT_HYSTERESIS_S
    better_margin: float = DEFAULT_BETTER_MARGIN

    def __post_init__(self) -> None:
        # Accept the plain string from a config file ("p95") as well as the enum.
        try:
            object.__setattr__(self, "stat", Stat(self.stat))
        except ValueError:
            names = ", ".join(s.value for s in Stat)
            raise UserError(
                f"latency_bound.stat: unknown statistic {self.stat!r} (expected one of {names})"
            ) from None
        if not (math.isfinite(self.seconds) and self.seconds > 0):
            raise UserError(f"latency_bound.seconds: must be a number > 0, got {self.seconds!r}")
        if self.window < 1:
            raise UserError(f"latency_bound.window: must be at least 1 sample, got {self.window!r}")
        if not (math.isfinite(self.hysteresis_s) and self.hysteresis_s >= 0):
            raise UserError(
                f"latency_bound.hysteresis_s: must be a number >= 0, got {self.hysteresis_s!r}"
            )
        if not (0 <= self.better_margin < 1):
            raise UserError(
                f"latency_bound.better_margin: must be in [0, 1), got {self.better_margin!r}"
            )


def _median(ordered: Sequence[float]) -> float:
    n = len(ordered)
    mid = n // 2
    return ordered[mid] if n % 2 else (ordered[mid - 1] + ordered[mid]) / 2


def _mean(ordered: Sequence[float]) -> float:
    # `sum`, not `math.fsum`: a window is a few dozen positive samples (an error of about 1e-16
    # of the mean), and statistics are made for every robot in every round.
    return sum(ordered) / len(ordered)


def _p95(ordered: Sequence[float]) -> float:
    # Nearest-rank p95: the smallest sample with at least 95 % of the window at or below it.
    return ordered[max(0, math.ceil(P95_QUANTILE * len(ordered)) - 1)]


def _max(ordered: Sequence[float]) -> float:
    return ordered[-1]


def _stddev(ordered: Sequence[float], mean: float | None = None) -> float:
    if mean is None:
        mean = _mean(ordered)
    # Two passes (no cancellation); a list, not a generator: this runs for the whole fleet.
    return math.sqrt(sum([(x - mean) * (x - mean) for x in ordered]) / len(ordered))


# Each statistic of a non-empty, sorted sequence of samples: WindowStats holds them all, a
# `Profiles` snapshot computes only the one it is asked to order by.
_STATISTIC = {
    Stat.MEDIAN: _median,
    Stat.MEAN: _mean,
    Stat.P95: _p95,
    Stat.MAX: _max,
    Stat.STDDEV: _stddev,
}


# A Stat member and its string are equal and hash alike: either finds the field.
_STAT_FIELDS = {stat.value: stat.value for stat in Stat}


# Slots: the registry may hold one of these per window (100,000 at 1,000 robots x 100
# deployments).
@dataclass(frozen=True, slots=True)
class WindowStats:
    """Statistics of one window at one moment. `stddev` is the population standard deviation."""

    count: int
    median: float
    mean: float
    p95: float
    max: float
    stddev: float
    last_at: float

    def value(self, stat: Stat | str) -> float:
        """The named statistic."""
        # A dict lookup first: this runs for every candidate of every robot in every round,
        # and converting to Stat costs several times more.
        name = _STAT_FIELDS.get(stat)
        return float(getattr(self, name if name is not None else Stat(stat).value))

    @classmethod
    def of(cls, samples: Iterable[float], last_at: float) -> WindowStats:
        """Statistics of a non-empty sequence of samples."""
        return cls.of_sorted(sorted(samples), last_at)

    @classmethod
    def of_sorted(cls, ordered: Sequence[float], last_at: float) -> WindowStats:
        """Statistics of a non-empty sequence of samples sorted in increasing order."""
        if not ordered:
            raise ValueError("WindowStats.of needs at least one sample")
        mean = _mean(ordered)
        return cls(
            count=len(ordered),
            median=_median(ordered),
            mean=mean,
            p95=_p95(ordered),
            max=_max(ordered),
            stddev=_stddev(ordered, mean),
            last_at=last_at,
        )


class LatencyWindow:
    """The last `size` latency samples (seconds) with cached statistics.

    The samples sit in a ring of C doubles (`array`), not a deque of float objects: the registry
    holds one window per robot x deployment x source (100,000 at 1,000 robots x 100
    deployments), and this is a fifth of the memory.
    """

    __slots__ = ("_last_at", "_next", "_ring", "_stats", "size")

    def __init__(self, size: int = DEFAULT_WINDOW) -> None:
        if size < 1:
            raise ValueError(f"window size must be at least 1, got {size}")
        self.size = size
        self._ring = array("d")  # grows to `size`, then the oldest is overwritten in place
        self._next = 0  # once full: where the next sample goes (the oldest)
        self._last_at: float | None = None
        self._stats: WindowStats | None = None

    def __len__(self) -> int:
        return len(self._ring)

    def add(self, sample_s: SupportsFloat, at: float) -> None:
        """Append one sample taken at time `at`; the oldest falls out when the window is full."""
        value = float(sample_s) if isinstance(sample_s, numbers.Real) else math.nan
        if not (math.isfinite(value) and value >= 0):
            # A NaN would poison every statistic of the window for its whole lifetime.
            raise ValueError(f"latency sample must be a finite number >= 0, got {sample_s!r}")
        if len(self._ring) < self.size:
            self._ring.append(value)
        else:
            self._ring[self._next] = value
            self._next = (self._next + 1) % self.size
        self._last_at = at
        self._stats = None

    def extend(self, samples: Iterable[SupportsFloat], at: float) -> None:
        """Append several samples (e.g. restored from the RIB) stamped with one time."""
        for sample in samples:
            self.add(sample, at)

    def samples(self) -> tuple[float, ...]:
        """The samples, oldest first."""
        ring, oldest = self._ring, self._next
        return tuple(ring[oldest:]) + tuple(ring[:oldest])

    def clear(self) -> None:
        """Forget every sample."""
        self._ring = array("d")
        self._next = 0
        self._last_at = None
        self._stats = None

    def stats(self) -> WindowStats | None:
        """Statistics of the current samples, or None for an empty window."""
        if self._last_at is None or not self._ring:
            return None
        if self._stats is None:
            self._stats = WindowStats.of(self._ring, self._last_at)
        return self._stats

    def sorted_samples(self) -> tuple[list[float], float] | None:
        """(the samples in increasing order, the time of the newest), or None when empty."""
        if self._last_at is None or not self._ring:
            return None
        return sorted(self._ring), self._last_at


WindowKey = tuple[str, str, Source]


class Profiles(Mapping[str, WindowStats]):
    """One robot's window statistics from one source, by deployment, at one moment.

    Immutable, so what is derived from it is computed once and kept with it: `ascending(stat)`,
    the deployments by increasing statistic, lets the scheduler visit the few deployments that
    could beat a limit instead of ranking them all. `LatencyWindows.profiles` hands out the same
    snapshot until one of the robot's windows of that source changes, and builds it from the
    windows' sorted samples: a deployment's `WindowStats` is made only when it is looked up
    (the scheduler looks up a few per robot; a robot probes 100 deployments every 2 s).
    """

    __slots__ = ("_ascending", "_bounds", "_flat", "_index", "_last_at", "_stats")

    def __init__(self, stats: Mapping[str, WindowStats] | None = None) -> None:
        self._stats: dict[str, WindowStats] = dict(stats) if stats is not None else {}
        # From windows: every deployment's sorted samples in one array (deployment i's are
        # flat[bounds[i]:bounds[i + 1]]) and their newest times in another. A robot's snapshot
        # lives for seconds: an object per deployment would reach the collector's oldest
        # generation by the hundred thousand at 1,000 robots and make its full passes frequent
        # (docs/scale.md); these are a few objects per robot.
        self._index: dict[str, int] = {}
        self._flat = array("d")
        self._bounds = array("q", [0])
        self._last_at = array("d")
        self._ascending: dict[Stat, tuple[array[float], tuple[str, ...]]] = {}

    @classmethod
    def of_samples(cls, samples: Iterable[tuple[str, tuple[Sequence[float], float]]]) -> Profiles:
        """From (deployment, (sorted non-empty samples, time of the newest)) pairs."""
        profiles = cls()
        for dep, (ordered, last_at) in samples:
            profiles._index[dep] = len(profiles._last_at)
            profiles._flat.extend(ordered)
            profiles._bounds.append(len(profiles._flat))
            profiles._last_at.append(last_at)
        return profiles

    def without(self, deployment: str) -> Profiles:
        """This snapshot less `deployment` (its windows were dropped): the others' sorted samples,
        statistics and orders as they are, nothing sorted again. A deployment that dies is in
        every robot's snapshot (every robot probes it); rebuilding them all made that round
        5 times a normal one at 1,000 robots (docs/scale.md)."""
        if deployment not in self._deployments():
            return self
        out = Profiles({dep: s for dep, s in self._stats.items() if dep != deployment})
        if self._index:
            i = self._index[deployment]
            lo, hi = self._bounds[i], self._bounds[i + 1]
            out._flat = self._flat[:lo] + self._flat[hi:]
            out._bounds = self._bounds[: i + 1] + array(
                "q", [bound - (hi - lo) for bound in self._bounds[i + 2 :]]
            )
            out._last_at = self._last_at[:i] + self._last_at[i + 1 :]
            out._index = {dep: j - (j > i) for dep, j in self._index.items() if dep != deployment}
        for stat, (values, ids) in self._ascending.items():
            k = ids.index(deployment)
            out._ascending[stat] = (values[:k] + values[k + 1 :], ids[:k] + ids[k + 1 :])
        return out

    def _ordered(self, i: int) -> array[float]:
        return self._flat[self._bounds[i] : self._bounds[i + 1]]

    def __getitem__(self, deployment: str) -> WindowStats:
        stats = self._stats.get(deployment)
        if stats is None:
            i = self._index[deployment]
            stats = WindowStats.of_sorted(self._ordered(i), self._last_at[i])
            self._stats[deployment] = stats
        return stats

    def _deployments(self) -> Mapping[str, object]:
        # Made from windows' samples (statistics then fill in as looked up) or from statistics.
        return self._index or self._stats

    def __contains__(self, deployment: object) -> bool:
        return deployment in self._deployments()

    def __iter__(self) -> Iterator[str]:
        return iter(self._deployments())

    def __len__(self) -> int:
        return len(self._deployments())

    def __repr__(self) -> str:
        return f"Profiles({dict(self)!r})"

    def ascending(self, stat: Stat | str) -> Iterator[tuple[float, str]]:
        """(value of `stat`, deployment) for every deployment, lowest value first (ties by id)."""
        stat = Stat(stat)
        order = self._ascending.get(stat)
        if order is None:
            if self._index:
                of = _STATISTIC[stat]
                pairs = sorted((of(self._ordered(i)), dep) for dep, i in self._index.items())
            else:
                pairs = sorted((stats.value(stat), dep) for dep, stats in self._stats.items())
            # Kept as an array and a tuple of ids: no object per deployment for the collector.
            # Filled on the control loop only; a second fill would compute the same.
            order = self._ascending[stat] = (
                array("d", (value for value, _ in pairs)),
                tuple(dep for _, dep in pairs),
            )
        return zip(*order, strict=True)


class LatencyWindows:
    """All windows of the registry, keyed by (robot, deployment, source).

    Indexed by robot and source, then deployment: a robot's profiles cost its own windows, not
    every window of the fleet (1,000 robots x 100 deployments is 100,000 probe windows), and no
    key object is kept per window (fewer objects for the garbage collector to walk). Each
    robot's `profiles` snapshot per source is kept until one of those windows may have changed:
    `window()` (the way to change one) and the drops discard it.
    """

    def __init__(self, size: int = DEFAULT_WINDOW) -> None:
        self.size = size
        self._windows: dict[tuple[str, Source], dict[str, LatencyWindow]] = {}
        self._snapshots: dict[tuple[str, Source], Profiles] = {}

    def window(self, robot: str, deployment: str, source: Source | str) -> LatencyWindow:
        """The window for this key, created empty on first use (the robot's snapshot of that
        source is dropped: the caller may change the window)."""
        key = (robot, Source(source))
        windows = self._windows.get(key)
        if windows is None:
            windows = self._windows[key] = {}
        win = windows.get(deployment)
        if win is None:
            win = windows[deployment] = LatencyWindow(self.size)
        self._snapshots.pop(key, None)
        return win

    def add(
        self, robot: str, deployment: str, source: Source | str, sample_s: SupportsFloat, at: float
    ) -> None:
        """Record one sample."""
        self.window(robot, deployment, source).add(sample_s, at)

    def _get(self, robot: str, deployment: str, source: Source | str) -> LatencyWindow | None:
        windows = self._windows.get((robot, Source(source)))
        return windows.get(deployment) if windows is not None else None

    def stats(self, robot: str, deployment: str, source: Source | str) -> WindowStats | None:
        """Statistics for this key, or None when nothing was recorded."""
        win = self._get(robot, deployment, source)
        return win.stats() if win is not None else None

    def samples(self, robot: str, deployment: str, source: Source | str) -> tuple[float, ...]:
        """The samples of this key, oldest first (empty when nothing was recorded)."""
        win = self._get(robot, deployment, source)
        return win.samples() if win is not None else ()

    def profiles(self, robot: str, source: Source | str = Source.PROBE) -> Profiles:
        """Per-deployment statistics of one robot from one source (the scheduler's input): the
        same snapshot as last time unless one of those windows changed since."""
        key = (robot, Source(source))
        snapshot = self._snapshots.get(key)
        if snapshot is None:
            samples = (
                (dep, entry)
                for dep, win in self._windows.get(key, {}).items()
                if (entry := win.sorted_samples()) is not None
            )
            snapshot = self._snapshots[key] = Profiles.of_samples(samples)
        return snapshot

    def drop_robot(self, robot: str) -> None:
        """Forget every window of a robot."""
        for source in Source:
            self._windows.pop((robot, source), None)
            self._snapshots.pop((robot, source), None)

    def drop_deployment(self, deployment: str) -> None:
        """Forget every window of a deployment (a restarted deployment starts fresh); the
        snapshots that held it lose it, the rest of each kept as it was."""
        for key, windows in self._windows.items():
            if windows.pop(deployment, None) is not None:
                snapshot = self._snapshots.get(key)
                if snapshot is not None:
                    self._snapshots[key] = snapshot.without(deployment)

    def items(self) -> Iterator[tuple[WindowKey, LatencyWindow]]:
        """Every (key, window) pair, e.g. to persist them in the RIB."""
        return iter(
            [
                ((robot, dep, source), win)
                for (robot, source), windows in self._windows.items()
                for dep, win in windows.items()
            ]
        )
