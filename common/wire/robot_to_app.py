"""What a robot publishes for the applications that use it: each applied frame's result, on
`keys.results_out` (`ef/<fleet>/out/<robot>`).

One `FrameResultMessage` per frame the robot applies, whichever path served it (the robot, the
cloud, a pool member, a fallback); a frame whose result was dropped as stale (pipelining) is not
published. The model's outputs travel by name as `EncodedTensor`s in a lossless-enough codec the
robot's config picks (`RESULT_CODECS`: raw by default, fp16 or zstd); an output the codec cannot
carry (fp16 of an integer tensor, or of a value past float16's range) goes raw. A reader decodes
them with `decode_tensors(message.outputs, max_bytes=...)`.

The layout is documented in docs/wire.md for clients in other languages: a msgpack map with the
envelope (`v`, `t`) and the fields below, tensors as maps {codec, dtype, shape, data}.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from common.wire.codec import Message, key_path, register
from common.wire.errors import InvalidValue, UnknownCodec
from common.wire.tensor_codecs import (
    CODEC_FP16,
    CODEC_RAW,
    CODEC_RAW_ZSTD,
    EncodedTensor,
    applies,
    check_encoded,
    encode_tensor_as,
)

# The codecs a robot's results may travel in: exact, or fp16 (a relative error of at most
# 2**-11 per value, the bound tests and clients compare with). Other lossy codecs (int8, JPEG)
# change answers and are refused when the config is read.
RESULT_CODECS = (CODEC_RAW, CODEC_FP16, CODEC_RAW_ZSTD)
# `zstd` in a config is the lossless raw+zstd.
RESULT_CODEC_ALIASES = {"zstd": CODEC_RAW_ZSTD}
FP16_RELATIVE_ERROR = 2.0**-11


class ServedBy(str, enum.Enum):
    """Whose result a frame applied: the robot's own run (P, or a fallback, or a hedge the robot
    won) or the cloud's reply."""

    ROBOT = "robot"
    CLOUD = "cloud"


def result_codec(name: str) -> str:
    """The wire name of result codec `name` (`zstd` is `raw+zstd`); UnknownCodec naming the
    allowed ones for anything else, lossy codecs included."""
    codec = RESULT_CODEC_ALIASES.get(name, name)
    if codec not in RESULT_CODECS:
        allowed = ", ".join((*RESULT_CODECS, *RESULT_CODEC_ALIASES))
        raise UnknownCodec(
            f"results codec {name!r} is not allowed; allowed: {allowed} (results are not sent "
            "in a codec that changes their values beyond fp16's rounding)"
        )
    return codec


def encode_output(array: np.ndarray, codec: str) -> EncodedTensor:
    """One output in result codec `codec`, or raw where that codec cannot carry it (fp16 of an
    integer tensor, or of values past float16's range)."""
    if codec != CODEC_RAW and applies(codec, array.dtype, array.shape):
        try:
            return encode_tensor_as(array, codec)
        except InvalidValue:  # fp16 overflow: raw keeps the value
            pass
    return encode_tensor_as(array, CODEC_RAW)


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class FrameResultMessage(Message):
    """Frame `frame` (the robot's frame number, from 0) of robot `robot` was applied.

    `stamp_ns`: the frame's capture stamp, ns since the epoch (the source's: a `zenoh` frame's
    own stamp, a ROS header's; else when the robot read the frame). `served_by`: whose result it
    is; `deployment`: the deployment that answered (None when the robot served it). `action`:
    the telemetry's action label ("P", "cut:<k>[:<codec>]", "cut:<k>-<e>[:<codec>]"), with its
    `cut` (None for P) and `codec` (of the tensors sent; None for P). `fallback`: offloaded, but
    finished on the robot. `latency_s`: end to end, from the frame's read to its result.
    `published_ns`: the robot's wall clock when it published this (its age is published_ns -
    stamp_ns on one clock). `outputs`: the model's outputs by name."""

    TYPE: ClassVar[str] = "frame_result"
    robot: str
    frame: int
    stamp_ns: int
    served_by: ServedBy
    deployment: str | None
    action: str
    cut: int | None
    codec: str | None
    fallback: bool
    latency_s: float
    published_ns: int
    outputs: dict[str, EncodedTensor]
    service: str | None = None

    def __post_init__(self) -> None:
        self._check_ids("robot", "deployment", "service")
        self._check_non_negative("frame", "stamp_ns", "cut", "latency_s", "published_ns")
        self._check_finite("latency_s")
        if not self.action:
            raise self._invalid("action", "must not be empty")
        for name, tensor in self.outputs.items():
            if not isinstance(tensor, EncodedTensor):
                raise self._invalid(
                    "outputs", f"{name!r} is a {type(tensor).__name__}, expected an EncodedTensor"
                )
            check_encoded(tensor, key_path(f"{self.TYPE}.outputs", name))


__all__ = [
    "FP16_RELATIVE_ERROR",
    "RESULT_CODECS",
    "FrameResultMessage",
    "ServedBy",
    "encode_output",
    "result_codec",
]
