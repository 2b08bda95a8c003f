"""The fleet's model as its daemons split it: one call, so that whoever splits it ahead of them
(the demo, the testbed, the load generator) fills the very cache entry the daemons then read."""

from __future__ import annotations

from common.config import FleetConfig
from common.partition import Partition, load_partition


def fleet_partition(cfg: FleetConfig) -> Partition:
    """`cfg.model` split at the fleet's cuts (`cuts.names`, `cuts.max_cut_tensors`, segments
    when `cuts.segments`) for its `input_shape`, from the partition cache when it is there."""
    shape = tuple(cfg.input_shape) if cfg.input_shape else None
    return load_partition(
        cfg.model_spec,
        cfg.cuts.names or "auto",
        cfg.cuts.max_cut_tensors,
        shape,
        segments=cfg.cuts.segments,
    )
