"""The key space is a public contract: every key exactly as docs/keyspace.md writes it, ids checked,
and concrete keys parsed back to their parts."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from common import keys
from common.errors import UserError
from common.keys import InvalidIdError, KeyKind, KeyParts, parse_key

F = "lab"


def test_every_key_as_documented() -> None:
    assert keys.prefix(F) == "ef/lab"
    assert keys.rib_deployments(F) == "ef/lab/rib/deployments"
    assert keys.rib_robots(F) == "ef/lab/rib/robots"
    assert keys.rib_routes(F) == "ef/lab/rib/routes"
    assert keys.rib_events(F) == "ef/lab/rib/events"
    assert keys.rib_profiles(F) == "ef/lab/rib/profiles"
    assert keys.alive_registry(F, "registry") == "ef/lab/alive/registry/registry"
    assert keys.alive_deployment(F, "edge-1") == "ef/lab/alive/cloud/edge-1"
    assert keys.alive_robot(F, "robot-1") == "ef/lab/alive/robot/robot-1"
    assert keys.svc_infer(F, "vision", "robot-1") == "ef/lab/svc/vision/robot-1/infer"
    assert keys.dep_probe(F, "edge-1") == "ef/lab/dep/edge-1/probe"
    assert keys.dep_ctl(F, "edge-1") == "ef/lab/dep/edge-1/ctl"
    assert keys.tele(F, "robot-1") == "ef/lab/tele/robot-1"
    assert keys.tele_probe(F, "robot-1") == "ef/lab/tele/robot-1/probe"
    assert keys.route(F, "robot-1") == "ef/lab/route/robot-1"
    assert keys.reg_register(F) == "ef/lab/reg/register"
    assert keys.reg_reroute(F) == "ef/lab/reg/reroute"
    assert keys.reg_drain(F) == "ef/lab/reg/drain"


def test_wildcards_for_subscribers() -> None:
    assert keys.alive_all(F) == "ef/lab/alive/**"
    assert keys.alive_deployments(F) == "ef/lab/alive/cloud/*"
    assert keys.alive_robots(F) == "ef/lab/alive/robot/*"
    assert keys.alive_registries(F) == "ef/lab/alive/registry/*"
    assert keys.rib_all(F) == "ef/lab/rib/*"
    assert keys.svc_infer_all(F, "vision") == "ef/lab/svc/vision/*/infer"
    assert keys.dep_probe_all(F) == "ef/lab/dep/*/probe"
    assert keys.tele_all(F) == "ef/lab/tele/*"
    assert keys.tele_probe_all(F) == "ef/lab/tele/*/probe"
    assert keys.route_all(F) == "ef/lab/route/*"


def test_wildcards_match_the_keys_they_are_for() -> None:
    zenoh = pytest.importorskip("zenoh")
    ke = zenoh.KeyExpr
    assert ke(keys.alive_deployments(F)).intersects(keys.alive_deployment(F, "edge-1"))
    assert not ke(keys.alive_deployments(F)).intersects(keys.alive_robot(F, "edge-1"))
    assert ke(keys.alive_all(F)).intersects(keys.alive_robot(F, "r"))
    # Per-frame telemetry and probe reports are told apart by the wildcard depth.
    assert not ke(keys.tele_all(F)).intersects(keys.tele_probe(F, "r"))
    assert ke(keys.tele_probe_all(F)).intersects(keys.tele_probe(F, "r"))
    # Another fleet's keys never match.
    assert not ke(keys.alive_all(F)).intersects(keys.alive_robot("other", "r"))


@pytest.mark.parametrize(
    "bad", ["", "a/b", "a*", "$x", "a#b", "what?", "has space", "tab\t", "\x00"]
)
def test_bad_ids_are_refused_with_a_clear_error(bad: str) -> None:
    with pytest.raises(InvalidIdError) as info:
        keys.alive_robot(F, bad)
    message = str(info.value)
    assert "robot id" in message
    assert "\n" not in message
    # A UserError (one line, exit 2 at the CLI) and a ValueError (pydantic validators).
    assert isinstance(info.value, UserError)
    assert isinstance(info.value, ValueError)


def test_bad_fleet_and_unknown_view_or_role() -> None:
    with pytest.raises(InvalidIdError, match="fleet name"):
        keys.tele("a/b", "r")
    with pytest.raises(InvalidIdError, match="unknown RIB view"):
        keys.rib(F, "secrets")
    with pytest.raises(InvalidIdError, match="unknown role"):
        keys.alive(F, "router", "x")
    with pytest.raises(InvalidIdError, match="longer than"):
        keys.validate_id("x" * (keys.MAX_ID_CHARS + 1))
    with pytest.raises(InvalidIdError, match="must be a string"):
        keys.validate_id(3)


def test_parse_every_concrete_key() -> None:
    cases = {
        keys.rib_events(F): KeyParts(F, KeyKind.RIB, view="events"),
        keys.reg_register(F): KeyParts(F, KeyKind.REG_REGISTER),
        keys.reg_reroute(F): KeyParts(F, KeyKind.REG_REROUTE),
        keys.reg_drain(F): KeyParts(F, KeyKind.REG_DRAIN),
        keys.alive_deployment(F, "e"): KeyParts(F, KeyKind.ALIVE, id="e", role="cloud"),
        keys.alive_robot(F, "r"): KeyParts(F, KeyKind.ALIVE, id="r", role="robot"),
        keys.alive_registry(F, "g"): KeyParts(F, KeyKind.ALIVE, id="g", role="registry"),
        keys.svc_infer(F, "s", "r"): KeyParts(F, KeyKind.SVC_INFER, id="r", service="s"),
        keys.dep_probe(F, "e"): KeyParts(F, KeyKind.DEP_PROBE, id="e"),
        keys.dep_ctl(F, "e"): KeyParts(F, KeyKind.DEP_CTL, id="e"),
        keys.tele(F, "r"): KeyParts(F, KeyKind.TELE, id="r"),
        keys.tele_probe(F, "r"): KeyParts(F, KeyKind.TELE_PROBE, id="r"),
        keys.route(F, "r"): KeyParts(F, KeyKind.ROUTE, id="r"),
    }
    for key, parts in cases.items():
        assert parse_key(key) == parts, key


@pytest.mark.parametrize(
    "foreign",
    [
        "",
        "ef",
        "ef/lab",
        "other/lab/tele/r",
        "ef/lab/tele/*",
        "ef/lab/alive/router/x",
        "ef/lab/rib/secrets",
        "ef/lab/svc/s/r/other",
        "ef/lab/tele/r/probe/extra",
        "ef//tele/r",
    ],
)
def test_parse_refuses_foreign_and_wildcard_keys(foreign: str) -> None:
    assert parse_key(foreign) is None


_ids = st.text(
    alphabet=st.characters(
        codec="utf-8", exclude_characters="/*$#?", exclude_categories=("Z", "C")
    ),
    min_size=1,
    max_size=20,
)


@given(fleet=_ids, robot=_ids, service=_ids)
def test_parse_round_trip(fleet: str, robot: str, service: str) -> None:
    assert parse_key(keys.svc_infer(fleet, service, robot)) == KeyParts(
        fleet, KeyKind.SVC_INFER, id=robot, service=service
    )
    assert parse_key(keys.alive_robot(fleet, robot)) == KeyParts(
        fleet, KeyKind.ALIVE, id=robot, role="robot"
    )


def test_results_out_and_frames_in_are_the_contract_keys() -> None:
    assert keys.results_out(F, "robot-1") == "ef/lab/out/robot-1"
    assert keys.frames_in(F, "robot-1") == "ef/lab/in/robot-1"
    assert keys.results_out_all(F) == "ef/lab/out/*"
    assert keys.frames_in_all(F) == "ef/lab/in/*"
    assert parse_key(keys.results_out(F, "r")) == KeyParts(F, KeyKind.RESULTS_OUT, id="r")
    assert parse_key(keys.frames_in(F, "r")) == KeyParts(F, KeyKind.FRAMES_IN, id="r")
    with pytest.raises(InvalidIdError):
        keys.results_out(F, "a/b")
