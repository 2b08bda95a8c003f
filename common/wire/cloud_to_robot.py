"""Replies a deployment sends to a robot's `InferRequest`.

Exactly one of `InferReply`, `BusyReply` or `ErrorReply` answers each request, so a robot decodes
with `decode(payload, expect=INFER_REPLIES)`. Busy and error replies are answered at once so the
robot can finish the frame locally without waiting for its deadline.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from common.wire.codec import ErrorReply, Message, register


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class InferReply(Message):
    """The suffix's outputs by name (for a segment request, `InferRequest.end_cut`'s tensors,
    lossless), with the deployment's own timings: `queue_s` waiting for a
    worker, `compute_s` running the suffix (so the robot can split latency into transfer and
    compute). `epoch` is the deployment's epoch for this robot's service state."""

    TYPE: ClassVar[str] = "infer_reply"
    frame: int
    deployment: str
    epoch: int
    outputs: dict[str, np.ndarray]
    queue_s: float
    compute_s: float

    def __post_init__(self) -> None:
        self._check_ids("deployment")
        self._check_non_negative("frame", "epoch", "queue_s", "compute_s")
        self._check_finite("queue_s", "compute_s")


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class BusyReply(Message):
    """The deployment's queue is full: `queued` requests wait for `capacity` slots."""

    TYPE: ClassVar[str] = "busy"
    frame: int
    deployment: str
    queued: int
    capacity: int

    def __post_init__(self) -> None:
        self._check_ids("deployment")
        self._check_non_negative("frame", "queued", "capacity")


INFER_REPLIES: tuple[type[Message], ...] = (InferReply, BusyReply, ErrorReply)

__all__ = ["INFER_REPLIES", "BusyReply", "ErrorReply", "InferReply"]
