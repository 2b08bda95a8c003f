"""Latency windows and the latency bound the scheduler reads them against."""

from __future__ import annotations

import math
import random
import statistics

import numpy as np
import pytest

from common.errors import UserError
from registry.latency import LatencyBound, LatencyWindow, LatencyWindows, Source, Stat, WindowStats


def test_each_statistic_on_a_known_window() -> None:
    win = LatencyWindow(size=5)
    for i, sample in enumerate([0.05, 0.01, 0.04, 0.02, 0.03]):
        win.add(sample, at=float(i))
    stats = win.stats()
    assert stats is not None
    assert stats.count == 5
    assert stats.median == pytest.approx(0.03)
    assert stats.mean == pytest.approx(0.03)
    assert stats.max == pytest.approx(0.05)
    assert stats.p95 == pytest.approx(0.05)  # nearest rank: ceil(0.95 * 5) = 5th smallest
    assert stats.stddev == pytest.approx(math.sqrt(0.0002))  # population stddev
    assert stats.last_at == 4.0
    assert stats.value(Stat.MEDIAN) == stats.value("median") == stats.median


def test_statistics_agree_with_reference_implementations() -> None:
    rng = random.Random(7)
    for n in (1, 2, 3, 19, 20):
        samples = [rng.lognormvariate(-3, 0.5) for _ in range(n)]
        stats = WindowStats.of(samples, last_at=0.0)
        assert stats.median == pytest.approx(statistics.median(samples))
        assert stats.mean == pytest.approx(statistics.fmean(samples))
        assert stats.stddev == pytest.approx(statistics.pstdev(samples))
        assert stats.max == max(samples)
        assert stats.p95 == pytest.approx(np.percentile(samples, 95, method="inverted_cdf"))


def test_p95_of_twenty_samples_is_the_nineteenth_smallest() -> None:
    stats = WindowStats.of([float(i) for i in range(1, 21)], last_at=0.0)
    assert stats.p95 == 19.0


def test_window_slides_and_cache_follows_new_samples() -> None:
    win = LatencyWindow(size=3)
    assert win.stats() is None
    for i, s in enumerate([1.0, 2.0, 3.0]):
        win.add(s, at=float(i))
    first = win.stats()
    assert first is not None and first.max == 3.0
    assert win.stats() is first  # cached until the next sample
    win.add(0.5, at=3.0)
    after = win.stats()
    assert after is not None
    assert win.samples() == (2.0, 3.0, 0.5)
    assert (after.count, after.median, after.last_at) == (3, 2.0, 3.0)
    win.clear()
    assert win.stats() is None and len(win) == 0


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -0.001, "0.1", None])
def test_bad_samples_are_refused(bad: object) -> None:
    win = LatencyWindow()
    with pytest.raises(ValueError, match="finite number >= 0"):
        win.add(bad, at=0.0)  # type: ignore[arg-type]
    assert len(win) == 0


def test_numpy_scalars_are_accepted() -> None:
    win = LatencyWindow()
    win.add(np.float32(0.25), at=0.0)
    win.add(np.int64(1), at=1.0)
    assert win.samples() == (0.25, 1.0)


def test_windows_table_keys_profiles_and_drops() -> None:
    table = LatencyWindows(size=4)
    table.add("r1", "edge-1", Source.PROBE, 0.02, at=1.0)
    table.add("r1", "edge-2", Source.PROBE, 0.03, at=1.0)
    table.add("r1", "edge-1", Source.TELEMETRY, 0.5, at=1.0)
    table.add("r2", "edge-1", Source.PROBE, 0.9, at=1.0)
    assert set(table.profiles("r1")) == {"edge-1", "edge-2"}
    assert table.profiles("r1")["edge-1"].median == 0.02
    assert set(table.profiles("r1", Source.TELEMETRY)) == {"edge-1"}
    assert table.stats("r1", "edge-3", Source.PROBE) is None
    table.drop_deployment("edge-1")
    assert set(table.profiles("r1")) == {"edge-2"}
    table.drop_robot("r1")
    assert table.profiles("r1") == {}
    assert [key for key, _ in table.items()] == []


def test_bound_accepts_config_strings_and_has_defaults() -> None:
    bound = LatencyBound(stat="p95", seconds=0.1)
    assert bound.stat is Stat.P95
    assert (bound.window, bound.hysteresis_s, bound.better_margin) == (20, 1.0, 0.2)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"stat": "p99", "seconds": 0.1}, "latency_bound.stat: unknown statistic 'p99'"),
        ({"stat": "median", "seconds": 0.0}, "latency_bound.seconds"),
        ({"stat": "median", "seconds": float("nan")}, "latency_bound.seconds"),
        ({"stat": "median", "seconds": 0.1, "window": 0}, "latency_bound.window"),
        ({"stat": "median", "seconds": 0.1, "hysteresis_s": -1.0}, "latency_bound.hysteresis_s"),
        ({"stat": "median", "seconds": 0.1, "better_margin": 1.0}, "latency_bound.better_margin"),
    ],
)
def test_bad_bound_is_a_user_error_naming_the_field(
    kwargs: dict[str, object], message: str
) -> None:
    with pytest.raises(UserError, match=message):
        LatencyBound(**kwargs)  # type: ignore[arg-type]
