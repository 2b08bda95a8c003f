"""Round-robin pools (`dispatch: round_robin`): which deployments serve one robot together.

In a round-robin fleet the route of a robot names its deployment (the scheduler's choice, as in
anycast) and a pool: that deployment first, then up to `pool_size - 1` more live deployments of
the service, all in service for the robot at the route's epoch. The robot sends each frame to one
member's key in turn (`common.keys.svc_infer_at`), so each frame is computed exactly once and the
members' compute adds up (the navigation paper's replicated workers).

`PoolPlanner` only chooses members; the switch protocol (`registry.switch.Switcher`) puts them in
service and publishes the route. `registry.pool_keeper.PoolKeeper` is the registry control loop's
part: every round it asks `needs_repool` of each route, and when a member's token goes it rebuilds
the pools it was in, so a member that died is dropped and a live standby joins.

Members are ranked by how many robots' pools they are in already (fewest first, then by id), so
robots spread over the deployments when pools are smaller than the fleet. A full pool is left
alone while its members live: ranking alone never moves a member, so pools do not flap.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable, Sequence

from common.config import DispatchMode, FleetConfig
from registry.rib import Rib, RibDeploymentRow, RibRouteRow

log = logging.getLogger(__name__)

# A robot's pool is rebuilt at most this often (a member that keeps refusing).
POOL_RETRY_S = 2.0


def pool_planner(cfg: FleetConfig, rib: Rib) -> PoolPlanner | None:
    """The fleet's planner: None in an anycast fleet."""
    if cfg.dispatch.mode is not DispatchMode.ROUND_ROBIN:
        return None
    return PoolPlanner(rib, cfg.service_name, cfg.dispatch.pool_limit())


class PoolPlanner:
    """`PoolPlanner(rib, "vision", limit=3)`: pools of at most `limit` deployments (0: every live
    deployment of the service)."""

    def __init__(self, rib: Rib, service: str, limit: int) -> None:
        if limit < 0:
            raise ValueError(f"pool limit must be >= 0, got {limit}")
        self._rib = rib
        self._service = service
        self.limit = limit

    def members(self, robot: str, primary: str) -> list[str]:
        """The pool for `robot` around `primary`: `primary` first, then the best ranked others."""
        usable = self.usable(self._rib.deployments())
        routes = self._rib.routes()
        pools = Counter(m for r in routes if r.robot != robot for m in _serving(r))
        others = sorted((d for d in usable if d != primary), key=lambda d: (pools[d], d))
        size = self.limit or len(usable) + 1
        return [primary, *others[: max(0, size - 1)]]

    def needs_repool(self, route: RibRouteRow, usable: set[str]) -> bool:
        """Whether `route`'s pool should change: a member is gone or draining, or the pool is
        short of its size while a usable deployment (of `usable(...)`, read once a round) is
        outside it."""
        if route.deployment is None:
            return False
        pool = route.pool or (route.deployment,)
        if route.deployment not in usable:
            return False  # the primary's failure is the scheduler's to handle
        if any(member not in usable for member in pool):
            return True
        size = self.limit or len(usable)
        return len(pool) < size and any(d not in pool for d in usable)

    def usable(self, deployments: Iterable[RibDeploymentRow]) -> set[str]:
        """The deployments that may be pool members: alive, not draining, of the service."""
        return {
            d.id for d in deployments if d.alive and not d.draining and d.service == self._service
        }


def _serving(route: RibRouteRow) -> Sequence[str]:
    if route.pool:
        return route.pool
    return (route.deployment,) if route.deployment is not None else ()
