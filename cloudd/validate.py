"""Checks an inference request against the model this deployment serves, before any work.

The codec already refused what cannot be a request (garbage, unknown schema version, bad dtype
names, shape/byte-count mismatch, oversize payload). What is left is whether a well-formed request
fits its key and *this* model: the robot it names (the ACL lets a robot query only its own
service key; this makes the body agree with the key: `wrong_robot`), the model digest, the cut
index, and the cut's tensors by name and declared dtype and shape (`SplitModel.cut_tensor_specs`).
Each problem is an `ErrorReply` with a code and a one-line reason the robot can log; nothing here
raises. The tensors' codecs are decoded later, on a worker (`decode_tensors`), into exactly
those sizes; a video codec's tensors were decoded at admission, in their stream's order
(`cloudd.video_streams`), and are passed in.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from common.partition import TensorSpec
from common.wire import ErrorCode, ErrorReply
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import decode_encoded

DIGEST_SHOWN_CHARS = 12


def _names(names: Sequence[str]) -> str:
    return ", ".join(repr(n) for n in names)


def _shape(shape: Sequence[int]) -> str:
    return "[" + ", ".join(str(d) for d in shape) + "]"


def decode_tensors(
    request: InferRequest,
    specs: Sequence[TensorSpec],
    decoded: Mapping[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """The request's tensors decoded from their codecs (after `check_request` passed): each
    into at most its spec's bytes, those in `decoded` (video, decoded at admission) as they
    are. Raises the codec's WireError, which names the problem."""
    done = decoded or {}
    return {
        spec.name: done[spec.name]
        if spec.name in done
        else decode_encoded(request.tensors[spec.name], max_bytes=spec.nbytes, name=spec.name)
        for spec in specs
    }


def check_request(
    request: InferRequest,
    *,
    robot: str,
    digest: str,
    cut_specs: Sequence[Sequence[TensorSpec]],
) -> ErrorReply | None:
    """The error reply for `request` arriving on `robot`'s service key, or None if this
    deployment can compute it. `cut_specs[k]` are the tensors crossing cut k."""
    if request.robot != robot:
        return ErrorReply.make(
            ErrorCode.WRONG_ROBOT,
            f"request names robot {request.robot!r} but came on the service key of {robot!r}",
        )
    if request.model_digest != digest:
        return ErrorReply.make(
            ErrorCode.MODEL_DIGEST,
            f"model digest {request.model_digest[:DIGEST_SHOWN_CHARS]!r} does not match this "
            f"deployment's model {digest[:DIGEST_SHOWN_CHARS]!r}: robot and cloud must load the "
            "same model",
        )
    if not 0 <= request.cut < len(cut_specs):
        return ErrorReply.make(
            ErrorCode.UNKNOWN_CUT,
            f"unknown cut {request.cut}: this model has cuts 0..{len(cut_specs) - 1}",
        )
    specs = cut_specs[request.cut]
    expected = [spec.name for spec in specs]
    missing = [name for name in expected if name not in request.tensors]
    if missing:
        return ErrorReply.make(
            ErrorCode.MISSING_FIELD,
            f"cut {request.cut} needs tensor(s) {_names(expected)}; missing {_names(missing)}",
        )
    extra = [name for name in request.tensors if name not in expected]
    if extra:
        return ErrorReply.make(
            ErrorCode.BAD_VALUE,
            f"cut {request.cut} takes tensor(s) {_names(expected)}; unexpected {_names(extra)}",
        )
    for spec in specs:
        # The declared dtype and shape are checked here, before any decoding: the codec then
        # decodes into exactly the spec's size (a size bomb is refused unopened).
        tensor = request.tensors[spec.name]
        if tensor.dtype != spec.dtype:
            return ErrorReply.make(
                ErrorCode.BAD_DTYPE,
                f"tensor {spec.name!r} of cut {request.cut}: dtype {tensor.dtype}, "
                f"expected {spec.dtype}",
            )
        if tuple(tensor.shape) != tuple(spec.shape):
            return ErrorReply.make(
                ErrorCode.SHAPE_MISMATCH,
                f"tensor {spec.name!r} of cut {request.cut}: shape {_shape(tensor.shape)}, "
                f"expected {_shape(spec.shape)}",
            )
    return None
