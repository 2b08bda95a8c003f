"""The wire format: one codec (`codec`) and the messages, grouped by who sends them.

- `robot_to_cloud`: InferRequest.
- `cloud_to_robot`: InferReply, BusyReply (and ErrorReply, which any replier may send).
- `registry`: registration, probe, control, routes, drain, RIB views (registry <-> daemons).
- `telemetry`: what a robot publishes for anyone (per-frame records, probe reports).

Typical use::

    payload = InferRequest(...).to_wire()
    try:
        request = InferRequest.from_wire(query_payload, max_bytes=limit)
    except WireError as exc:
        query.reply(key, error_reply(exc))

Only this package imports msgpack.
"""

from common.wire import cloud_to_robot, registry, robot_to_cloud, telemetry
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
    ErrorCode,
    InvalidValue,
    MalformedPayload,
    MissingField,
    PayloadTooLarge,
    ShapeMismatch,
    TrailingBytes,
    UnexpectedMessageType,
    UnknownMessageType,
    UnknownSchemaVersion,
    WireError,
    WrongFieldType,
)

__all__ = [
    "DEFAULT_MAX_PAYLOAD_BYTES",
    "DTYPES",
    "SCHEMA_VERSION",
    "BadDtype",
    "ErrorCode",
    "ErrorReply",
    "InvalidValue",
    "MalformedPayload",
    "Message",
    "MissingField",
    "PayloadTooLarge",
    "ShapeMismatch",
    "Struct",
    "TrailingBytes",
    "UnexpectedMessageType",
    "UnknownMessageType",
    "UnknownSchemaVersion",
    "WireError",
    "WrongFieldType",
    "cloud_to_robot",
    "decode",
    "decode_tensor",
    "encode",
    "encode_raw",
    "encode_tensor",
    "error_reply",
    "registry",
    "robot_to_cloud",
    "telemetry",
    "to_jsonable",
]
