"""The scheduler's search for a staying robot's target: `_Targets.best` (deployments by ascending
probe statistic, stopping as soon as none can come first) finds exactly the first of the full
ranking (`_Targets.ranked`), on random fleets with ties, thin and stale profiles, full, draining,
dead, penalized and foreign deployments. Guards the fast path that keeps a round of 1,000
robots x 100 deployments in tens of milliseconds from ever choosing differently."""

from __future__ import annotations

import random

import pytest

from registry.latency import LatencyBound, Profiles, Stat, WindowStats
from registry.scheduler import (
    DeploymentTable,
    DeploymentView,
    RobotView,
    Scheduler,
    SchedulerParams,
    _Targets,
)

SERVICE = "detect"
NOW = 1000.0
# Few distinct values, so that predictions tie and the order falls to utilization, then id.
LATENCIES_S = (0.02, 0.04, 0.05, 0.08, 0.1, 0.12, 0.3)


def _fleet(rng: random.Random) -> tuple[DeploymentTable, Profiles, set[str]]:
    views, stats, penalized = [], {}, set()
    for j in range(rng.randint(1, 14)):
        dep = f"dep-{j:02d}"
        capacity = rng.choice((0, 4, 8))
        views.append(
            DeploymentView(
                id=dep,
                service=SERVICE if rng.random() < 0.9 else "other",
                alive=rng.random() < 0.9,
                draining=rng.random() < 0.1,
                load=rng.randint(0, capacity) if capacity else 0,
                capacity=capacity,
                model_digest=rng.choice((None, "a", "b")),
            )
        )
        if rng.random() < 0.85:
            count = rng.randint(1, 6)  # below min_probe_samples (3): a thin profile
            age_s = rng.choice((0.5, 3.0, 30.0))  # 30 s: older than profile_max_age_s
            samples = [rng.choice(LATENCIES_S) for _ in range(count)]
            stats[dep] = WindowStats.of(samples, last_at=NOW - age_s)
        if rng.random() < 0.15:
            penalized.add(dep)
    return DeploymentTable(views), Profiles(stats), penalized


@pytest.mark.parametrize("stat", [Stat.MEDIAN, Stat.P95, Stat.MEAN])
def test_best_is_the_first_of_the_full_ranking(stat: Stat) -> None:
    rng = random.Random(stat.value)
    bound = LatencyBound(stat=stat, seconds=0.1)
    sched = Scheduler(bound, SchedulerParams(load_weight=rng.choice((0.0, 1.0))), clock=lambda: NOW)
    compared = 0
    for case in range(400):
        table, profiles, penalized = _fleet(rng)
        st = sched.memory.state(f"robot-{case}")
        st.left_at = dict.fromkeys(penalized, NOW - 1.0)
        current = rng.choice(table.views)
        robot = RobotView(
            id=f"robot-{case}",
            service=SERVICE,
            route=current.id,
            model_digest=rng.choice((None, "a")),
        )
        targets = _Targets(sched, robot, current, table, profiles, st, NOW)
        for limit in (0.0, 0.03, 0.05, 0.09, 0.1, 0.2, 1.0):
            for max_tier in (0, 1):
                ranked = targets.ranked(limit, max_tier)
                best = targets.best(limit, max_tier)
                first = ranked[0].deployment.id if ranked else None
                assert (best.deployment.id if best else None) == first, (case, limit, max_tier)
                compared += first is not None
    assert compared > 100, "the random fleets must offer targets often enough to mean something"


def test_a_table_and_a_list_of_deployments_decide_alike() -> None:
    views = [
        DeploymentView(id="edge-1", service=SERVICE),
        DeploymentView(id="edge-2", service=SERVICE, load=1, capacity=4),
    ]
    profiles = {
        "edge-1": WindowStats.of([0.05] * 5, last_at=NOW),
        "edge-2": WindowStats.of([0.02] * 5, last_at=NOW),
    }
    bound = LatencyBound(stat=Stat.MEDIAN, seconds=0.1)
    robot = RobotView(id="robot-1", service=SERVICE, route=None)
    from_list = Scheduler(bound, clock=lambda: NOW).evaluate(robot, views, profiles)
    from_table = Scheduler(bound, clock=lambda: NOW).evaluate(
        robot, DeploymentTable(views), Profiles(profiles)
    )
    assert from_list == from_table
    # Both meet the bound: a first placement goes where there is most room (edge-1 reports none).
    assert from_list is not None and from_list.candidates == ("edge-1", "edge-2")
