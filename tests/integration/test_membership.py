"""common.membership over real Zenoh sessions on loopback: seeded by a liveliness get, then
followed. Every wait is on the view itself, with a timeout."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable

import pytest
import zenoh

from common import keys
from common.membership import MemberChange, MembershipView
from common.session import open_session
from tests.integration.conftest import LEASE_MS, find_free_port, loopback_endpoint

WAIT_S = 10.0


@pytest.fixture
def fleet() -> str:
    return f"m-{uuid.uuid4().hex[:8]}"


def test_follows_tokens_that_come_and_go(
    open_peer: Callable[..., zenoh.Session], fleet: str
) -> None:
    watcher, member = open_peer(), open_peer()
    changes: list[MemberChange] = []
    with MembershipView(watcher, fleet, on_change=changes.append) as view:
        token = member.liveliness().declare_token(keys.alive_deployment(fleet, "edge-1"))
        assert view.wait_for("cloud", ["edge-1"], timeout_s=WAIT_S), "edge-1 not seen"
        token.undeclare()
        assert view.wait_for("cloud", ["edge-1"], timeout_s=WAIT_S, present=False)
    assert [(c.role, c.id, c.alive) for c in changes] == [
        ("cloud", "edge-1", True),
        ("cloud", "edge-1", False),
    ]


def test_seeded_with_the_tokens_alive_before_it_started(
    open_peer: Callable[..., zenoh.Session], fleet: str
) -> None:
    watcher, member = open_peer(), open_peer()
    token = member.liveliness().declare_token(keys.alive_robot(fleet, "robot-1"))
    try:
        # Wait until the watcher's session knows the token, then start a second view: it has
        # the token as soon as start() returns, without waiting.
        with MembershipView(watcher, fleet, roles=("robot",)) as first:
            assert first.wait_for("robot", ["robot-1"], timeout_s=WAIT_S)
        changes: list[MemberChange] = []
        with MembershipView(watcher, fleet, on_change=changes.append) as view:
            assert view.alive("robot", "robot-1")
            assert view.snapshot()["robot"] == {"robot-1"}
        assert [(c.id, c.alive) for c in changes] == [("robot-1", True)]
    finally:
        token.undeclare()


def test_one_role_ignores_the_others_and_predicates_wait_for_counts(
    open_peer: Callable[..., zenoh.Session], fleet: str
) -> None:
    watcher, member = open_peer(), open_peer()
    with (
        MembershipView(watcher, fleet, roles=("registry",)) as registries,
        MembershipView(watcher, fleet) as everyone,
    ):
        tokens = [
            member.liveliness().declare_token(keys.alive_deployment(fleet, "edge-1")),
            member.liveliness().declare_token(keys.alive_deployment(fleet, "edge-2")),
            member.liveliness().declare_token(keys.alive_registry(fleet, "reg")),
        ]
        try:
            assert everyone.wait_for(
                lambda m: len(m["cloud"]) == 2 and bool(m["registry"]), timeout_s=WAIT_S
            )
            assert registries.wait_for("registry", timeout_s=WAIT_S)
            assert registries.snapshot() == {"registry": {"reg"}}
        finally:
            for token in tokens:
                token.undeclare()


def test_a_wait_times_out_and_close_wakes_a_waiter(
    open_peer: Callable[..., zenoh.Session], fleet: str
) -> None:
    view = MembershipView(open_peer(), fleet).start()
    started = time.monotonic()
    assert not view.wait_for("cloud", ["nobody"], timeout_s=0.2)
    assert time.monotonic() - started >= 0.2
    result: list[bool] = []
    waiter = threading.Thread(
        target=lambda: result.append(view.wait_for("cloud", ["nobody"], timeout_s=None))
    )
    waiter.start()
    view.close()
    waiter.join(WAIT_S)
    assert not waiter.is_alive() and result == [False]


def test_a_router_that_goes_away_is_seen_gone(
    open_peer: Callable[..., zenoh.Session], fleet: str
) -> None:
    """Regression: with a subscriber without history, a peer never heard that its router (and
    its token, declared before the subscriber) went away; Zenoh logged "Unknown token"."""
    endpoint = loopback_endpoint(find_free_port())
    router = open_session(router=True, listen=[endpoint], lease_ms=LEASE_MS)
    try:
        # Held in a variable: a token that is garbage-collected is undeclared.
        _token = router.liveliness().declare_token(keys.alive_registry(fleet, "reg"))
        peer = open_peer(connect=[endpoint])
        with MembershipView(peer, fleet, roles=("registry",)) as view:
            assert view.wait_for("registry", ["reg"], timeout_s=WAIT_S), "the router's token"
            router.close()
            assert view.wait_for("registry", ["reg"], timeout_s=WAIT_S, present=False)
    finally:
        router.close()
