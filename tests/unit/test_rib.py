"""The routing information base: schema, views, events, epochs, and restore after a restart."""

from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path

import pytest

from common.errors import UserError
from registry import rib_events as rib_module
from registry.rib import SCHEMA_VERSION, DeploymentState, EventKind, Rib


class FakeWallClock:
    """Wall clock that only moves when told to."""

    def __init__(self, start: float = 1_700_000_000.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> FakeWallClock:
    return FakeWallClock()


@pytest.fixture
def rib_path(tmp_path: Path) -> Path:
    return tmp_path / "state" / "rib.sqlite"


def _fleet(rib: Rib) -> None:
    rib.upsert_deployment(
        "edge-1", service="detect", model_digest="sha256:aa", capacity=4, version="0.1.0"
    )
    rib.upsert_deployment(
        "edge-2", service="detect", model_digest="sha256:aa", capacity=2, version="0.1.0", load=1
    )
    rib.upsert_robot("robot-1", service="detect")


def test_fresh_file_gets_versioned_schema_in_wal_mode(rib_path: Path) -> None:
    with Rib(rib_path):
        pass
    conn = sqlite3.connect(rib_path)
    try:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    finally:
        conn.close()
    assert {"deployments", "deployment_states", "robots", "routes", "profiles", "events"} <= tables


def test_unknown_schema_version_is_refused_naming_file_and_version(rib_path: Path) -> None:
    rib_path.parent.mkdir(parents=True)
    conn = sqlite3.connect(rib_path)
    conn.execute("CREATE TABLE routes (robot TEXT)")
    conn.execute("PRAGMA user_version = 99")
    conn.commit()
    conn.close()
    with pytest.raises(UserError, match=r"rib\.sqlite: RIB schema version 99 is not supported"):
        Rib(rib_path)


def test_garbage_file_is_refused_as_not_a_rib(rib_path: Path) -> None:
    rib_path.parent.mkdir(parents=True)
    rib_path.write_bytes(b"definitely not sqlite " * 100)
    with pytest.raises(UserError, match="is not an elasticfog RIB"):
        Rib(rib_path)


def test_foreign_sqlite_file_is_refused(rib_path: Path) -> None:
    rib_path.parent.mkdir(parents=True)
    conn = sqlite3.connect(rib_path)
    conn.execute("CREATE TABLE photos (id INTEGER)")
    conn.commit()
    conn.close()
    with pytest.raises(UserError, match=r"other tables \(photos\)"):
        Rib(rib_path)


def test_deployment_and_robot_views(rib_path: Path, clock: FakeWallClock) -> None:
    with Rib(rib_path, clock=clock) as rib:
        _fleet(rib)
        clock.now += 5
        rib.update_deployment_load("edge-1", 3, capacity=8)
        deps = rib.deployments()
        assert [d.id for d in deps] == ["edge-1", "edge-2"]
        edge1 = rib.deployment("edge-1")
        assert edge1 is not None
        assert (edge1.load, edge1.capacity, edge1.last_seen) == (3, 8, clock.now)
        assert edge1.alive and not edge1.draining
        assert rib.deployment("nope") is None
        robot = rib.robot("robot-1")
        assert robot is not None and robot.alive and robot.service == "detect"
        assert [r.id for r in rib.robots()] == ["robot-1"]
        # Plain data for the CLI's --json views.
        json.dumps([d.to_dict() for d in deps] + [r.to_dict() for r in rib.robots()])


def test_liveness_transitions_are_events_with_reasons(rib_path: Path) -> None:
    with Rib(rib_path) as rib:
        _fleet(rib)
        assert rib.set_deployment_draining("edge-1", "SIGTERM")
        assert not rib.set_deployment_draining("edge-1", "again")
        assert rib.set_deployment_alive("edge-1", False, "token gone")
        assert not rib.set_deployment_alive("edge-1", False, "twice")
        assert not rib.set_deployment_alive("unknown", False, "never registered")
        dep = rib.deployment("edge-1")
        assert dep is not None and not dep.alive and not dep.draining
        assert rib.set_robot_alive("robot-1", False, "token gone")
        # Coming back: registering again marks it alive and records it.
        rib.upsert_deployment(
            "edge-1", service="detect", model_digest="sha256:aa", capacity=4, version="0.1.0"
        )
        kinds = [(e.kind, e.deployment or e.robot, e.reason) for e in rib.events()]
    assert kinds == [
        ("deployment_up", "edge-1", "service detect"),
        ("deployment_up", "edge-2", "service detect"),
        ("robot_up", "robot-1", "service detect"),
        ("deployment_drain", "edge-1", "SIGTERM"),
        ("deployment_down", "edge-1", "token gone"),
        ("robot_down", "robot-1", "token gone"),
        ("deployment_up", "edge-1", "service detect"),
    ]


def test_routes_states_and_epochs_survive_a_restart(rib_path: Path, clock: FakeWallClock) -> None:
    with Rib(rib_path, clock=clock) as rib:
        _fleet(rib)
        e1 = rib.reserve_epoch("robot-1")
        rib.set_route("robot-1", "edge-1", e1, "initial")
        clock.now += 10
        e2 = rib.reserve_epoch("robot-1")
        rib.set_route("robot-1", "edge-2", e2, "bound_violation")
        rib.set_deployment_state("edge-1", "robot-1", DeploymentState.STANDBY, e2)
        rib.save_profile("robot-1", "edge-1", "probe", [0.01, 0.02, 0.03])
        # An epoch reserved for a switch that never completed (the registry crashed mid-switch).
        e3 = rib.reserve_epoch("robot-1")
    assert (e1, e2, e3) == (1, 2, 3)

    with Rib(rib_path, clock=clock) as rib:
        route = rib.route("robot-1")
        assert route is not None
        assert (route.deployment, route.epoch, route.since) == ("edge-2", 2, clock.now)
        assert [r.robot for r in rib.routes()] == ["robot-1"]
        states = {(s.deployment, s.state, s.epoch) for s in rib.deployment_states(robot="robot-1")}
        assert states == {("edge-1", DeploymentState.STANDBY, 2), ("edge-2", "service", 2)}
        [profile] = rib.profiles("robot-1")
        assert (profile.deployment, profile.source, profile.samples) == (
            "edge-1",
            "probe",
            (0.01, 0.02, 0.03),
        )
        # Epochs only grow, past the reserved one too.
        assert rib.issued_epoch("robot-1") == 3
        assert rib.reserve_epoch("robot-1") == 4
        assert len(rib.events(limit=1000)) > 0


def test_route_epochs_only_grow(rib_path: Path) -> None:
    with Rib(rib_path) as rib:
        rib.set_route("robot-1", "edge-1", rib.reserve_epoch("robot-1"))
        rib.set_route("robot-1", "edge-2", rib.reserve_epoch("robot-1"))
        with pytest.raises(ValueError, match="epoch 2 for robot 'robot-1' is not newer"):
            rib.set_route("robot-1", "edge-1", 2)
        with pytest.raises(ValueError, match=r"epoch 1 .* is not newer than the current 2"):
            rib.set_route("robot-1", "edge-1", 1)
        route = rib.route("robot-1")
        assert route is not None and (route.deployment, route.epoch) == ("edge-2", 2)
        assert rib.reserve_epoch("robot-1", at_least=40) == 40
        assert rib.reserve_epoch("robot-1", at_least=10) == 41


def test_local_route_and_reservation_without_route(rib_path: Path) -> None:
    with Rib(rib_path) as rib:
        rib.reserve_epoch("robot-9")
        # A reserved epoch alone is no route.
        assert rib.route("robot-9") is None and rib.routes() == []
        rib.set_route("robot-9", None, rib.reserve_epoch("robot-9"), "deployment_lost")
        route = rib.route("robot-9")
        assert route is not None and route.deployment is None and route.epoch == 2
        [event] = rib.events(kind="route")
        assert event.reason == "deployment_lost: local -> local"


def test_events_newest_first_limit_filters_and_ts(rib_path: Path, clock: FakeWallClock) -> None:
    with Rib(rib_path, clock=clock) as rib:
        for i in range(10):
            clock.now += 1
            rib.record_event(
                EventKind.STATE, robot=f"robot-{i % 2}", deployment="edge-1", epoch=i, reason=str(i)
            )
        latest = rib.events(limit=3)
        assert [e.reason for e in latest] == ["7", "8", "9"]
        assert [e.ts for e in latest] == [clock.now - 2, clock.now - 1, clock.now]
        assert [e.reason for e in rib.events(limit=2, robot="robot-0")] == ["6", "8"]
        assert rib.events(kind="route") == []
        json.dumps([e.to_dict() for e in latest])
        with pytest.raises(ValueError, match="limit"):
            rib.events(limit=0)


def test_events_are_pruned_past_the_kept_count(
    rib_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(rib_module, "EVENTS_KEEP", 20)
    monkeypatch.setattr(rib_module, "EVENTS_PRUNE_EVERY", 10)
    with Rib(rib_path) as rib:
        for i in range(95):
            rib.record_event("test", reason=str(i))
        kept = rib.events(limit=1000)
    # Pruned every 10 inserts down to the newest 20: never more than 20 + 10 rows, newest kept.
    assert 20 <= len(kept) < 30
    assert kept[-1].reason == "94"


def test_reset_liveness_marks_everything_unseen_without_events(rib_path: Path) -> None:
    with Rib(rib_path) as rib:
        _fleet(rib)
        before = len(rib.events(limit=1000))
        rib.reset_liveness()
        assert not any(d.alive for d in rib.deployments())
        assert not any(r.alive for r in rib.robots())
        assert len(rib.events(limit=1000)) == before


def test_bad_values_are_refused(rib_path: Path) -> None:
    with Rib(rib_path) as rib:
        with pytest.raises(ValueError, match="capacity"):
            rib.upsert_deployment("e", service="s", model_digest="d", capacity=-1, version="1")
        with pytest.raises(ValueError, match="deployment id"):
            rib.upsert_deployment("", service="s", model_digest="d", capacity=1, version="1")
        with pytest.raises(ValueError, match=r"'sleeping' is not a valid DeploymentState"):
            rib.set_deployment_state("e", "r", "sleeping", 1)
        with pytest.raises(ValueError, match="finite"):
            rib.save_profile("r", "e", "probe", [float("nan")])
        with pytest.raises(sqlite3.IntegrityError):
            rib.save_profile("r", "e", "guess", [0.1])


def test_concurrent_writers_are_serialized(rib_path: Path) -> None:
    errors: list[BaseException] = []
    with Rib(rib_path) as rib:

        def write(n: int) -> None:
            try:
                for i in range(50):
                    rib.record_event("test", robot=f"robot-{n}", reason=str(i))
                    rib.reserve_epoch(f"robot-{n}")
            except BaseException as exc:  # collected and asserted below
                errors.append(exc)

        threads = [threading.Thread(target=write, args=(n,)) for n in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=10)
        assert not any(t.is_alive() for t in threads)
        assert errors == []
        assert len(rib.events(limit=1000)) == 200
        assert [rib.issued_epoch(f"robot-{n}") for n in range(4)] == [50] * 4


def test_memory_rib_for_tests() -> None:
    with Rib(":memory:") as rib:
        _fleet(rib)
        assert len(rib.deployments()) == 2
