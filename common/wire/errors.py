"""Named decode errors and the machine-readable error codes carried by error replies.

Every way a payload can be wrong has its own `WireError` subclass with a stable `code`, so a
queryable can turn any decode failure into an `ErrorReply(code, reason)` without a traceback and
keep serving. `WireError` is a ValueError: code that only cares about "bad input" can catch that.
The application-level codes (unknown cut, wrong model digest, stale epoch...) are not raised by the
codec; daemons put them in their error replies so every peer reads the same vocabulary.
"""

from __future__ import annotations

import enum
from typing import ClassVar


class ErrorCode(str, enum.Enum):
    """Machine-readable reason of an error reply (the wire carries the string value)."""

    # Raised by the codec.
    MALFORMED = "malformed"
    SCHEMA_VERSION = "schema_version"
    TRAILING_BYTES = "trailing_bytes"
    TOO_LARGE = "too_large"
    UNKNOWN_TYPE = "unknown_type"
    UNEXPECTED_TYPE = "unexpected_type"
    MISSING_FIELD = "missing_field"
    WRONG_TYPE = "wrong_type"
    BAD_VALUE = "bad_value"
    BAD_DTYPE = "bad_dtype"
    SHAPE_MISMATCH = "shape_mismatch"
    # Raised by the tensor codecs (tensor_codecs).
    UNKNOWN_CODEC = "unknown_codec"
    CODEC_MISMATCH = "codec_mismatch"
    CORRUPT_PAYLOAD = "corrupt_payload"
    BAD_QUANTIZATION = "bad_quantization"
    # Used by daemons in their replies.
    UNKNOWN_CUT = "unknown_cut"
    MODEL_DIGEST = "model_digest"
    NOT_SERVING = "not_serving"
    WRONG_ROBOT = "wrong_robot"  # the body names another robot than the key it came on
    DEADLINE_EXPIRED = "deadline_expired"
    STALE_EPOCH = "stale_epoch"
    PROTOCOL_VERSION = "protocol_version"
    REFUSED = "refused"
    UNKNOWN_SERVICE = "unknown_service"  # not a service of the fleet, or not served there
    # A video P-frame whose reference picture the deployment's decoder does not hold: the robot
    # resends the frame as a keyframe (or finishes it itself).
    NEED_KEYFRAME = "need_keyframe"
    INTERNAL = "internal"


class WireError(ValueError):
    """A payload that cannot be decoded (or a message that cannot be encoded); `str()` is the
    reason, one line naming the problem."""

    code: ClassVar[ErrorCode] = ErrorCode.MALFORMED

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class MalformedPayload(WireError):
    """Not msgpack, not a map at the top level, or invalid UTF-8."""

    code = ErrorCode.MALFORMED


class UnknownSchemaVersion(WireError):
    """The envelope's schema version is missing or not one this build reads."""

    code = ErrorCode.SCHEMA_VERSION


class TrailingBytes(WireError):
    """Bytes left over after the message."""

    code = ErrorCode.TRAILING_BYTES


class PayloadTooLarge(WireError):
    """The payload is bigger than the configured limit (checked before unpacking)."""

    code = ErrorCode.TOO_LARGE


class UnknownMessageType(WireError):
    """The envelope names a message type this build does not know."""

    code = ErrorCode.UNKNOWN_TYPE


class UnexpectedMessageType(WireError):
    """A known message type, but not one this key accepts."""

    code = ErrorCode.UNEXPECTED_TYPE


class MissingField(WireError):
    """A required field is absent."""

    code = ErrorCode.MISSING_FIELD


class WrongFieldType(WireError):
    """A field has the wrong type (e.g. a string where an integer belongs)."""

    code = ErrorCode.WRONG_TYPE


class InvalidValue(WireError):
    """A field has the right type but an impossible value (negative frame, drop rate above 1...)."""

    code = ErrorCode.BAD_VALUE


class BadDtype(WireError):
    """A tensor's dtype is not on the allow-list."""

    code = ErrorCode.BAD_DTYPE


class ShapeMismatch(WireError):
    """A tensor's shape does not match its byte count (or is not a list of sizes), or an encoded
    image's header disagrees with the declared shape."""

    code = ErrorCode.SHAPE_MISMATCH


class TensorTooLarge(PayloadTooLarge):
    """An encoded tensor declares a decoded size over the receiver's limit (checked before
    decompressing or decoding anything: a size bomb)."""

    code = ErrorCode.TOO_LARGE


class UnknownCodec(WireError):
    """A tensor codec name this build does not know."""

    code = ErrorCode.UNKNOWN_CODEC


class CodecMismatch(WireError):
    """A known codec that does not apply to the tensor's dtype or shape (e.g. jpeg for float32)."""

    code = ErrorCode.CODEC_MISMATCH


class CorruptPayload(WireError):
    """Encoded tensor data that cannot be decoded: corrupt zstd, JPEG or PNG bytes, or a zstd
    frame that does not hold the expected number of bytes."""

    code = ErrorCode.CORRUPT_PAYLOAD


class BadQuantization(WireError):
    """int8 parameters missing, of the wrong length or dtype, a scale that is not finite and
    positive, a zero point not a whole number in 0..255, or parameters on a non-int8 tensor."""

    code = ErrorCode.BAD_QUANTIZATION


class NeedKeyframe(WireError):
    """A video P-frame that the receiver's decoder cannot decode: it holds no picture of the
    frame's stream, or not the one the frame is predicted from (frames were lost, refused or
    served elsewhere, the decoder was freed). Resending the frame as a keyframe cures it."""

    code = ErrorCode.NEED_KEYFRAME
