"""Probe profiles as the scheduler takes them: one snapshot per robot and source, kept until one
of its windows changes (so what the scheduler derives from it is computed once per change, not
once per round), statistics made only when looked up and equal to a window's own, deployments
listed by ascending statistic; windows hold their samples in a ring."""

from __future__ import annotations

import random

import pytest

from registry.latency import LatencyWindow, LatencyWindows, Profiles, Source, Stat, WindowStats


def test_the_snapshot_is_kept_until_one_of_its_windows_changes() -> None:
    table = LatencyWindows(size=4)
    table.add("r1", "edge-1", Source.PROBE, 0.02, at=1.0)
    table.add("r1", "edge-2", Source.PROBE, 0.03, at=1.0)
    first = table.profiles("r1")
    assert table.profiles("r1") is first
    table.add("r1", "edge-1", Source.TELEMETRY, 0.5, at=2.0)
    table.add("r2", "edge-1", Source.PROBE, 0.9, at=2.0)
    assert table.profiles("r1") is first, "another source or robot changes nothing here"
    table.add("r1", "edge-2", Source.PROBE, 0.05, at=2.0)
    second = table.profiles("r1")
    assert second is not first
    assert second["edge-2"].median == pytest.approx(0.04)
    assert first["edge-2"].median == 0.03, "an old snapshot does not change under its holder"
    table.drop_deployment("edge-1")
    assert set(table.profiles("r1")) == {"edge-2"}
    table.drop_robot("r1")
    assert table.profiles("r1") == {}


def test_lazy_statistics_equal_the_windows_own() -> None:
    table = LatencyWindows(size=5)
    for i, value in enumerate([0.09, 0.01, 0.05, 0.05, 0.3, 0.02]):
        table.add("r1", "edge-1", Source.PROBE, value, at=float(i))
    window = table.window("r1", "edge-1", Source.PROBE)
    assert table.profiles("r1")["edge-1"] == window.stats()
    assert window.samples() == (0.01, 0.05, 0.05, 0.3, 0.02), "oldest first, the first fell out"


@pytest.mark.parametrize("stat", list(Stat))
def test_ascending_orders_by_the_statistic_then_by_id(stat: Stat) -> None:
    stats = {
        "edge-b": WindowStats.of([0.02, 0.04], last_at=0.0),
        "edge-a": WindowStats.of([0.02, 0.04], last_at=0.0),
        "edge-c": WindowStats.of([0.01], last_at=0.0),
    }
    profiles = Profiles(stats)
    expected = sorted((s.value(stat), dep) for dep, s in stats.items())
    assert list(profiles.ascending(stat)) == expected
    assert [dep for _, dep in profiles.ascending(Stat.MEDIAN)] == ["edge-c", "edge-a", "edge-b"]


def test_a_window_ring_keeps_the_last_samples_in_order_and_clears() -> None:
    window = LatencyWindow(3)
    window.extend([1.0, 2.0, 3.0, 4.0, 5.0], at=9.0)
    assert window.samples() == (3.0, 4.0, 5.0) and len(window) == 3
    entry = window.sorted_samples()
    assert entry is not None and (list(entry[0]), entry[1]) == ([3.0, 4.0, 5.0], 9.0)
    window.clear()
    assert window.samples() == () and window.stats() is None and window.sorted_samples() is None
    window.add(7.0, at=10.0)
    assert window.samples() == (7.0,)


@pytest.mark.parametrize("stat", list(Stat))
@pytest.mark.parametrize("full", [True, False], ids=["full windows", "some windows filling"])
def test_a_snapshot_sorted_at_once_agrees_with_each_window_to_the_bit(
    stat: Stat, full: bool
) -> None:
    """The snapshot sorts all of a robot's windows in one call and picks order statistics from
    them at once: every deployment's statistics, and the order by any statistic, are exactly
    those of its window on its own (ties included: equal windows rank by id)."""
    rng = random.Random(5)
    table = LatencyWindows(size=20)
    values = {}
    for d in range(40):
        count = 20 if full or d % 3 else rng.randint(1, 19)
        # Rounded to the millisecond so that equal statistics (ties) do occur.
        samples = [round(rng.uniform(0.01, 0.2), 3) for _ in range(count + 7 * full)]
        for i, x in enumerate(samples):
            table.add("r1", f"edge-{d:02d}", Source.PROBE, x, at=float(i))
        window = table.window("r1", f"edge-{d:02d}", Source.PROBE)
        values[f"edge-{d:02d}"] = window.stats()
    profiles = table.profiles("r1")
    expected = sorted((s.value(stat), dep) for dep, s in values.items() if s is not None)
    assert list(profiles.ascending(stat)) == expected
    assert {dep: profiles[dep] for dep in profiles} == values


def _filled(size: int, deployments: list[str], seed: int) -> LatencyWindows:
    rng = random.Random(seed)
    table = LatencyWindows(size=size)
    for d, dep in enumerate(deployments):
        for i in range(rng.randint(1, size + 5) if d % 2 else size + 3):
            table.add("r1", dep, Source.PROBE, round(rng.uniform(0.01, 0.2), 3), at=float(i))
    return table


@pytest.mark.parametrize("dropped", ["edge-00", "edge-07", "edge-13"])
def test_a_dropped_deployment_leaves_each_snapshot_as_if_built_without_it(dropped: str) -> None:
    """Every robot's snapshot holds a deployment that dies: dropping it keeps the rest of the
    snapshot (nothing sorted again) and gives what a snapshot built without it gives, the
    orders already computed included; a holder of the old snapshot sees no change."""
    deps = [f"edge-{d:02d}" for d in range(14)]
    table = _filled(6, deps, seed=3)
    before = table.profiles("r1")
    orders = {stat: list(before.ascending(stat)) for stat in (Stat.MEDIAN, Stat.P95)}
    looked_up = {dep: before[dep] for dep in deps[::3]}  # statistics made lazily, kept
    table.drop_deployment(dropped)
    after = table.profiles("r1")
    assert set(after) == set(deps) - {dropped} and len(after) == len(deps) - 1
    own = {dep: stats for dep in after if (stats := table.window("r1", dep, Source.PROBE).stats())}
    assert {dep: after[dep] for dep in after} == own
    for stat in Stat:  # median and p95 from the kept orders, the others computed anew
        assert list(after.ascending(stat)) == sorted((s.value(stat), dep) for dep, s in own.items())
    assert list(before.ascending(Stat.MEDIAN)) == orders[Stat.MEDIAN], "the old one is unchanged"
    assert all(before[dep] == stats for dep, stats in looked_up.items()) and dropped in before
