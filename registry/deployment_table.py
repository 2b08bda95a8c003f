"""The scheduler's view of the RIB's deployments, read once per round as one table.

Apart from the round's other inputs (`registry.round_inputs`, which read the registrar) so that
the registrar can price a registration against the same table without importing them back.
"""

from __future__ import annotations

from collections.abc import Iterable

from registry.rib import RibDeploymentRow
from registry.scheduler import DeploymentTable, DeploymentView


def deployment_table(
    rows: Iterable[RibDeploymentRow], unusable: frozenset[str] = frozenset()
) -> DeploymentTable:
    """The scheduler's view of the RIB's deployments; those `unusable` count as dead."""
    return DeploymentTable(
        [
            DeploymentView(
                id=row.id,
                service=row.service,
                alive=row.alive and row.id not in unusable,
                draining=row.draining,
                load=row.load,
                capacity=row.capacity,
                model_digest=row.model_digest or None,
            )
            for row in rows
        ]
    )
