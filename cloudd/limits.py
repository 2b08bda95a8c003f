"""A cloud daemon's limits on what one request may cost it, and the checks that apply them.

Resolved once from the fleet file (`machines.<id>.limits`, `CloudLimitsConfig`):

- request payload (`max_request_bytes`, else the fleet's `max_payload_bytes`): the codec refuses
  a bigger payload on the service, probe and ctl keys before unpacking it (`too_large`);
- declared tensor size (`max_tensor_bytes`): a tensor whose dtype and shape declare more decoded
  bytes is refused before anything is decoded (`too_large`), whatever its codec compressed it to;
- probe echo (`max_echo_bytes`): a probe asking for a bigger echo is refused (`too_large`), so a
  few dozen bytes cannot make the deployment send back megabytes;
- video decoders (`max_video_streams`, `video_idle_s`): how many robots' h264 streams a service
  plane decodes at once, and how long an unused one is kept (`cloudd.video_streams`).

The in-flight limit per robot belongs to the queue (`batching.max_in_flight_per_robot`,
`cloudd.batch_queue`), which answers `busy`. Every check returns the error reply or None and
raises nothing; the callers count refusals (`cloudd.refusals`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from common.config import (
    DEFAULT_MAX_VIDEO_STREAMS,
    DEFAULT_VIDEO_IDLE_S,
    FleetConfig,
    MachineConfig,
)
from common.partition import TensorSpec
from common.wire import ErrorCode, ErrorReply
from common.wire.registry import ProbeRequest
from common.wire.robot_to_cloud import InferRequest


@dataclass(frozen=True)
class CloudLimits:
    """The limits of one deployment, in bytes."""

    request_bytes: int
    tensor_bytes: int
    echo_bytes: int
    video_streams: int = DEFAULT_MAX_VIDEO_STREAMS
    video_idle_s: float = DEFAULT_VIDEO_IDLE_S

    @classmethod
    def of(cls, cfg: FleetConfig, machine: MachineConfig) -> CloudLimits:
        """The machine's `limits` section, its request limit defaulting to the fleet's."""
        limits = machine.limits
        request_bytes = limits.max_request_bytes
        return cls(
            request_bytes=cfg.max_payload_bytes if request_bytes is None else request_bytes,
            tensor_bytes=limits.max_tensor_bytes,
            echo_bytes=limits.max_echo_bytes,
            video_streams=limits.max_video_streams,
            video_idle_s=limits.video_idle_s,
        )

    def describe(self) -> str:
        """One phrase for the ready line."""
        return (
            f"requests up to {self.request_bytes} bytes, tensors up to {self.tensor_bytes}, "
            f"probe echo up to {self.echo_bytes}"
        )

    def tensor_refusal(self, request: InferRequest) -> ErrorReply | None:
        """The error reply for the first tensor of `request` declaring more decoded bytes than
        `tensor_bytes`, or None."""
        for name, tensor in request.tensors.items():
            # Decoding the request checked each declaration (`check_encoded`): its dtype and
            # shape are valid, so only their size is read here.
            size = np.dtype(tensor.dtype).itemsize * math.prod(tensor.shape)
            if size > self.tensor_bytes:
                return ErrorReply.make(
                    ErrorCode.TOO_LARGE,
                    f"tensor {name!r}: {tensor.dtype}{list(tensor.shape)} decodes to {size} bytes, "
                    f"over this deployment's limit of {self.tensor_bytes} bytes "
                    "(limits.max_tensor_bytes)",
                )
        return None

    def echo_refusal(self, request: ProbeRequest) -> ErrorReply | None:
        """The error reply for a probe asking for more echo than `echo_bytes`, or None."""
        if request.echo_bytes <= self.echo_bytes:
            return None
        return ErrorReply.make(
            ErrorCode.TOO_LARGE,
            f"probe asks for an echo of {request.echo_bytes} bytes, over this deployment's cap of "
            f"{self.echo_bytes} bytes (limits.max_echo_bytes)",
        )

    def oversized_tensors(self, cut_specs: Sequence[Sequence[TensorSpec]]) -> list[str]:
        """The model's cut tensors bigger than `tensor_bytes` (`cut k 'name' (N bytes)`): every
        request for those cuts will be refused, which the daemon says at start."""
        return [
            f"cut {cut} {spec.name!r} ({spec.nbytes} bytes)"
            for cut, specs in enumerate(cut_specs)
            for spec in specs
            if spec.nbytes > self.tensor_bytes
        ]
