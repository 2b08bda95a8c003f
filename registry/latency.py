"""Latency windows: the last N samples per (robot, deployment, source) and their statistics.

The scheduler compares a statistic of a sliding window (median, mean, p95, max or stddev) against
the fleet's latency bound. Windows are small (20 samples by default), so statistics are computed by
sorting on demand and cached until the next sample: cheap enough to evaluate on every telemetry
message. Two sources feed windows: `telemetry` (frames the robot actually sent to its serving
deployment) and `probe` (the robot's low-rate probes of every deployment, standby included).

Both sources must measure the same thing (the remote part of a frame: transfer plus cloud time),
so that a probe profile and a telemetry window can be compared. Timestamps are in the scheduler's
clock.
"""

from __future__ import annotations

import math
import numbers
from collections import deque
from collections.abc import Iterable, Iterator
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


@dataclass(frozen=True)
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
        return float(getattr(self, Stat(stat).value))

    @classmethod
    def of(cls, samples: Iterable[float], last_at: float) -> WindowStats:
        """Statistics of a non-empty sequence of samples."""
        ordered = sorted(samples)
        n = len(ordered)
        if n == 0:
            raise ValueError("WindowStats.of needs at least one sample")
        mid = n // 2
        median = ordered[mid] if n % 2 else (ordered[mid - 1] + ordered[mid]) / 2
        mean = math.fsum(ordered) / n
        # Nearest-rank p95: the smallest sample with at least 95 % of the window at or below it.
        p95 = ordered[max(0, math.ceil(P95_QUANTILE * n) - 1)]
        variance = math.fsum((x - mean) ** 2 for x in ordered) / n
        return cls(
            count=n,
            median=median,
            mean=mean,
            p95=p95,
            max=ordered[-1],
            stddev=math.sqrt(variance),
            last_at=last_at,
        )


class LatencyWindow:
    """The last `size` latency samples (seconds) with cached statistics."""

    def __init__(self, size: int = DEFAULT_WINDOW) -> None:
        if size < 1:
            raise ValueError(f"window size must be at least 1, got {size}")
        self.size = size
        self._samples: deque[float] = deque(maxlen=size)
        self._last_at: float | None = None
        self._stats: WindowStats | None = None

    def __len__(self) -> int:
        return len(self._samples)

    def add(self, sample_s: SupportsFloat, at: float) -> None:
        """Append one sample taken at time `at`; the oldest falls out when the window is full."""
        value = float(sample_s) if isinstance(sample_s, numbers.Real) else math.nan
        if not (math.isfinite(value) and value >= 0):
            # A NaN would poison every statistic of the window for its whole lifetime.
            raise ValueError(f"latency sample must be a finite number >= 0, got {sample_s!r}")
        self._samples.append(value)
        self._last_at = at
        self._stats = None

    def extend(self, samples: Iterable[SupportsFloat], at: float) -> None:
        """Append several samples (e.g. restored from the RIB) stamped with one time."""
        for sample in samples:
            self.add(sample, at)

    def samples(self) -> tuple[float, ...]:
        """The samples, oldest first."""
        return tuple(self._samples)

    def clear(self) -> None:
        """Forget every sample."""
        self._samples.clear()
        self._last_at = None
        self._stats = None

    def stats(self) -> WindowStats | None:
        """Statistics of the current samples, or None for an empty window."""
        if self._last_at is None or not self._samples:
            return None
        if self._stats is None:
            self._stats = WindowStats.of(self._samples, self._last_at)
        return self._stats


WindowKey = tuple[str, str, Source]


class LatencyWindows:
    """All windows of the registry, keyed by (robot, deployment, source)."""

    def __init__(self, size: int = DEFAULT_WINDOW) -> None:
        self.size = size
        self._windows: dict[WindowKey, LatencyWindow] = {}

    def window(self, robot: str, deployment: str, source: Source | str) -> LatencyWindow:
        """The window for this key, created empty on first use."""
        key = (robot, deployment, Source(source))
        win = self._windows.get(key)
        if win is None:
            win = self._windows[key] = LatencyWindow(self.size)
        return win

    def add(
        self, robot: str, deployment: str, source: Source | str, sample_s: SupportsFloat, at: float
    ) -> None:
        """Record one sample."""
        self.window(robot, deployment, source).add(sample_s, at)

    def stats(self, robot: str, deployment: str, source: Source | str) -> WindowStats | None:
        """Statistics for this key, or None when nothing was recorded."""
        win = self._windows.get((robot, deployment, Source(source)))
        return win.stats() if win is not None else None

    def profiles(self, robot: str, source: Source | str = Source.PROBE) -> dict[str, WindowStats]:
        """Per-deployment statistics of one robot from one source (the scheduler's input)."""
        out: dict[str, WindowStats] = {}
        source = Source(source)
        for (r, dep, src), win in self._windows.items():
            stats = win.stats()
            if r == robot and src == source and stats is not None:
                out[dep] = stats
        return out

    def drop_robot(self, robot: str) -> None:
        """Forget every window of a robot."""
        for key in [k for k in self._windows if k[0] == robot]:
            del self._windows[key]

    def drop_deployment(self, deployment: str) -> None:
        """Forget every window of a deployment (a restarted deployment starts fresh)."""
        for key in [k for k in self._windows if k[1] == deployment]:
            del self._windows[key]

    def items(self) -> Iterator[tuple[WindowKey, LatencyWindow]]:
        """Every (key, window) pair, e.g. to persist them in the RIB."""
        return iter(list(self._windows.items()))
