"""The wire format: one codec (`codec`) and the messages, grouped by who sends them.

- `robot_to_cloud`: InferRequest, whose tensors are `EncodedTensor`s (`tensor_codecs`: raw, fp16,
  int8, int8+zstd, raw+zstd, jpeg<Q>, png, h264; decoded strictly, within the receiver's limit;
  h264's streams through `video_codec`).
- `cloud_to_robot`: InferReply, BusyReply (and ErrorReply, which any replier may send).
- `registry`: registration, probe, control, routes, drain, RIB views (registry <-> daemons).
- `telemetry`: what a robot publishes for anyone (per-frame records, probe reports).
- `robot_to_app`: FrameResultMessage, each applied frame's result for applications (`out/<robot>`).
- `app_to_robot`: FrameIn, a camera frame an application sends a robot (`in/<robot>`).

Typical use::

    payload = InferRequest(..., tensors={"x": encode_tensor_as(x, "int8+zstd")}).to_wire()
    try:
        request = InferRequest.from_wire(query_payload, max_bytes=limit)
        tensors = decode_tensors(request.tensors, max_bytes=limit)
    except WireError as exc:
        query.reply(key, error_reply(exc))

Only this package imports msgpack.
"""

from common.wire import (
    app_to_robot,
    cloud_to_robot,
    registry,
    robot_to_app,
    robot_to_cloud,
    telemetry,
    tensor_codecs,
)
from common.wire.codec import (
    DEFAULT_MAX_PAYLOAD_BYTES,
    DTYPES,
    SCHEMA_VERSION,
    ErrorReply,
    Message,
    Struct,
    decode,
    decode_tensor,
    encode,
    encode_raw,
    encode_tensor,
    error_reply,
    to_jsonable,
)
from common.wire.errors import (
    BadDtype,
    BadQuantization,
    CodecMismatch,
    CorruptPayload,
    ErrorCode,
    InvalidValue,
    MalformedPayload,
    MissingField,
    NeedKeyframe,
    PayloadTooLarge,
    ShapeMismatch,
    TensorTooLarge,
    TrailingBytes,
    UnexpectedMessageType,
    UnknownCodec,
    UnknownMessageType,
    UnknownSchemaVersion,
    WireError,
    WrongFieldType,
)
from common.wire.tensor_codecs import (
    CODEC_RAW,
    Codec,
    EncodedTensor,
    applies,
    codec_names_for,
    decode_encoded,
    decode_tensors,
    encode_tensor_as,
    parse_codec,
)

__all__ = [
    "CODEC_RAW",
    "DEFAULT_MAX_PAYLOAD_BYTES",
    "DTYPES",
    "SCHEMA_VERSION",
    "BadDtype",
    "BadQuantization",
    "Codec",
    "CodecMismatch",
    "CorruptPayload",
    "EncodedTensor",
    "ErrorCode",
    "ErrorReply",
    "InvalidValue",
    "MalformedPayload",
    "Message",
    "MissingField",
    "NeedKeyframe",
    "PayloadTooLarge",
    "ShapeMismatch",
    "Struct",
    "TensorTooLarge",
    "TrailingBytes",
    "UnexpectedMessageType",
    "UnknownCodec",
    "UnknownMessageType",
    "UnknownSchemaVersion",
    "WireError",
    "WrongFieldType",
    "app_to_robot",
    "applies",
    "cloud_to_robot",
    "codec_names_for",
    "decode",
    "decode_encoded",
    "decode_tensor",
    "decode_tensors",
    "encode",
    "encode_raw",
    "encode_tensor",
    "encode_tensor_as",
    "error_reply",
    "parse_codec",
    "registry",
    "robot_to_app",
    "robot_to_cloud",
    "telemetry",
    "tensor_codecs",
    "to_jsonable",
]
