"""common.membership without a network: the seed/follow race, decided by a fake session that
lets the test interleave the subscriber's news with the seeding get's replies.

Regression guarded against: a seed reply that arrives after the subscriber has reported the same
token gone must not bring it back (a dead deployment counted alive until the next change).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import zenoh

from common import keys
from common.membership import MemberChange, MembershipView

FLEET = "unit"


@dataclass
class FakeSample:
    key_expr: str
    kind: zenoh.SampleKind


@dataclass
class FakeOk:
    key_expr: str


@dataclass
class FakeReply:
    ok: FakeOk | None


class FakeLiveliness:
    """Records the subscription; `get` yields `seed` keys, running `between` before each."""

    def __init__(self) -> None:
        self.subscribed: str | None = None
        self.on_sample: Callable[[Any], None] | None = None
        self.undeclared = False
        self.seed: list[str] = []
        self.between: list[Callable[[], None]] = []

    def declare_subscriber(
        self, key: str, callback: Callable[[Any], None], *, history: bool
    ) -> FakeLiveliness:
        assert history, "without history Zenoh may never report the end of an older token"
        self.subscribed, self.on_sample = key, callback
        return self

    def undeclare(self) -> None:
        self.undeclared = True

    def get(self, key: str, timeout: float) -> Iterator[FakeReply]:
        assert key == self.subscribed, "seeded from the key it follows"
        for n, seed_key in enumerate(self.seed):
            if n < len(self.between):
                self.between[n]()
            yield FakeReply(FakeOk(seed_key))

    def sample(self, key: str, kind: zenoh.SampleKind) -> None:
        assert self.on_sample is not None
        self.on_sample(FakeSample(key, kind))


class FakeSession:
    def __init__(self) -> None:
        self.live = FakeLiveliness()

    def liveliness(self) -> FakeLiveliness:
        return self.live


def _view(session: FakeSession, changes: list[MemberChange], **kwargs: Any) -> MembershipView:
    return MembershipView(session, FLEET, on_change=changes.append, **kwargs)  # type: ignore[arg-type]


def test_a_stale_seed_does_not_revive_a_token_the_subscriber_saw_go() -> None:
    session = FakeSession()
    edge1, edge2 = keys.alive_deployment(FLEET, "edge-1"), keys.alive_deployment(FLEET, "edge-2")
    session.live.seed = [edge2, edge1]
    # edge-1 comes and goes on the subscriber while the get is still answering (with old news).
    session.live.between = [
        lambda: session.live.sample(edge1, zenoh.SampleKind.PUT),
        lambda: session.live.sample(edge1, zenoh.SampleKind.DELETE),
    ]
    changes: list[MemberChange] = []
    with _view(session, changes) as view:
        assert view.ids("cloud") == {"edge-2"}
    assert [(c.id, c.alive, c.seed) for c in changes] == [
        ("edge-1", True, False),
        ("edge-2", True, True),
        ("edge-1", False, False),
    ]
    assert session.live.undeclared


def test_repeated_news_change_nothing_and_alive_ids_follow() -> None:
    session = FakeSession()
    robot = keys.alive_robot(FLEET, "robot-1")
    session.live.seed = [robot]
    changes: list[MemberChange] = []
    with _view(session, changes) as view:
        session.live.sample(robot, zenoh.SampleKind.PUT)  # already known from the seed
        session.live.sample(keys.alive_robot(FLEET, "robot-2"), zenoh.SampleKind.PUT)
        session.live.sample(robot, zenoh.SampleKind.DELETE)
        assert view.snapshot() == {
            "registry": frozenset(),
            "cloud": frozenset(),
            "robot": frozenset({"robot-2"}),
        }
    assert [(c.id, c.alive, c.alive_ids) for c in changes] == [
        ("robot-1", True, {"robot-1"}),
        ("robot-2", True, {"robot-1", "robot-2"}),
        ("robot-1", False, {"robot-2"}),
    ]


def test_one_role_follows_its_own_key_and_other_fleets_are_ignored() -> None:
    session = FakeSession()
    changes: list[MemberChange] = []
    with _view(session, changes, roles=("registry",)) as view:
        assert session.live.subscribed == keys.alive_registries(FLEET)
        session.live.sample(keys.alive_registry("other", "reg"), zenoh.SampleKind.PUT)
        session.live.sample(keys.tele(FLEET, "robot-1"), zenoh.SampleKind.PUT)
        assert view.ids("registry") == frozenset()
        with pytest.raises(ValueError, match="follows registry"):
            view.wait_for("cloud", timeout_s=0)
    assert changes == []


def test_a_failing_listener_is_logged_not_raised(caplog: pytest.LogCaptureFixture) -> None:
    session = FakeSession()

    def listener(change: MemberChange) -> None:
        raise RuntimeError("listener bug")

    with MembershipView(session, FLEET, on_change=listener) as view:  # type: ignore[arg-type]
        session.live.sample(keys.alive_deployment(FLEET, "edge-1"), zenoh.SampleKind.PUT)
        assert view.alive("cloud", "edge-1")
    assert any("membership listener failed" in r.getMessage() for r in caplog.records)


def test_unknown_roles_are_refused() -> None:
    with pytest.raises(ValueError, match="roles must be"):
        MembershipView(FakeSession(), FLEET, roles=("drone",))  # type: ignore[arg-type]
