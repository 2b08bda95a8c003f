"""Fuzzing decode: whatever the bytes, it returns a message or raises a WireError subclass, never
anything else (a queryable turns that error into an error reply and keeps serving)."""

from __future__ import annotations

import dataclasses
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.wire import SCHEMA_VERSION, Message, WireError, decode, encode_raw
from common.wire.codec import MESSAGE_TYPES
from tests.unit.test_wire import SAMPLES, assert_same

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def decode_or_wire_error(data: bytes) -> Message | None:
    """Decode; None on a WireError; any other exception fails the test."""
    try:
        message = decode(data)
    except WireError as exc:
        assert str(exc) and "\n" not in str(exc)
        return None
    # Whatever decodes must encode again and decode to the same message.
    assert_same(decode(message.to_wire()), message)
    return message


scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.binary(max_size=64)
)
values = st.recursive(
    scalars,
    lambda children: (
        st.lists(children, max_size=5)
        | st.dictionaries(st.text(max_size=10) | st.binary(max_size=4), children, max_size=5)
    ),
    max_leaves=20,
)
tensors = st.fixed_dictionaries(
    {
        "dtype": st.sampled_from(["float32", "int64", "bool", "uint8", "complex64", "", "f4"]),
        "shape": st.lists(st.integers(min_value=-2, max_value=6), max_size=4)
        | st.lists(st.sampled_from([0, 1, 2**31, 2**62, 2**64 - 1]), max_size=17)
        | values,
        "bytes": st.binary(max_size=200) | values,
    }
)


@FUZZ
@given(st.binary(max_size=512))
def test_random_bytes(data: bytes) -> None:
    decode_or_wire_error(data)


@FUZZ
@given(
    version=st.sampled_from([SCHEMA_VERSION, 0, 1, SCHEMA_VERSION + 1, -1, "2", 2.0, None]),
    tag=st.sampled_from(sorted(MESSAGE_TYPES)) | st.text(max_size=12) | values,
    fields=st.dictionaries(st.text(max_size=15), values, max_size=8),
)
def test_random_maps(version: Any, tag: Any, fields: dict[str, Any]) -> None:
    decode_or_wire_error(encode_raw({"v": version, "t": tag, **fields}))


@FUZZ
@given(
    sample=st.sampled_from(SAMPLES),
    field_choice=st.integers(min_value=0),
    value=values | tensors | st.dictionaries(st.text(max_size=5), tensors, max_size=2),
)
def test_one_field_replaced(sample: Message, field_choice: int, value: Any) -> None:
    body = {"v": SCHEMA_VERSION, "t": type(sample).TYPE, **_plain(sample.to_map())}
    names = [f.name for f in dataclasses.fields(sample)]  # type: ignore[arg-type]
    body[names[field_choice % len(names)]] = value
    decode_or_wire_error(encode_raw(body))


@FUZZ
@given(
    sample=st.sampled_from(SAMPLES),
    cuts=st.lists(st.tuples(st.integers(min_value=0), st.binary(max_size=3)), max_size=4),
    truncate=st.integers(min_value=0),
)
def test_mutated_valid_payloads(
    sample: Message, cuts: list[tuple[int, bytes]], truncate: int
) -> None:
    data = bytearray(sample.to_wire())
    for position, replacement in cuts:
        at = position % (len(data) + 1)
        data[at : at + len(replacement)] = replacement
    if truncate % 3 == 0:
        data = data[: truncate % (len(data) + 1)]
    decode_or_wire_error(bytes(data))


def _plain(value: Any) -> Any:
    """Memoryviews (tensor data as encoded) as bytes, so the map can be packed again."""
    if isinstance(value, memoryview):
        return bytes(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value
