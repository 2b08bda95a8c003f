"""The control loop's part of round-robin pools: rebuilding a robot's pool when it needs it.

Every round the registry's control loop (`registry.control_loop`) asks `PoolKeeper.tend` of each
route, and when a member's token goes it rebuilds the pools it was in (`rebuild`), so a member that
died is dropped and a live standby joins. The members are the planner's choice
(`registry.pools.PoolPlanner`); the switch protocol (`registry.switch.Switcher`) puts them in
service. It lives apart from the planner because it drives the switch, which uses the planner.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from registry.pools import POOL_RETRY_S, PoolPlanner
from registry.rib import RibRouteRow
from registry.switch import Switcher

log = logging.getLogger("registry.pools")  # the pools' lines under one logger


class PoolKeeper:
    """`PoolKeeper(switcher)` (its `pools` set): rebuilds robots' pools from the control loop, at
    most once per `retry_s` for a robot, so a member that keeps refusing cannot turn every round
    into a switch."""

    def __init__(
        self,
        switcher: Switcher,
        *,
        retry_s: float = POOL_RETRY_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if switcher.pools is None:
            raise ValueError("a pool keeper needs a switcher with a pool planner")
        self._switcher = switcher
        self.planner: PoolPlanner = switcher.pools
        self._retry_s = retry_s
        self._clock = clock
        self._after: dict[str, float] = {}  # robot -> clock time of its next rebuild

    def tend(self, route: RibRouteRow, usable: set[str]) -> None:
        """Rebuild `route`'s pool if it needs it (`PoolPlanner.needs_repool`)."""
        if self.planner.needs_repool(route, usable):
            self.rebuild(route.robot, "pool")

    def rebuild(self, robot: str, reason: str) -> None:
        """Rebuild `robot`'s pool now, unless it was rebuilt less than `retry_s` ago."""
        now = self._clock()
        if now < self._after.get(robot, 0.0):
            return
        self._after[robot] = now + self._retry_s
        result = self._switcher.repool(robot, reason=reason)
        if result.changed:
            log.info(
                "route %s: pool %s (epoch %d, %s)",
                robot,
                ", ".join(self._switcher.rib.pool(robot)) or "-",
                result.epoch,
                reason,
            )


def pool_keeper(switcher: Switcher) -> PoolKeeper | None:
    """The keeper of a round-robin fleet's pools; None in an anycast fleet."""
    return PoolKeeper(switcher) if switcher.pools is not None else None
