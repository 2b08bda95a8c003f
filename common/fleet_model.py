"""The fleet's model as its daemons split it: one call, so that whoever splits it ahead of them
(the demo, the testbed, the load generator) fills the very cache entry the daemons then read.
A handler's service is split the same way: the identity graph of its image, one cut (0), run by
`common.handler_model.HandlerModel`."""

from __future__ import annotations

from typing import Any

from common.config import FleetConfig
from common.partition import Partition, load_partition
from common.partition.runtime import SplitModel
from common.zoo import DEFAULT_INPUT_SHAPE


def fleet_partition(cfg: FleetConfig) -> Partition:
    """`cfg.model` split at the fleet's cuts (`cuts.names`, `cuts.max_cut_tensors`, segments
    when `cuts.segments`) for its `input_shape`, from the partition cache when it is there. A
    zoo model is built with the fleet's build options (`FleetConfig.zoo_options`: zoo:stereo
    for the `nav.camera` geometry), so robot and deployments hold the same file and digest."""
    if cfg.handler is not None:
        from common.handlers import identity_model_path

        return load_partition(identity_model_path(handler_image_shape(cfg)))
    shape = tuple(cfg.input_shape) if cfg.input_shape else None
    return load_partition(
        cfg.model_spec,
        cfg.cuts.names or "auto",
        cfg.cuts.max_cut_tensors,
        shape,
        segments=cfg.cuts.segments,
        zoo_options=cfg.zoo_options,
    )


def handler_image_shape(cfg: FleetConfig) -> tuple[int, int, int]:
    """A handler's image (C, H, W): the service's input_shape, else the fleet's, else the zoo's
    default (a deployment must know it before any robot sends a frame)."""
    shape = cfg.input_shape or list(DEFAULT_INPUT_SHAPE)
    if len(shape) != 3:
        from common.errors import UserError

        raise UserError(
            f"services.{cfg.service_name}.input_shape: a handler's image is C, H, W; got {shape}"
        )
    c, h, w = shape
    return (c, h, w)


def fleet_split_model(cfg: FleetConfig, **options: Any) -> SplitModel:
    """The (first) service's model as sessions (`SplitModel` options), or its handler's
    `HandlerModel`."""
    partition = fleet_partition(cfg)
    if cfg.handler is None:
        return SplitModel(partition, **options)
    from common.handler_model import HandlerModel
    from common.handlers import load_handler

    base = cfg.source_path.resolve().parent if cfg.source_path is not None else None
    handler = load_handler(cfg.handler, cfg.service_config.params, base)
    return HandlerModel(partition, handler, **options)
