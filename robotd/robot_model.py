"""The robot's split model as its frame loop uses it.

`open_split_model` loads the fleet's model at startup: its partition at the configured cuts, as
one set of shared-weight onnxruntime sessions for this machine (the caller hands it to the
lifecycle, which closes it). `RobotModel` is what the loop needs around those sessions: the one
camera input (the adapter that turns a frame into the model's input), the startup profile the
policies start from (`robotd.robot_profile`), the position of each cut index in the partition,
and the check of a cloud reply against the model's outputs (a reply that
lacks one is a decode error: the robot finishes the frame itself).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from common.config import FleetConfig, MachineConfig
from common.errors import UserError
from common.image_input import InputAdapter
from common.partition import load_partition, sample_feeds
from common.split_runtime import SplitModel
from common.wire.telemetry import FallbackReason
from robotd.offload import CallResult
from robotd.policies import Decision
from robotd.robot_profile import measured_profile


def open_split_model(config: FleetConfig, machine: MachineConfig) -> SplitModel:
    """The fleet's model, partitioned at its cuts, as sessions on `machine`'s providers."""
    shape = tuple(config.input_shape) if config.input_shape else None
    partition = load_partition(
        config.model, config.cuts.names or "auto", config.cuts.max_cut_tensors, shape
    )
    return SplitModel(partition, providers=machine.providers, threads=machine.threads or None)


class RobotModel:
    """`RobotModel(model, name)`: UserError unless `model` (called `name` in messages) takes
    one input, the camera frame."""

    def __init__(self, model: SplitModel, name: str) -> None:
        specs = model.input_specs()
        if len(specs) != 1:
            names = ", ".join(s.name for s in specs)
            raise UserError(f"the robot feeds one camera frame; model {name} has inputs {names}")
        self.model = model
        self.input_name = specs[0].name
        self.adapter = InputAdapter(specs[0])
        # Input of the model's shape and type, for the warm-up and the startup profile.
        self.sample_feeds = sample_feeds(specs)
        self._position = {cut.index: k for k, cut in enumerate(model.partition.cuts)}

    def profile(
        self, config: FleetConfig, *, source_spec: str, seed: int, threads: int, policy_spec: str
    ) -> dict[str, Any]:
        """This robot's profile, measured here (`robotd.robot_profile.measured_profile`)."""
        return measured_profile(
            self.model,
            self.sample_feeds,
            config=config,
            adapter=self.adapter,
            source_spec=source_spec,
            seed=seed,
            threads=threads,
            policy_spec=policy_spec,
        )

    def feeds(self, frame: np.ndarray) -> dict[str, np.ndarray]:
        """The model's input for camera frame `frame`."""
        return {self.input_name: self.adapter(frame)}

    def position_of(self, decision: Decision, policy: str) -> int:
        """The partition position of the cut `decision` chose; a UserError naming `policy` and
        the model's cuts when it has no such cut."""
        try:
            return self._position[int(decision.action)]
        except (KeyError, ValueError):
            known = ", ".join(str(i) for i in self._position)
            raise UserError(
                f"policy {policy} chose cut {decision.action!r}; this model has cuts {known}"
            ) from None

    def checked(self, result: CallResult) -> CallResult:
        """`result`, or a decode error when its reply lacks an output of the model (the frame is
        then finished on the robot)."""
        reply = result.reply
        if reply is None:
            return result
        missing = [n for n in self.model.output_names if n not in reply.outputs]
        if not missing:
            return result
        return dataclasses.replace(
            result,
            reply=None,
            reason=FallbackReason.DECODE_ERROR,
            detail=f"reply from {reply.deployment} lacks output(s) {', '.join(missing)}",
        )
