"""Round-robin pools: who joins a robot's pool, the switch protocol's pool steps, the RIB's
pool column (and its migration), the wire's pool field, and the robot's turn order."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest

from common.config import fleet_from_dict
from common.errors import UserError
from common.wire import decode
from common.wire.codec import InvalidValue
from common.wire.registry import DeploymentState, RouteChange
from registry.pool_keeper import PoolKeeper
from registry.pools import PoolPlanner, pool_planner
from registry.rib import SCHEMA_VERSION, Rib
from registry.switch import Switcher
from robotd.frame_path.pool_turns import PoolTurns
from tests.unit.test_switch import ROBOT, FakeTransport, _fleet

SERVICE = "detect"


@pytest.fixture
def rib(tmp_path: Path) -> Iterator[Rib]:
    with Rib(tmp_path / "rib.sqlite") as r:
        for name in ("a", "b", "c"):
            r.upsert_deployment(
                name, service=SERVICE, model_digest="sha256:aa", capacity=4, version="0.1.0"
            )
        r.upsert_robot(ROBOT, service=SERVICE)
        yield r


def _switcher(rib: Rib, transport: FakeTransport, limit: int) -> Switcher:
    return Switcher(rib, transport, pools=PoolPlanner(rib, SERVICE, limit))


def _states(rib: Rib) -> dict[str, tuple[DeploymentState, int]]:
    return {s.deployment: (s.state, s.epoch) for s in rib.deployment_states(robot=ROBOT)}


def test_a_switch_puts_the_whole_pool_in_service_at_one_epoch(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    result = _switcher(rib, transport, 3).switch(ROBOT, ["b"], reason="initial")
    assert result.changed and result.deployment == "b"
    route = rib.route(ROBOT)
    assert route is not None and route.pool == ("b", "a", "c")  # the primary first
    assert [(c.deployment, c.pool, c.epoch) for c in transport.published] == [
        ("b", ("b", "a", "c"), result.epoch)
    ]
    assert {name: d.states[ROBOT] for name, d in deps.items()} == {
        n: DeploymentState.SERVICE for n in "abc"
    }
    assert {e for _, e in _states(rib).values()} == {result.epoch}


def test_pool_size_limits_the_members_and_spreads_robots(rib: Rib) -> None:
    transport, _ = _fleet(rib)
    rib.upsert_robot("robot-2", service=SERVICE)
    switcher = _switcher(rib, transport, 2)
    switcher.switch(ROBOT, ["a"], reason="initial")
    switcher.switch("robot-2", ["a"], reason="initial")
    pools = {r.robot: r.pool for r in rib.routes()}
    # b already serves robot-1's pool: robot-2's second member is the idle c.
    assert pools == {ROBOT: ("a", "b"), "robot-2": ("a", "c")}


def test_a_member_that_does_not_acknowledge_is_left_out_and_fenced(rib: Rib) -> None:
    transport, _ = _fleet(rib, c="refuse")
    _switcher(rib, transport, 0).switch(ROBOT, ["a"], reason="initial")
    route = rib.route(ROBOT)
    assert route is not None and route.pool == ("a", "b")
    assert [e.deployment for e in rib.events(kind="ack_failed")] == ["c"]
    assert ("ctl", "c", "standby") in [entry[:3] for entry in transport.log]


def test_a_dead_member_is_dropped_and_a_standby_joins(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    planner = PoolPlanner(rib, SERVICE, 2)
    switcher = Switcher(rib, transport, pools=planner)
    switcher.switch(ROBOT, ["a"], reason="initial")
    route = rib.route(ROBOT)
    assert route is not None and route.pool == ("a", "b")
    assert not planner.needs_repool(
        route, planner.usable(rib.deployments())
    )  # full and alive: left alone

    rib.set_deployment_alive("b", False, "token gone")
    assert planner.needs_repool(route, planner.usable(rib.deployments()))
    result = switcher.repool(ROBOT, reason="pool member gone")
    after = rib.route(ROBOT)
    assert result.changed and after is not None
    assert (after.deployment, after.pool) == ("a", ("a", "c"))
    assert after.epoch > route.epoch
    assert transport.published[-1].pool == ("a", "c")
    assert deps["c"].states[ROBOT] is DeploymentState.SERVICE
    # b was dead: recorded as standby, not asked.
    assert _states(rib)["b"] == (DeploymentState.STANDBY, after.epoch)
    assert not planner.needs_repool(after, planner.usable(rib.deployments()))


def test_a_short_pool_grows_when_a_deployment_comes(rib: Rib) -> None:
    transport, _ = _fleet(rib)
    rib.set_deployment_alive("c", False, "not up yet")
    planner = PoolPlanner(rib, SERVICE, 0)
    switcher = Switcher(rib, transport, pools=planner)
    switcher.switch(ROBOT, ["a"], reason="initial")
    route = rib.route(ROBOT)
    assert route is not None and route.pool == ("a", "b")
    rib.upsert_deployment(
        "c", service=SERVICE, model_digest="sha256:aa", capacity=4, version="0.1.0"
    )
    assert planner.needs_repool(route, planner.usable(rib.deployments()))
    switcher.repool(ROBOT)
    after = rib.route(ROBOT)
    assert after is not None and after.pool == ("a", "b", "c")


def test_moving_the_primary_stands_down_old_members_outside_the_new_pool(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    switcher = _switcher(rib, transport, 2)
    switcher.switch(ROBOT, ["a"], reason="initial")  # pool a, b
    rib.set_deployment_alive("a", False, "token gone")
    deps["a"].mode = "timeout"
    result = switcher.switch(ROBOT, ["c"], reason="deployment_lost")
    after = rib.route(ROBOT)
    assert result.changed and after is not None and after.pool == ("c", "b")
    assert deps["b"].states[ROBOT] is DeploymentState.SERVICE
    assert deps["b"].epochs[ROBOT] == after.epoch


def test_repool_without_the_primary_acknowledging_changes_nothing(rib: Rib) -> None:
    transport, deps = _fleet(rib)
    switcher = _switcher(rib, transport, 2)
    switcher.switch(ROBOT, ["a"], reason="initial")
    before = rib.route(ROBOT)
    deps["a"].mode = "timeout"
    result = switcher.repool(ROBOT)
    assert not result.changed
    assert rib.route(ROBOT) == before


def test_anycast_fleets_have_no_pool(rib: Rib) -> None:
    transport, _ = _fleet(rib)
    Switcher(rib, transport).switch(ROBOT, ["a"], reason="initial")
    route = rib.route(ROBOT)
    assert route is not None and route.pool == ()
    assert transport.published[-1].pool == ()


def test_the_rib_keeps_pools_across_a_restart_and_migrates_version_1(tmp_path: Path) -> None:
    path = tmp_path / "rib.sqlite"
    with Rib(path) as r:
        r.upsert_robot(ROBOT, service=SERVICE)
        r.set_route(ROBOT, "a", r.reserve_epoch(ROBOT), "initial", pool=("a", "b"))
    with Rib(path) as r:
        assert r.pool(ROBOT) == ("a", "b")
        [(_, live_route)] = r.live_robots()
        assert live_route is not None and live_route.pool == ("a", "b")
        with pytest.raises(ValueError, match="must start with"):
            r.set_route(ROBOT, "a", r.reserve_epoch(ROBOT), pool=("b", "a"))
    # A version-1 file (no pool column) is brought to the current version when opened.
    old = tmp_path / "v1.sqlite"
    with Rib(old) as r:
        r.upsert_robot(ROBOT, service=SERVICE)
        r.set_route(ROBOT, "a", r.reserve_epoch(ROBOT), "initial")
    conn = sqlite3.connect(old)
    conn.execute("ALTER TABLE routes DROP COLUMN pool")
    conn.execute("PRAGMA user_version = 1")
    conn.commit()
    conn.close()
    with Rib(old) as r:
        route = r.route(ROBOT)
        assert route is not None and (route.deployment, route.pool) == ("a", ())
    conn = sqlite3.connect(old)
    assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    conn.close()


def test_the_route_message_carries_the_pool_and_checks_it() -> None:
    change = RouteChange(robot=ROBOT, deployment="a", epoch=3, reason="x", at=1.0, pool=("a", "b"))
    assert decode(change.to_wire(), expect=RouteChange) == change
    for bad, problem in (
        (("b", "a"), "must start with"),
        (("a", "a"), "twice"),
        (("a", "b/c"), "'/'"),
    ):
        with pytest.raises(InvalidValue, match=problem):
            RouteChange(robot=ROBOT, deployment="a", epoch=3, reason="x", at=1.0, pool=bad)


def _fleet_cfg(dispatch: object) -> dict[str, object]:
    return {
        "service": SERVICE,
        "model": "zoo:stereo",
        "deadline_s": 1.0,
        "latency_bound": {"seconds": 0.3},
        "dispatch": dispatch,
    }


def test_dispatch_config_forms_and_errors(tmp_path: Path) -> None:
    with Rib(tmp_path / "r.sqlite") as r:
        assert pool_planner(fleet_from_dict(_fleet_cfg("anycast")), r) is None
        short = pool_planner(fleet_from_dict(_fleet_cfg("round_robin")), r)
        assert short is not None and short.limit == 0  # every live deployment
        sized = pool_planner(
            fleet_from_dict(_fleet_cfg({"mode": "round_robin", "pool_size": 3})), r
        )
        assert sized is not None and sized.limit == 3
    with pytest.raises(UserError, match="pool_size: only for mode round_robin"):
        fleet_from_dict(_fleet_cfg({"mode": "anycast", "pool_size": 2}))
    with pytest.raises(UserError, match=r"dispatch\.mode"):
        fleet_from_dict(_fleet_cfg("round_robn"))


def test_the_robot_takes_the_members_in_turn() -> None:
    turns = PoolTurns()
    pool = ("a", "b", "c")
    assert [turns.next(pool) for _ in range(7)] == ["a", "b", "c", "a", "b", "c", "a"]
    assert turns.next(("a",)) is None and turns.next(()) is None  # the anycast key


def test_the_keeper_rebuilds_a_robot_s_pool_at_most_once_per_retry_interval(rib: Rib) -> None:
    transport, _ = _fleet(rib)
    switcher = _switcher(rib, transport, 2)
    switcher.switch(ROBOT, ["a"], reason="initial")
    now = [0.0]
    keeper = PoolKeeper(switcher, retry_s=2.0, clock=lambda: now[0])
    rib.set_deployment_alive("b", False, "token gone")
    keeper.rebuild(ROBOT, "pool member gone")
    first = rib.route(ROBOT)
    assert first is not None and first.pool == ("a", "c")
    rib.set_deployment_alive("c", False, "token gone")
    keeper.tend(first, keeper.planner.usable(rib.deployments()))
    assert rib.route(ROBOT) == first  # within the interval: not rebuilt again
    now[0] = 2.0
    keeper.tend(first, keeper.planner.usable(rib.deployments()))
    after = rib.route(ROBOT)
    assert after is not None and after.pool == ("a",)
