"""Who is alive in a fleet, from liveliness tokens: one view, seeded then followed.

Every process of the fleet holds a token `alive/<role>/<id>` (common/keys.py). A
`MembershipView` declares a liveliness subscriber first and then seeds itself with a liveliness
`get`, so no token declared meanwhile is missed and the view is filled when `start()` returns; a
seed reply about an id the subscriber has already reported is dropped (the subscriber's news are
newer), so no order of arrival leaves a dead token counted or a live one out. It keeps role -> set
of ids, calls `on_change` once per real change (a repeated report changes nothing), and lets any
thread wait on a condition variable until the members satisfy a predicate (`wait_for`), with a
timeout: readiness is waited for, never slept for.

The subscriber asks for history although the get seeds the view: without it, Zenoh (1.10) does
not always deliver the end of a token that existed before the subscriber. Seen on loopback: a
peer never heard that its router's token went away, and Zenoh logged "Unknown token" (on stdout,
which broke `elasticfog demo --json`). With history it reports those tokens itself, their end
included; the get still makes the seed synchronous.

`on_change` runs on Zenoh's subscriber thread (or the starting thread for seeds) while the view's
lock is held, so listeners see changes in the order the view applied them; keep it short (set an
event, queue an item). It may read the view. A listener's exception is logged, never raised into
Zenoh.

Use it as a context manager (`with MembershipView(...) as view`, or a daemon's `hold`): entering
declares and seeds, exiting undeclares the subscriber and wakes every waiter.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from types import TracebackType

import zenoh

from common import keys

log = logging.getLogger(__name__)

SEED_TIMEOUT_S = 1.0
"""How long the seeding `get` waits for replies (it returns earlier once every peer answered)."""

# The subscription of a view that follows one role only (no key is formatted here).
_ROLE_KEYS: dict[str, Callable[[str], str]] = {
    keys.Role.REGISTRY: keys.alive_registries,
    keys.Role.CLOUD: keys.alive_deployments,
    keys.Role.ROBOT: keys.alive_robots,
}

Members = Mapping[str, frozenset[str]]
"""role -> ids alive, for every role the view follows."""


@dataclass(frozen=True)
class MemberChange:
    """One member came (`alive`) or went. `seed`: learnt from the start-up `get` rather than
    the subscriber. `alive_ids`: the ids of that role alive after the change."""

    role: str
    id: str
    alive: bool
    seed: bool
    alive_ids: frozenset[str]


class MembershipView:
    """`MembershipView(session, fleet, roles=("cloud",), on_change=...)`; no I/O until entered."""

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        roles: Iterable[str] = keys.ROLES,
        *,
        on_change: Callable[[MemberChange], None] | None = None,
        seed_timeout_s: float = SEED_TIMEOUT_S,
    ) -> None:
        self.fleet = keys.validate_id(fleet, "fleet name")
        self.roles = tuple(dict.fromkeys(roles))
        unknown = [r for r in self.roles if r not in keys.ROLES]
        if unknown or not self.roles:
            raise ValueError(f"roles must be some of {', '.join(keys.ROLES)}, got {self.roles}")
        self._session = session
        self._on_change = on_change
        self._seed_timeout_s = seed_timeout_s
        # Reentrant: a listener runs under the lock and may read the view.
        self._changed = threading.Condition(threading.RLock())
        self._members: dict[str, set[str]] = {role: set() for role in self.roles}
        # Reported by the subscriber while seeding (a seed about them is stale); emptied once
        # seeding is over, so it does not grow with the fleet's history.
        self._followed: set[tuple[str, str]] = set()
        self._seeding = True
        self._subscriber: zenoh.Subscriber[None] | None = None
        self._closed = False

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> MembershipView:
        """Subscribe, then seed from a liveliness get (blocks for at most the seed timeout)."""
        key = _ROLE_KEYS[self.roles[0]](self.fleet) if len(self.roles) == 1 else None
        key = key or keys.alive_all(self.fleet)
        liveliness = self._session.liveliness()
        self._subscriber = liveliness.declare_subscriber(key, self._on_sample, history=True)
        try:
            for reply in liveliness.get(key, timeout=self._seed_timeout_s):
                if reply.ok is not None:
                    self._apply(str(reply.ok.key_expr), alive=True, seed=True)
        except BaseException:
            self.close()
            raise
        with self._changed:
            self._seeding = False
            self._followed.clear()
        return self

    def close(self) -> None:
        """Stop following (undeclare the subscriber) and wake every waiter; idempotent."""
        subscriber, self._subscriber = self._subscriber, None
        if subscriber is not None:
            try:
                subscriber.undeclare()
            except zenoh.ZError as exc:  # the session is already closed: nothing to undo
                log.debug("membership subscriber already gone: %s", exc)
        with self._changed:
            self._closed = True
            self._changed.notify_all()

    def __enter__(self) -> MembershipView:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- reading ---------------------------------------------------------------------------
    def ids(self, role: str) -> frozenset[str]:
        """The ids of `role` alive now."""
        with self._changed:
            return frozenset(self._members[role])

    def alive(self, role: str, id: str) -> bool:
        """Whether `id` of `role` is alive now."""
        with self._changed:
            return id in self._members[role]

    def snapshot(self) -> dict[str, frozenset[str]]:
        """role -> ids alive now, for every role followed."""
        with self._changed:
            return {role: frozenset(ids) for role, ids in self._members.items()}

    def wait_for(
        self,
        condition: Callable[[Members], bool] | str,
        ids: Iterable[str] | None = None,
        *,
        timeout_s: float | None,
        present: bool = True,
    ) -> bool:
        """Block until the members satisfy `condition`; True if they do, False after
        `timeout_s` (None: no limit) or once the view is closed.

        `condition` is a predicate over `snapshot()`, or a role: then every one of `ids` is
        alive (`present=False`: gone), or without `ids` any member of the role is (none is).
        """
        if callable(condition):
            test = condition
        elif condition in self.roles:
            test = _role_test(condition, ids, present)
        else:
            raise ValueError(f"this view follows {', '.join(self.roles)}, not {condition!r}")
        with self._changed:
            self._changed.wait_for(lambda: self._closed or test(self.snapshot()), timeout_s)
            return test(self.snapshot())

    # -- following -------------------------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._apply(str(sample.key_expr), alive=sample.kind == zenoh.SampleKind.PUT, seed=False)

    def _apply(self, key: str, *, alive: bool, seed: bool) -> None:
        parts = keys.parse_key(key)
        if parts is None or parts.kind is not keys.KeyKind.ALIVE or parts.fleet != self.fleet:
            return
        assert parts.role is not None and parts.id is not None
        if parts.role not in self._members:
            return
        member = (parts.role, parts.id)
        with self._changed:
            if seed and member in self._followed:
                return
            if not seed and self._seeding:
                self._followed.add(member)
            ids = self._members[parts.role]
            if (parts.id in ids) == alive:
                return
            if alive:
                ids.add(parts.id)
            else:
                ids.discard(parts.id)
            self._changed.notify_all()
            if self._on_change is not None:
                change = MemberChange(parts.role, parts.id, alive, seed, frozenset(ids))
                try:
                    self._on_change(change)
                except Exception:
                    log.exception("membership listener failed on %s", change)


def _role_test(role: str, ids: Iterable[str] | None, present: bool) -> Callable[[Members], bool]:
    wanted = None if ids is None else frozenset(ids)

    def test(members: Members) -> bool:
        alive = members[role]
        if wanted is None:
            return bool(alive) == present
        return wanted <= alive if present else not (wanted & alive)

    return test
