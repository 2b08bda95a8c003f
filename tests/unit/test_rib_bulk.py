"""The RIB's reads and writes in bulk: a scheduling round reads the live robots with their
routes in one query; profile windows and deployment loads are written many in one transaction
(one transaction per window took seconds at 100,000 windows)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest

from registry.rib import Rib, RibRouteRow


@pytest.fixture
def rib(tmp_path: Path) -> Iterator[Rib]:
    with Rib(tmp_path / "rib.sqlite", clock=lambda: 1_700_000_000.0) as opened:
        yield opened


def test_live_robots_come_with_their_routes_and_the_gone_ones_do_not(rib: Rib) -> None:
    for robot in ("robot-1", "robot-2", "robot-3"):
        rib.upsert_robot(robot, service="detect")
    rib.upsert_deployment("edge-1", service="detect", model_digest="d", capacity=4, version="1")
    rib.set_route("robot-1", "edge-1", rib.reserve_epoch("robot-1"), reason="initial")
    rib.reserve_epoch("robot-2")  # an epoch reserved is no route yet
    rib.set_robot_alive("robot-3", False, "gone")
    live = rib.live_robots()
    assert [(row.id, route) for row, route in live] == [
        ("robot-1", RibRouteRow("robot-1", "edge-1", 1, 1_700_000_000.0)),
        ("robot-2", None),
    ]
    assert all(row.alive and row.service == "detect" for row, _ in live)


def test_profiles_are_saved_many_at_once_and_read_back(rib: Rib) -> None:
    rows = [(f"robot-{i}", "edge-1", "probe", (0.01 * i, 0.02), 5.0) for i in range(1, 4)]
    assert rib.save_profiles(rows) == 3
    assert rib.save_profiles([("robot-1", "edge-1", "probe", (0.5,), None)]) == 1
    saved = {p.robot: (p.samples, p.updated_at) for p in rib.profiles()}
    assert saved["robot-1"] == ((0.5,), 1_700_000_000.0), "a later save replaces the window"
    assert saved["robot-3"] == ((0.03, 0.02), 5.0)


def test_a_bad_sample_writes_none_of_the_batch(rib: Rib) -> None:
    rows = [
        ("robot-1", "edge-1", "probe", (0.01,), None),
        ("robot-2", "edge-1", "probe", (math.nan,), None),
    ]
    with pytest.raises(ValueError, match="robot-2/edge-1 must be finite numbers >= 0"):
        rib.save_profiles(rows)
    assert rib.profiles() == []


def test_loads_are_written_for_live_deployments_that_changed(rib: Rib) -> None:
    for dep in ("edge-1", "edge-2", "edge-3"):
        rib.upsert_deployment(dep, service="detect", model_digest="d", capacity=4, version="1")
    rib.set_deployment_alive("edge-3", False, "gone")
    changed = rib.update_deployment_loads(
        {"edge-1": (2, None), "edge-2": (0, 4), "edge-3": (1, 4), "edge-9": (1, 1)}
    )
    assert changed == 1, "edge-2 is unchanged, edge-3 is gone, edge-9 is unknown"
    loads = {row.id: (row.load, row.capacity) for row in rib.deployments()}
    assert loads == {"edge-1": (2, 4), "edge-2": (0, 4), "edge-3": (0, 4)}
    with pytest.raises(ValueError, match="load of edge-1"):
        rib.update_deployment_loads({"edge-1": (-1, None)})
