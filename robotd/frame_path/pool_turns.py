"""Round-robin dispatch on the robot: which member of its pool gets the next offloaded frame.

In a `dispatch: round_robin` fleet the registry's route names a pool of deployments, all in
service for this robot at the route's epoch (`registry.pools`). Each frame goes to one member's
key (`common.keys.svc_infer_at`) in turn, so it is computed exactly once and, with more than one
frame in flight (`max_in_flight`), the members compute frames side by side. A frame whose member
fails is finished on the robot like any failed offload: none is lost, none is sent twice.
"""

from __future__ import annotations

import threading


class PoolTurns:
    """`PoolTurns().next(("edge-1", "edge-2"))` -> "edge-1", then "edge-2", then "edge-1"...;
    None for a pool of fewer than two (the anycast key reaches the one deployment)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._turn = 0

    def next(self, pool: tuple[str, ...]) -> str | None:
        if len(pool) < 2:
            return None
        with self._lock:
            member = pool[self._turn % len(pool)]
            self._turn += 1
        return member

    def peek(self, pool: tuple[str, ...]) -> str | None:
        """The member `next` would give now, without taking the turn."""
        if len(pool) < 2:
            return None
        with self._lock:
            return pool[self._turn % len(pool)]
