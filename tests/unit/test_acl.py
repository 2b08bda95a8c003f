"""`common.acl`: the access control generated from the fleet file. Each host may send only what
its role needs on its own keys (checked with Zenoh's own key-expression inclusion, the test Zenoh
applies), the CLI reads views and follows results only, only the registry drives ctl and routes,
and Zenoh accepts the generated section."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from common import acl, keys
from common.acl import Message
from common.config import FleetConfig, load_fleet
from common.init_cli import write_fleet
from common.session import zenoh_config


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> FleetConfig:
    directory = tmp_path_factory.mktemp("fleet")
    return load_fleet(write_fleet(directory, fleet="acl", robots=2, tls=True))


def allowed(cfg: FleetConfig, subject: str, message: Message, key: str) -> bool:
    """Whether a rule of `subject` lets it send `message` on `key` (Zenoh: a rule's key
    expression must include the message's)."""
    return any(
        message in grant.messages and any(zenoh.KeyExpr(k).includes(key) for k in grant.key_exprs)
        for grant in acl.grants(cfg)[subject]
    )


def test_subjects_are_every_host_and_the_cli(fleet: FleetConfig) -> None:
    assert list(acl.grants(fleet)) == ["registry", "edge-1", "edge-2", "robot-1", "robot-2", "cli"]


def test_a_robot_touches_only_its_own_keys(fleet: FleetConfig) -> None:
    f, svc = fleet.fleet, fleet.service
    for robot, other in (("robot-1", "robot-2"), ("robot-2", "robot-1")):
        assert allowed(fleet, robot, Message.QUERY, keys.svc_infer(f, svc, robot))
        assert not allowed(fleet, robot, Message.QUERY, keys.svc_infer(f, svc, other))
        assert not allowed(fleet, robot, Message.QUERY, keys.svc_infer_all(f, svc))
        for key in (keys.reg_register(f), keys.reg_reroute(f), keys.dep_probe_all(f)):
            assert allowed(fleet, robot, Message.QUERY, key)
        assert not allowed(fleet, robot, Message.QUERY, keys.dep_ctl(f, "edge-1"))
        assert not allowed(fleet, robot, Message.QUERY, keys.reg_drain(f))
        assert allowed(fleet, robot, Message.PUT, keys.tele(f, robot))
        assert not allowed(fleet, robot, Message.PUT, keys.tele(f, other))
        assert not allowed(fleet, robot, Message.PUT, keys.route(f, robot))
        assert allowed(fleet, robot, Message.DECLARE_SUBSCRIBER, keys.route(f, robot))
        assert not allowed(fleet, robot, Message.DECLARE_SUBSCRIBER, keys.route(f, other))
        assert not allowed(fleet, robot, Message.DECLARE_SUBSCRIBER, keys.tele(f, other))
        assert allowed(fleet, robot, Message.LIVELINESS_TOKEN, keys.alive_robot(f, robot))
        assert not allowed(fleet, robot, Message.LIVELINESS_TOKEN, keys.alive_robot(f, other))
        assert not allowed(
            fleet, robot, Message.LIVELINESS_TOKEN, keys.alive_deployment(f, "edge-1")
        )
        assert not allowed(fleet, robot, Message.DECLARE_QUERYABLE, keys.svc_infer(f, svc, robot))
        assert not allowed(fleet, robot, Message.REPLY, keys.svc_infer(f, svc, robot))


def test_a_cloud_serves_its_fleet_and_answers_only_its_own_probe_and_ctl(
    fleet: FleetConfig,
) -> None:
    f, svc = fleet.fleet, fleet.service
    for message in (Message.DECLARE_QUERYABLE, Message.REPLY):
        assert allowed(fleet, "edge-1", message, keys.svc_infer(f, svc, "robot-2"))
        assert allowed(fleet, "edge-1", message, keys.svc_infer_all(f, svc))
        assert not allowed(fleet, "edge-1", message, keys.svc_infer(f, "other-service", "robot-1"))
        assert not allowed(fleet, "edge-1", message, keys.svc_infer("other-fleet", svc, "robot-1"))
        assert allowed(fleet, "edge-1", message, keys.dep_ctl(f, "edge-1"))
        assert allowed(fleet, "edge-1", message, keys.dep_probe(f, "edge-1"))
        assert not allowed(fleet, "edge-1", message, keys.dep_ctl(f, "edge-2"))
        assert not allowed(fleet, "edge-1", message, keys.dep_probe(f, "edge-2"))
        assert not allowed(fleet, "edge-1", message, keys.rib_routes(f))
    assert not allowed(fleet, "edge-1", Message.QUERY, keys.dep_ctl(f, "edge-2"))
    assert not allowed(fleet, "edge-1", Message.QUERY, keys.svc_infer(f, svc, "robot-1"))
    assert allowed(fleet, "edge-1", Message.QUERY, keys.reg_drain(f))
    assert not allowed(fleet, "edge-1", Message.PUT, keys.route(f, "robot-1"))


def test_only_the_registry_drives_ctl_and_routes(fleet: FleetConfig) -> None:
    f = fleet.fleet
    subjects = list(acl.grants(fleet))
    ctl, route = keys.dep_ctl(f, "edge-1"), keys.route(f, "robot-1")
    assert [s for s in subjects if allowed(fleet, s, Message.QUERY, ctl)] == ["registry"]
    assert [s for s in subjects if allowed(fleet, s, Message.PUT, route)] == ["registry"]


def test_the_cli_reads_views_and_nothing_else(fleet: FleetConfig) -> None:
    f = fleet.fleet
    for view in keys.RIB_VIEWS:
        assert allowed(fleet, "cli", Message.QUERY, keys.rib(f, view))
    assert not allowed(fleet, "cli", Message.QUERY, keys.dep_ctl(f, "edge-1"))
    assert not allowed(fleet, "cli", Message.QUERY, keys.dep_probe(f, "edge-1"))
    assert not allowed(fleet, "cli", Message.QUERY, keys.svc_infer(f, fleet.service, "robot-1"))
    assert not allowed(fleet, "cli", Message.QUERY, keys.reg_register(f))
    for message in Message:
        if message is not Message.QUERY:
            assert not allowed(fleet, "cli", message, keys.rib_routes(f)), message
    assert not allowed(fleet, "cli", Message.DECLARE_SUBSCRIBER, keys.route(f, "robot-1"))


def test_nothing_outside_the_fleet(fleet: FleetConfig) -> None:
    for subject in acl.grants(fleet):
        for message in Message:
            assert not allowed(fleet, subject, message, "ef/other/rib/routes")
            assert not allowed(fleet, subject, message, "@/admin/x")


def test_zenoh_takes_the_section_default_deny(fleet: FleetConfig) -> None:
    section = acl.access_control(fleet)
    assert section["enabled"] is True and section["default_permission"] == "deny"
    ids = [r["id"] for r in section["rules"]]
    assert len(ids) == len(set(ids))
    # Every session of the fleet carries it, read back from a real zenoh.Config.
    for kwargs in ({"machine": "robot-1"}, {"machine": "edge-2"}, {"router": True}):
        conf = zenoh_config(fleet, **kwargs)
        assert json.loads(conf.get_json("access_control/enabled")) is True
        subjects = json.loads(conf.get_json("access_control/subjects"))
        assert {"id": "host:robot-2", "cert_common_names": ["robot-2"]} in [
            {k: v for k, v in s.items() if v is not None} for s in subjects
        ]


def test_plain_fleets_have_none(tmp_path: Path) -> None:
    plain = load_fleet(write_fleet(tmp_path, fleet="plain"))
    assert not plain.tls and not plain.access_control
    conf = zenoh_config(plain, machine="robot-1")
    assert json.loads(conf.get_json("access_control/enabled")) is False


def test_table_lists_every_grant(fleet: FleetConfig) -> None:
    rows = acl.table(fleet)
    assert ("cli", "query", keys.rib_all(fleet.fleet), "read the RIB views") in rows
    assert {r[0] for r in rows} == set(acl.grants(fleet))


def test_a_robot_publishes_its_own_results_and_takes_its_own_frames(fleet: FleetConfig) -> None:
    f = fleet.fleet
    assert allowed(fleet, "robot-1", Message.PUT, keys.results_out(f, "robot-1"))
    assert not allowed(fleet, "robot-1", Message.PUT, keys.results_out(f, "robot-2"))
    for message in (Message.DECLARE_SUBSCRIBER, Message.PUT):
        assert allowed(fleet, "robot-1", message, keys.frames_in(f, "robot-1"))
        assert not allowed(fleet, "robot-1", message, keys.frames_in(f, "robot-2"))
    # The CLI (`elasticfog results`) follows every robot's results and sends no frame.
    assert allowed(fleet, "cli", Message.DECLARE_SUBSCRIBER, keys.results_out(f, "robot-2"))
    assert not allowed(fleet, "cli", Message.PUT, keys.frames_in(f, "robot-1"))
    assert not allowed(fleet, "cli", Message.PUT, keys.results_out(f, "robot-1"))
