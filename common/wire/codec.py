"""The one codec: messages as msgpack maps with a schema version, tensors as {dtype, shape, bytes}.

Envelope: a msgpack map `{"v": SCHEMA_VERSION, "t": <message type>, <field>: <value>, ...}`. Fields
are the message dataclass's fields by name; unknown fields are ignored (a newer sender may add
fields), missing fields with a default take the default (an older sender may omit them), missing
required fields are an error.

A tensor is the map `{"dtype": <name>, "shape": [<int>...], "bytes": <bin>}` with little-endian
data in C order; dtypes come from an allow-list. msgpack copies a `bin` once while unpacking; the
array is then a read-only `numpy.frombuffer` view of those bytes, with no further copy. The
tensors of an `InferRequest` travel instead as `EncodedTensor` records naming a per-tensor codec
(raw, fp16, int8, zstd, JPEG, PNG: see `tensor_codecs`), decoded by the receiver with its limit.

Decoding is strict and total: for *any* input, `decode` returns a message or raises a
`WireError` subclass whose message names the problem (size limit, not msgpack, trailing bytes,
unknown schema version or message type, missing field, wrong type, bad dtype, shape/byte-count
mismatch, bad value). It is on the per-frame path, so each message class's field decoders are
built once, when the class is registered.

Only this package imports msgpack.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from collections.abc import Callable
from typing import Any, ClassVar, Literal, TypeVar, Union, overload

import msgpack
import numpy as np

from common.keys import InvalidIdError, validate_id
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

# 2: InferRequest tensors are EncodedTensor records (per-tensor codecs) instead of raw tensors.
SCHEMA_VERSION = 2
SUPPORTED_SCHEMA_VERSIONS = frozenset({SCHEMA_VERSION})
VERSION_FIELD = "v"
TYPE_FIELD = "t"

# Bigger payloads are refused before unpacking. 64 MiB holds the raw input of any model in the zoo
# many times over; daemons pass their configured limit (fleet.yaml `max_payload_bytes`).
DEFAULT_MAX_PAYLOAD_BYTES = 64 * 1024 * 1024
MAX_TENSOR_NDIM = 16
# Free-form (`Any`) fields hold JSON-like data; this bounds their nesting.
MAX_ANY_DEPTH = 32

# dtype name on the wire -> little-endian numpy dtype. ONNX tensor types numpy can represent.
DTYPES: dict[str, np.dtype[Any]] = {
    name: np.dtype(name).newbyteorder("<")
    for name in (
        "bool",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "float16",
        "float32",
        "float64",
    )
}

Buffer = bytes | bytearray | memoryview
_Decoder = Callable[[Any, str], Any]
_Encoder = Callable[[Any], Any]
S = TypeVar("S", bound="Struct")
M = TypeVar("M", bound="Message")


def _type_name(value: object) -> str:
    return {
        dict: "map",
        list: "array",
        str: "string",
        bytes: "bytes",
        bool: "bool",
        int: "integer",
        float: "float",
        type(None): "nil",
    }.get(type(value), type(value).__name__)


# -- tensors ---------------------------------------------------------------------------------------
def encode_tensor(array: np.ndarray) -> dict[str, Any]:
    """The wire map of one array (little-endian, C order; a copy only if the array is not)."""
    if isinstance(array, np.generic):  # a numpy scalar (e.g. from a reduction) is a 0-d tensor
        array = np.asarray(array)
    if not isinstance(array, np.ndarray):
        raise WrongFieldType(f"tensor: expected a numpy array, got {type(array).__name__}")
    dtype = DTYPES.get(array.dtype.name)
    if dtype is None:
        raise BadDtype(f"tensor: dtype {array.dtype.name!r} is not allowed; allowed: {_ALLOWED}")
    if array.dtype != dtype or not array.flags.c_contiguous:
        array = np.ascontiguousarray(array, dtype=dtype)
    # A flat uint8 view packs as one msgpack bin without a tobytes() copy.
    data: Buffer = array.reshape(-1).view(np.uint8).data if array.nbytes else b""
    return {"dtype": dtype.name, "shape": list(array.shape), "bytes": data}


def decode_tensor(value: Any, path: str = "tensor") -> np.ndarray:
    """The array of one wire map: a read-only view of the received bytes, checked for dtype and
    for shape against byte count."""
    if type(value) is not dict:
        raise WrongFieldType(f"{path}: expected a tensor map, got {_type_name(value)}")
    try:
        dtype_name, shape, data = value["dtype"], value["shape"], value["bytes"]
    except KeyError as exc:
        raise MissingField(f"{path}: tensor is missing {exc.args[0]!r}") from None
    dtype = DTYPES.get(dtype_name) if type(dtype_name) is str else None
    if dtype is None:
        raise BadDtype(f"{path}.dtype: {dtype_name!r} is not allowed; allowed: {_ALLOWED}")
    if type(shape) is not list or len(shape) > MAX_TENSOR_NDIM:
        raise ShapeMismatch(f"{path}.shape: expected a list of at most {MAX_TENSOR_NDIM} sizes")
    count = 1
    for size in shape:
        if type(size) is not int or size < 0:
            raise ShapeMismatch(f"{path}.shape: sizes must be non-negative integers, got {shape}")
        count *= size
    if type(data) is not bytes:
        raise WrongFieldType(f"{path}.bytes: expected bytes, got {_type_name(data)}")
    if count * dtype.itemsize != len(data):
        raise ShapeMismatch(
            f"{path}: shape {shape} of {dtype.name} needs {count * dtype.itemsize} bytes, "
            f"got {len(data)}"
        )
    try:
        array = np.frombuffer(data, dtype=dtype).reshape(shape)
    except ValueError:  # e.g. shape [0, 2**70]: no elements, but dimensions numpy cannot hold
        raise ShapeMismatch(f"{path}.shape: {shape} is too large for an array") from None
    if dtype.kind == "b" and array.size and array.view(np.uint8).max() > 1:
        raise InvalidValue(f"{path}: bool tensor holds bytes other than 0 and 1")
    return array


_ALLOWED = ", ".join(DTYPES)
_READS = (
    "this build reads schema version"
    + ("s " if len(SUPPORTED_SCHEMA_VERSIONS) > 1 else " ")
    + ", ".join(str(v) for v in sorted(SUPPORTED_SCHEMA_VERSIONS))
)


# -- field decoders and encoders, built from type hints --------------------------------------------
def _decode_str(value: Any, path: str) -> str:
    if type(value) is not str:
        raise WrongFieldType(f"{path}: expected string, got {_type_name(value)}")
    return value


def _decode_bytes(value: Any, path: str) -> bytes:
    if type(value) is not bytes:
        raise WrongFieldType(f"{path}: expected bytes, got {_type_name(value)}")
    return value


def _decode_bool(value: Any, path: str) -> bool:
    if type(value) is not bool:
        raise WrongFieldType(f"{path}: expected bool, got {_type_name(value)}")
    return value


def _decode_int(value: Any, path: str) -> int:
    if type(value) is not int:
        raise WrongFieldType(f"{path}: expected integer, got {_type_name(value)}")
    return value


def _decode_float(value: Any, path: str) -> float:
    kind = type(value)
    if kind is float:
        return value
    if kind is int:
        return float(value)
    raise WrongFieldType(f"{path}: expected number, got {_type_name(value)}")


def _decode_none(value: Any, path: str) -> None:
    if value is not None:
        raise WrongFieldType(f"{path}: expected nil, got {_type_name(value)}")


def _decode_any(value: Any, path: str, depth: int = 0) -> Any:
    """JSON-like data only (what `--json` can print): nil, bool, numbers, strings, arrays, maps."""
    if depth > MAX_ANY_DEPTH:
        raise InvalidValue(f"{path}: nested deeper than {MAX_ANY_DEPTH} levels")
    kind = type(value)
    if value is None or kind in (bool, int, float, str):
        return value
    if kind is list:
        return [_decode_any(v, f"{path}[{i}]", depth + 1) for i, v in enumerate(value)]
    if kind is dict:
        _check_keys(value, path)
        return {k: _decode_any(v, key_path(path, k), depth + 1) for k, v in value.items()}
    raise WrongFieldType(f"{path}: expected JSON-like data, got {_type_name(value)}")


def key_path(path: str, key: str) -> str:
    """`path.key` for an error reason, the key quoted when it holds a newline or another
    character that does not print: reasons are logged and sent back on one line, and a sender's
    map key must not forge a log line (found by tests/unit/test_fuzz_wire.py)."""
    return f"{path}.{key}" if key.isprintable() else f"{path}.{key!r}"


def _check_keys(value: dict[Any, Any], path: str) -> None:
    for key in value:
        if type(key) is not str:
            raise WrongFieldType(f"{path}: map keys must be strings, got {_type_name(key)}")


_SIMPLE_DECODERS: dict[Any, _Decoder] = {
    str: _decode_str,
    bytes: _decode_bytes,
    # A field typed Buffer is bytes when decoded, and any bytes-like object when built locally
    # (e.g. a memoryview of an array's data, sent without a copy): msgpack packs them all as bin.
    Buffer: _decode_bytes,
    bool: _decode_bool,
    int: _decode_int,
    float: _decode_float,
    type(None): _decode_none,
    Any: _decode_any,
}


def _decoder_for(tp: Any) -> _Decoder:
    simple = _SIMPLE_DECODERS.get(tp)
    if simple is not None:
        return simple
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is np.ndarray or origin is np.ndarray:
        return decode_tensor
    if origin in (Union, types.UnionType):
        members = [a for a in args if a is not type(None)]
        if len(members) != 1 or len(args) != 2:
            raise TypeError(f"only `X | None` unions are supported on the wire, not {tp}")
        inner = _decoder_for(members[0])

        def optional(value: Any, path: str) -> Any:
            return None if value is None else inner(value, path)

        return optional
    if origin is Literal:
        allowed = args

        def literal(value: Any, path: str) -> Any:
            if type(value) is not str or value not in allowed:
                choices = ", ".join(repr(a) for a in allowed)
                raise InvalidValue(f"{path}: expected one of {choices}, got {value!r}")
            return value

        return literal
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        enum_type = tp

        def enum_member(value: Any, path: str) -> Any:
            try:
                return enum_type(value)
            except (ValueError, TypeError):
                choices = ", ".join(repr(m.value) for m in enum_type)
                raise InvalidValue(f"{path}: expected one of {choices}, got {value!r}") from None

        return enum_member
    if isinstance(tp, type) and issubclass(tp, Struct):
        struct_type = tp
        return lambda value, path: struct_type.from_map(value, path)
    if origin in (list, tuple):
        if origin is tuple and (len(args) != 2 or args[1] is not Ellipsis):
            raise TypeError(f"only homogeneous `tuple[X, ...]` is supported on the wire, not {tp}")
        item = _decoder_for(args[0])
        as_tuple = origin is tuple

        def sequence(value: Any, path: str) -> Any:
            if type(value) is not list:
                raise WrongFieldType(f"{path}: expected array, got {_type_name(value)}")
            items = [item(v, f"{path}[{i}]") for i, v in enumerate(value)]
            return tuple(items) if as_tuple else items

        return sequence
    if origin is dict:
        if args[0] is not str:
            raise TypeError(f"map keys on the wire are strings, not {args[0]}")
        item = _decoder_for(args[1])

        def mapping(value: Any, path: str) -> Any:
            if type(value) is not dict:
                raise WrongFieldType(f"{path}: expected map, got {_type_name(value)}")
            _check_keys(value, path)
            return {k: item(v, key_path(path, k)) for k, v in value.items()}

        return mapping
    raise TypeError(f"no wire decoder for {tp}")


def _encoder_for(tp: Any) -> _Encoder | None:
    """None where the value goes on the wire as it is."""
    if tp in _SIMPLE_DECODERS:
        return None
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is np.ndarray or origin is np.ndarray:
        return encode_tensor
    if origin in (Union, types.UnionType):
        inner_encoder = _encoder_for(next(a for a in args if a is not type(None)))
        if inner_encoder is None:
            return None
        return lambda value: None if value is None else inner_encoder(value)
    if origin is Literal:
        return None
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return lambda value: value.value
    if isinstance(tp, type) and issubclass(tp, Struct):
        return lambda value: value.to_map()
    if origin in (list, tuple):
        element = _encoder_for(args[0])
        if element is None:
            return list
        return lambda value: [element(v) for v in value]
    if origin is dict:
        entry = _encoder_for(args[1])
        if entry is None:
            return None
        return lambda value: {k: entry(v) for k, v in value.items()}
    raise TypeError(f"no wire encoder for {tp}")


@dataclasses.dataclass(frozen=True)
class _FieldCodec:
    name: str
    path: str  # "<struct>.<field>", the error path when the struct is decoded at the top level
    required: bool
    decode: _Decoder
    encode: _Encoder | None


_FIELD_CODECS: dict[type, tuple[_FieldCodec, ...]] = {}


def _field_codecs(cls: type) -> tuple[_FieldCodec, ...]:
    codecs = _FIELD_CODECS.get(cls)
    if codecs is None:
        hints = typing.get_type_hints(cls)
        codecs = tuple(
            _FieldCodec(
                name=f.name,
                path=f"{_struct_name(cls)}.{f.name}",
                required=f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING,
                decode=_decoder_for(hints[f.name]),
                encode=_encoder_for(hints[f.name]),
            )
            for f in dataclasses.fields(cls)
        )
        _FIELD_CODECS[cls] = codecs
    return codecs


# -- structs and messages --------------------------------------------------------------------------
class Struct:
    """Base of the wire dataclasses (declare them `@dataclass(frozen=True, slots=True,
    kw_only=True)`). Subclasses check values in `__post_init__` with `self._invalid(...)`, so a
    message built locally and one decoded from the wire pass the same checks."""

    __slots__ = ()

    def to_map(self) -> dict[str, Any]:
        """This struct as a msgpack-ready map."""
        out: dict[str, Any] = {}
        for fc in _field_codecs(type(self)):
            value = getattr(self, fc.name)
            out[fc.name] = value if fc.encode is None or value is None else fc.encode(value)
        return out

    @classmethod
    def from_map(cls: type[S], value: Any, path: str | None = None) -> S:
        """Build from a decoded map; unknown keys are ignored, missing ones take their default."""
        where = path or _struct_name(cls)
        if type(value) is not dict:
            raise WrongFieldType(f"{where}: expected map, got {_type_name(value)}")
        kwargs: dict[str, Any] = {}
        for fc in _field_codecs(cls):
            if fc.name in value:
                field_path = fc.path if path is None else f"{path}.{fc.name}"
                kwargs[fc.name] = fc.decode(value[fc.name], field_path)
            elif fc.required:
                raise MissingField(f"{where}: missing field {fc.name!r}")
        return cls(**kwargs)

    def _invalid(self, field: str, problem: str) -> InvalidValue:
        return InvalidValue(f"{_struct_name(type(self))}.{field}: {problem}")

    def _check_non_negative(self, *fields: str) -> None:
        for field in fields:
            value = getattr(self, field)
            if value is not None and not value >= 0:  # `not >=` also catches NaN
                raise self._invalid(field, f"must be >= 0, got {value}")

    def _check_positive(self, *fields: str) -> None:
        for field in fields:
            value = getattr(self, field)
            if value is not None and not value > 0:
                raise self._invalid(field, f"must be > 0, got {value}")

    def _check_ids(self, *fields: str) -> None:
        for field in fields:
            value = getattr(self, field)
            if value is None:
                continue
            try:
                validate_id(value, field)
            except InvalidIdError as exc:
                raise self._invalid(field, str(exc)) from None

    def _check_finite(self, *fields: str) -> None:
        for field in fields:
            value = getattr(self, field)
            if value is not None and not math.isfinite(value):
                raise self._invalid(field, f"must be finite, got {value}")


def _struct_name(cls: type) -> str:
    return getattr(cls, "TYPE", None) or cls.__name__


class Message(Struct):
    """A top-level wire message: a Struct with a registered `TYPE` tag."""

    __slots__ = ()
    TYPE: ClassVar[str]

    def to_wire(self) -> bytes:
        """Encode with the envelope (schema version and type tag)."""
        return encode(self)

    @classmethod
    def from_wire(cls: type[M], data: Buffer, *, max_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES) -> M:
        """Decode `data`, which must hold this message type; raises a WireError subclass."""
        return decode(data, expect=cls, max_bytes=max_bytes)


MESSAGE_TYPES: dict[str, type[Message]] = {}


def register(cls: type[M]) -> type[M]:
    """Class decorator: make a Message dataclass decodable by its TYPE tag."""
    tag = cls.__dict__.get("TYPE")
    if not isinstance(tag, str) or not tag:
        raise TypeError(f"{cls.__name__} needs a TYPE tag")
    if tag in MESSAGE_TYPES and MESSAGE_TYPES[tag] is not cls:
        raise TypeError(f"message type {tag!r} is registered twice")
    clash = {f.name for f in dataclasses.fields(typing.cast(Any, cls))} & {
        VERSION_FIELD,
        TYPE_FIELD,
    }
    if clash:
        raise TypeError(f"{cls.__name__}: field names {clash} are reserved for the envelope")
    _field_codecs(cls)  # fail at import, not on the first frame, if a field type is unsupported
    MESSAGE_TYPES[tag] = cls
    return cls


@register
@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class ErrorReply(Message):
    """Any replier -> any querier: the request was refused or failed. `code` is an ErrorCode value
    (kept a string so a newer peer's codes still decode); `reason` is one line for a person."""

    TYPE: ClassVar[str] = "error"
    code: str
    reason: str

    @classmethod
    def of(cls, error: WireError) -> ErrorReply:
        """The reply for a decode failure."""
        return cls(code=error.code.value, reason=error.reason)

    @classmethod
    def make(cls, code: ErrorCode, reason: str) -> ErrorReply:
        """The reply for an application-level refusal (unknown cut, wrong digest...)."""
        return cls(code=code.value, reason=reason)

    @property
    def error_code(self) -> ErrorCode | None:
        """The code as an ErrorCode, None if this build does not know it."""
        try:
            return ErrorCode(self.code)
        except ValueError:
            return None


# -- envelope --------------------------------------------------------------------------------------
def encode(message: Message) -> bytes:
    """Encode a registered message with its envelope."""
    if not isinstance(message, Message) or type(message).TYPE not in MESSAGE_TYPES:
        raise WrongFieldType(f"cannot encode {type(message).__name__}: not a registered message")
    body = {VERSION_FIELD: SCHEMA_VERSION, TYPE_FIELD: message.TYPE}
    body.update(message.to_map())
    packed: bytes = msgpack.packb(body, use_bin_type=True)
    return packed


def encode_raw(body: Any) -> bytes:
    """msgpack bytes of arbitrary data, without envelope or checks: for tests and tools that
    craft payloads, malformed ones included (e.g. a map with `"v": 99`)."""
    packed: bytes = msgpack.packb(body, use_bin_type=True)
    return packed


def _refuse_ext(code: int, data: bytes) -> Any:
    raise MalformedPayload(f"msgpack extension type {code} is not used on this wire")


@overload
def decode(data: Buffer, *, expect: type[M], max_bytes: int = ...) -> M: ...
@overload
def decode(
    data: Buffer,
    *,
    expect: tuple[type[Message], ...] | None = None,
    max_bytes: int = ...,
) -> Message: ...
def decode(
    data: Buffer,
    *,
    expect: type[Message] | tuple[type[Message], ...] | None = None,
    max_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
) -> Message:
    """Decode one message; `expect` restricts the accepted types. Raises a WireError subclass for
    anything else, never another exception."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MalformedPayload(f"expected bytes, got {type(data).__name__}")
    size = data.nbytes if isinstance(data, memoryview) else len(data)
    if size > max_bytes:
        raise PayloadTooLarge(f"payload of {size} bytes exceeds the limit of {max_bytes} bytes")
    if size == 0:
        raise MalformedPayload("empty payload")
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=True, ext_hook=_refuse_ext)
    except WireError:
        raise
    except msgpack.ExtraData as exc:
        extra = getattr(exc, "extra", None)
        count = len(extra) if isinstance(extra, (bytes, bytearray, memoryview)) else "some"
        raise TrailingBytes(f"{count} trailing bytes after the message") from None
    except Exception as exc:  # msgpack raises ValueError/TypeError/UnicodeDecodeError/...
        raise MalformedPayload(f"not a msgpack message ({type(exc).__name__}: {exc})") from None
    if type(body) is not dict:
        raise MalformedPayload(f"expected a map at the top level, got {_type_name(body)}")
    version = body.get(VERSION_FIELD)
    if type(version) is not int or version not in SUPPORTED_SCHEMA_VERSIONS:
        if VERSION_FIELD not in body:
            raise UnknownSchemaVersion(f"no schema version ('v') in the message; {_READS}")
        raise UnknownSchemaVersion(f"schema version {version!r} is not supported; {_READS}")
    tag = body.get(TYPE_FIELD)
    cls = MESSAGE_TYPES.get(tag) if type(tag) is str else None
    if cls is None:
        raise UnknownMessageType(f"unknown message type {tag!r}")
    if expect is not None:
        allowed = expect if isinstance(expect, tuple) else (expect,)
        if cls not in allowed:
            names = " or ".join(repr(a.TYPE) for a in allowed)
            raise UnexpectedMessageType(f"expected a {names} message, got {tag!r}")
    return cls.from_map(body)


def error_reply(error: WireError) -> bytes:
    """The encoded ErrorReply for a decode failure (what a queryable answers to bad input)."""
    return ErrorReply.of(error).to_wire()


def to_jsonable(message: Struct) -> dict[str, Any]:
    """A JSON-friendly view (tensors summarised by dtype and shape), for logs and `--json`."""
    return {
        f.name: _jsonable(getattr(message, f.name))
        for f in dataclasses.fields(message)  # type: ignore[arg-type]
    }


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return {"dtype": value.dtype.name, "shape": list(value.shape)}
    if isinstance(value, Struct):
        return to_jsonable(value)
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, (bytes, bytearray, memoryview)):
        return {"bytes": memoryview(value).nbytes}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    return value
