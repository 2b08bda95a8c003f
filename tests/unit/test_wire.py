"""The wire codec: every message round-trips, tensors decode as views of the received bytes, and
every kind of bad payload is refused with its own named error and code."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from common.wire import (
    DEFAULT_MAX_PAYLOAD_BYTES,
    DTYPES,
    SCHEMA_VERSION,
    BadDtype,
    EncodedTensor,
    ErrorCode,
    ErrorReply,
    InvalidValue,
    MalformedPayload,
    Message,
    MissingField,
    PayloadTooLarge,
    ShapeMismatch,
    TrailingBytes,
    UnexpectedMessageType,
    UnknownMessageType,
    UnknownSchemaVersion,
    WireError,
    WrongFieldType,
    decode,
    decode_encoded,
    decode_tensor,
    decode_tensors,
    encode,
    encode_raw,
    encode_tensor,
    encode_tensor_as,
    error_reply,
    to_jsonable,
)
from common.wire.app_to_robot import FrameIn, ImageEncoding, ImageIn
from common.wire.cloud_to_robot import INFER_REPLIES, BusyReply, InferReply
from common.wire.codec import MESSAGE_TYPES
from common.wire.registry import (
    PROTOCOL_VERSION,
    CtlOp,
    CtlReply,
    CtlRequest,
    DeploymentRow,
    DeploymentState,
    DeploymentsView,
    DrainReply,
    DrainRequest,
    EventRow,
    EventsView,
    FaultSpec,
    ProbeReply,
    ProbeRequest,
    ProfileRow,
    ProfilesView,
    RegisterReply,
    RegisterRequest,
    RerouteRequest,
    RibQuery,
    RobotRow,
    RobotsView,
    RouteChange,
    RouteRow,
    RoutesView,
    check_registration,
)
from common.wire.robot_to_app import FrameResultMessage, ServedBy
from common.wire.robot_to_cloud import InferRequest
from common.wire.telemetry import (
    JSONL_FIELDS,
    ProbeReport,
    TelemetryRecord,
    action_label,
    parse_action,
)

DIGEST = "9f" * 32
ROUTE = RouteChange(robot="robot-1", deployment="edge-1", epoch=3, reason="start", at=1.5)


def _tensor(shape: tuple[int, ...] = (1, 3, 4, 4), dtype: str = "float32") -> np.ndarray:
    return np.arange(math.prod(shape), dtype=dtype).reshape(shape)


# One instance of every registered message type, with non-default values where possible.
SAMPLES: list[Message] = [
    InferRequest(
        robot="robot-1",
        frame=7,
        model_digest=DIGEST,
        cut=2,
        tensors={
            "a": EncodedTensor.raw(_tensor()),
            "b": encode_tensor_as(_tensor((2,), "int64"), "raw+zstd"),
            "c": encode_tensor_as(_tensor((1, 2, 3, 3)), "int8"),
        },
        deadline_s=0.25,
        sent_at=1700000000.5,
        epoch=3,
    ),
    InferReply(
        frame=7,
        deployment="edge-1",
        epoch=3,
        outputs={"logits": _tensor((1, 10))},
        queue_s=0.001,
        compute_s=0.02,
    ),
    BusyReply(frame=7, deployment="edge-1", queued=4, capacity=5),
    ErrorReply.make(ErrorCode.UNKNOWN_CUT, "cut 99 is not a cut of this model (0..15)"),
    RegisterRequest(
        role="cloud",
        id="edge-1",
        protocol_version=PROTOCOL_VERSION,
        capabilities=("infer", "probe", "ctl"),
        service="vision",
        model_digest=DIGEST,
        software="0.1.0",
    ),
    RegisterReply(accepted=True, reason="", protocol_version=PROTOCOL_VERSION, route=ROUTE),
    ProbeRequest(sender="robot-1", sent_at=2.0, echo_bytes=1024, padding=b"\x00" * 512),
    ProbeReply(
        deployment="edge-2",
        protocol_version=PROTOCOL_VERSION,
        capabilities=("infer", "probe", "ctl"),
        service="vision",
        model_digest=DIGEST,
        states={"robot-1": DeploymentState.STANDBY, "robot-2": DeploymentState.SERVICE},
        load=2,
        capacity=5,
        num_cuts=16,
        fault=FaultSpec(delay_ms=50.0, drop=0.1, stall=False),
        echo=b"\x01" * 1024,
    ),
    CtlRequest(op=CtlOp.SERVICE, robot="robot-1", epoch=4, sender="registry", reason="bound"),
    CtlReply(
        ok=True,
        deployment="edge-2",
        op=CtlOp.SERVICE,
        robot="robot-1",
        epoch=4,
        state=DeploymentState.SERVICE,
    ),
    ROUTE,
    RerouteRequest(
        robot="robot-1", deployment="edge-1", epoch=3, reason="timeouts", consecutive_timeouts=3
    ),
    DrainRequest(deployment="edge-1", reason="SIGTERM"),
    DrainReply(ok=True, moved=("robot-1",), reason=""),
    RibQuery(robot="robot-1", limit=10),
    DeploymentsView(
        rows=(
            DeploymentRow(
                id="edge-1",
                service="vision",
                alive=True,
                model_digest=DIGEST,
                states={"robot-1": DeploymentState.SERVICE},
                load=1,
                capacity=5,
                last_seen=3.0,
                extra={"zid": "abc", "nested": [1, 2.5, None, {"k": True}]},
            ),
        ),
        generated_at=4.0,
    ),
    RobotsView(
        rows=(
            RobotRow(
                id="robot-1",
                service="vision",
                alive=True,
                deployment="edge-1",
                epoch=3,
                bound_stat="p95",
                bound_s=0.3,
                window_stat_s=0.12,
                window_len=20,
                deadline_s=0.5,
                action="cut:3",
            ),
        ),
        generated_at=4.0,
    ),
    RoutesView(
        rows=(RouteRow(robot="robot-1", deployment=None, epoch=5, since=3.5, reason="lost"),),
        generated_at=4.0,
    ),
    EventsView(
        rows=(
            EventRow(seq=1, at=1.0, kind="route", reason="start", robot="robot-1", epoch=1),
            EventRow(seq=2, at=2.0, kind="alive", deployment="edge-2"),
        ),
        generated_at=4.0,
    ),
    ProfilesView(
        rows=(
            ProfileRow(
                robot="robot-1",
                deployment="edge-2",
                samples=12,
                median_s=0.01,
                mean_s=0.011,
                p95_s=0.02,
                max_s=0.03,
                stddev_s=0.002,
                updated_at=4.0,
            ),
        ),
        generated_at=4.0,
    ),
    TelemetryRecord(
        robot="robot-1",
        frame=7,
        action="cut:2",
        bytes_up=1234,
        bytes_down=56,
        prefix_s=0.01,
        transfer_s=0.002,
        cloud_s=0.02,
        suffix_local_s=0.0,
        latency_s=0.035,
        robot_cpu_s=0.012,
        energy_j=0.05,
        deployment="edge-1",
        fallback=False,
        reason=None,
        epoch=3,
        at=5.0,
    ),
    ProbeReport(
        robot="robot-1",
        deployment="edge-2",
        ok=True,
        at=5.0,
        rtt_s=0.004,
        up_bytes=512,
        down_bytes=1024,
        load=0,
        capacity=5,
        expected_latency_s=0.04,
    ),
    FrameResultMessage(
        robot="robot-1",
        frame=12,
        stamp_ns=1_700_000_000_123_456_789,
        served_by=ServedBy.CLOUD,
        deployment="edge-1",
        action="cut:2:int8",
        cut=2,
        codec="int8",
        fallback=False,
        latency_s=0.031,
        published_ns=1_700_000_000_160_000_000,
        outputs={"logits": EncodedTensor.raw(np.arange(10, dtype=np.float32).reshape(1, 10))},
    ),
    FrameIn(
        stamp_ns=1_700_000_000_123_456_789,
        images={
            "image": ImageIn(encoding=ImageEncoding.RGB8, data=bytes(range(24)), height=2, width=4),
            "right": ImageIn(encoding=ImageEncoding.JPEG, data=b"\xff\xd8 not checked here"),
        },
    ),
    # A fleet with several services: messages name the service they concern.
    ProbeRequest(sender="robot-1", sent_at=2.0, service="segment"),
    CtlRequest(op=CtlOp.STANDBY, robot="robot-1", epoch=5, sender="registry", service="tags"),
]


def assert_same(a: Any, b: Any) -> None:
    """Deep equality that compares arrays by dtype, shape and values, and bytes-like objects (a
    locally encoded tensor's memoryview, the decoded bytes) by content."""
    if isinstance(a, (memoryview, bytearray)):
        a = bytes(a)
    if isinstance(b, (memoryview, bytearray)):
        b = bytes(b)
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray)
        assert a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()  # bitwise, so NaNs compare equal too
    elif dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b)
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name))
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys()
        for k in a:
            assert_same(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same(x, y)
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b)
    else:
        assert a == b and type(a) is type(b)


def test_samples_cover_every_message_type() -> None:
    assert {type(m).TYPE for m in SAMPLES} == set(MESSAGE_TYPES)


@pytest.mark.parametrize("message", SAMPLES, ids=lambda m: type(m).TYPE)
def test_round_trip(message: Message) -> None:
    data = message.to_wire()
    assert data == encode(message)
    assert_same(type(message).from_wire(data), message)
    assert_same(decode(data), message)


def test_envelope_carries_version_and_type() -> None:
    body = SAMPLES[0].to_map()
    assert "v" not in body and "t" not in body
    raw = encode_raw({"v": SCHEMA_VERSION, "t": "infer_request", **body})
    assert_same(decode(raw), SAMPLES[0])


# -- tensors ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", list(DTYPES))
def test_every_allowed_dtype_round_trips(dtype: str) -> None:
    array = (np.arange(12) % 2).astype(dtype).reshape(3, 4)
    wire = encode_tensor(array)
    assert wire["dtype"] == dtype and wire["shape"] == [3, 4]
    assert_same(decode_tensor(dict(wire, bytes=bytes(wire["bytes"]))), array)


@pytest.mark.parametrize(
    "array",
    [
        np.array(2.5, np.float32),  # 0-d
        np.zeros((0, 3), np.float32),  # empty
        np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2],  # not contiguous
        np.arange(6, dtype=">f4"),  # big-endian in, little-endian on the wire
        np.asfortranarray(np.arange(6, dtype=np.int32).reshape(2, 3)),
    ],
    ids=["0d", "empty", "strided", "big-endian", "fortran"],
)
def test_awkward_arrays_round_trip(array: np.ndarray) -> None:
    request = dataclasses.replace(
        SAMPLES[0],  # type: ignore[type-var]
        tensors={"x": EncodedTensor.raw(array)},
    )
    got = decode_encoded(InferRequest.from_wire(request.to_wire()).tensors["x"], max_bytes=1024)
    assert got.shape == array.shape
    assert got.dtype == array.dtype.newbyteorder("<")
    assert np.array_equal(got, array)


def test_decoded_tensor_is_a_read_only_view_of_the_payload_bytes() -> None:
    got = InferRequest.from_wire(SAMPLES[0].to_wire()).tensors["a"]
    assert isinstance(got.data, bytes)
    got = decode_encoded(got, max_bytes=1024)  # raw: a view of the received bytes
    assert not got.flags.writeable
    assert not got.flags.owndata  # np.frombuffer over the unpacked bytes: no copy of its own
    assert isinstance(got.base, (bytes, np.ndarray))


def test_encoding_refuses_unsupported_arrays() -> None:
    with pytest.raises(BadDtype, match="complex64"):
        encode_tensor(np.zeros(2, np.complex64))
    with pytest.raises(WrongFieldType, match="numpy array"):
        encode_tensor([1.0, 2.0])  # type: ignore[arg-type]


# -- strict decode ---------------------------------------------------------------------------------
def _request_map(**changes: Any) -> dict[str, Any]:
    body: dict[str, Any] = {"v": SCHEMA_VERSION, "t": "infer_request", **SAMPLES[0].to_map()}
    body["tensors"] = {k: _plain_tensor(v) for k, v in body["tensors"].items()}
    body.update(changes)
    return body


def _plain_tensor(enc: dict[str, Any]) -> dict[str, Any]:
    """An encoded tensor's map with memoryviews as bytes, so it can be packed again."""
    plain = dict(enc, data=bytes(enc["data"]))
    for param in ("scale", "zero_point"):
        if plain[param] is not None:
            plain[param] = dict(plain[param], bytes=bytes(plain[param]["bytes"]))
    return plain


def _tensor_map(**changes: Any) -> dict[str, Any]:
    raw = {"codec": "raw", "dtype": "float32", "shape": [2, 2], "data": b"\x00" * 16}
    return {"x": {**raw, **changes}}


def _bad(name: str, payload: bytes, error: type[WireError], words: str) -> Any:
    return pytest.param(payload, error, words, id=name)


def _raw(**changes: Any) -> bytes:
    return encode_raw(_request_map(**changes))


def _raw_tensor(**changes: Any) -> bytes:
    return encode_raw(_request_map(tensors=_tensor_map(**changes)))


_NO_CUT = encode_raw({k: v for k, v in _request_map().items() if k != "cut"})
_BOOL_BYTES = {"codec": "raw", "dtype": "bool", "shape": [16], "data": b"\x02" * 16}

BAD_PAYLOADS = [
    _bad("empty", b"", MalformedPayload, "empty"),
    _bad("garbage", b"\xc1\xff\x00garbage", MalformedPayload, "not a msgpack"),
    _bad("truncated", SAMPLES[0].to_wire()[:-5], MalformedPayload, "not a msgpack"),
    _bad("not a map", encode_raw([1, 2, 3]), MalformedPayload, "map at the top level"),
    _bad("extension type", b"\x81\xa1v\xd4\x05\x00", MalformedPayload, "extension"),
    _bad("trailing", SAMPLES[0].to_wire() + b"\x00\x01", TrailingBytes, "2 trailing bytes"),
    _bad("no version", encode_raw({"t": "busy"}), UnknownSchemaVersion, "no schema version"),
    _bad("future version", _raw(v=99), UnknownSchemaVersion, "99"),
    _bad("v1 sender", _raw(v=1), UnknownSchemaVersion, "reads schema version 2"),
    _bad("bool version", _raw(v=True), UnknownSchemaVersion, "True"),
    _bad("list version", _raw(v=[1]), UnknownSchemaVersion, "[1]"),
    _bad("unknown type", _raw(t="teleport"), UnknownMessageType, "teleport"),
    _bad("missing field", _NO_CUT, MissingField, "infer_request: missing field 'cut'"),
    _bad("wrong type", _raw(frame="7"), WrongFieldType, "frame: expected integer, got string"),
    _bad("bool for int", _raw(cut=True), WrongFieldType, "infer_request.cut"),
    _bad("tensors not a map", _raw(tensors=[1]), WrongFieldType, "tensors"),
    _bad("non-string key", _raw(tensors={b"x": 1}), WrongFieldType, "keys must be strings"),
    _bad("bad dtype", _raw_tensor(dtype="complex128"), BadDtype, "x.dtype: 'complex128' is not"),
    _bad("object dtype", _raw_tensor(dtype="object"), BadDtype, "'object' is not allowed"),
    _bad("shape/bytes", _raw_tensor(shape=[3, 2]), ShapeMismatch, "needs 24 bytes, got 16"),
    _bad("negative dim", _raw_tensor(shape=[-2, -2]), ShapeMismatch, "non-negative"),
    _bad("shape not list", _raw_tensor(shape="2x2"), WrongFieldType, "x.shape: expected array"),
    _bad("huge empty", _raw_tensor(shape=[0, 2**62, 2**62], bytes=b""), ShapeMismatch, "large"),
    _bad("too many dims", _raw_tensor(shape=[1] * 17, bytes=b"\x00" * 4), ShapeMismatch, "at most"),
    _bad("bytes as str", _raw_tensor(data="x" * 16), WrongFieldType, "expected bytes"),
    _bad("old tensor map", _raw(tensors={"x": {"dtype": "float32"}}), MissingField, "'codec'"),
    _bad("tensor field", _raw_tensor(shape=None), WrongFieldType, "x.shape: expected array"),
    _bad("bool not 0/1", _raw(tensors={"x": _BOOL_BYTES}), InvalidValue, "bool tensor"),
    _bad("negative frame", _raw(frame=-1), InvalidValue, "frame: must be >= 0"),
    _bad("zero deadline", _raw(deadline_s=0.0), InvalidValue, "deadline_s: must be > 0"),
    _bad("nan deadline", _raw(deadline_s=float("nan")), InvalidValue, "deadline_s"),
    _bad("no tensors", _raw(tensors={}), InvalidValue, "at least one tensor"),
    _bad("bad robot id", _raw(robot="a/b"), InvalidValue, "robot"),
]


def decode_fully(payload: bytes) -> Message:
    """Decode, and decode an InferRequest's tensors too (what a deployment does)."""
    message = decode(payload)
    if isinstance(message, InferRequest):
        decode_tensors(message.tensors, max_bytes=DEFAULT_MAX_PAYLOAD_BYTES)
    return message


@pytest.mark.parametrize(("payload", "error", "words"), BAD_PAYLOADS)
def test_bad_payloads_get_a_named_error(payload: bytes, error: type[WireError], words: str) -> None:
    with pytest.raises(error) as info:
        decode_fully(payload)
    assert type(info.value) is error
    assert words in str(info.value)
    assert "\n" not in str(info.value)
    # The reply a queryable sends back names the same problem with a machine-readable code.
    reply = ErrorReply.from_wire(error_reply(info.value))
    assert reply.code == error.code.value
    assert reply.error_code is error.code
    assert reply.reason == str(info.value)


def test_size_limit_is_checked_before_unpacking() -> None:
    data = SAMPLES[0].to_wire()
    assert decode(data, max_bytes=len(data))
    with pytest.raises(PayloadTooLarge, match=f"{len(data)} bytes exceeds the limit of 100"):
        decode(data, max_bytes=100)
    with pytest.raises(PayloadTooLarge):
        InferRequest.from_wire(data, max_bytes=len(data) - 1)


def test_expected_type_is_enforced() -> None:
    data = SAMPLES[0].to_wire()
    with pytest.raises(
        UnexpectedMessageType, match="expected a 'probe' message, got 'infer_request'"
    ):
        ProbeRequest.from_wire(data)
    with pytest.raises(UnexpectedMessageType, match="'infer_reply' or 'busy' or 'error'"):
        decode(data, expect=INFER_REPLIES)
    busy = BusyReply(frame=1, deployment="edge-1", queued=1, capacity=1).to_wire()
    assert isinstance(decode(busy, expect=INFER_REPLIES), BusyReply)


def test_memoryview_and_bytearray_inputs() -> None:
    data = SAMPLES[2].to_wire()
    assert_same(decode(memoryview(data)), SAMPLES[2])
    assert_same(decode(bytearray(data)), SAMPLES[2])
    with pytest.raises(MalformedPayload, match="expected bytes"):
        decode("text")  # type: ignore[call-overload]


# -- compatibility ---------------------------------------------------------------------------------
def test_unknown_fields_are_ignored_for_forward_compatibility() -> None:
    body = {"v": SCHEMA_VERSION, **SAMPLES[7].to_map(), "t": "probe_reply", "future": {"x": 1}}
    body["fault"] = dict(body["fault"], future_knob=3)
    got = decode(encode_raw(body))
    assert isinstance(got, ProbeReply)
    assert got.fault == FaultSpec(delay_ms=50.0, drop=0.1)


def test_missing_optional_fields_take_their_default() -> None:
    raw = encode_raw({"v": SCHEMA_VERSION, "t": "ctl", "op": "drain"})
    assert decode(raw) == CtlRequest(op=CtlOp.DRAIN)


def test_unknown_enum_value_is_a_bad_value() -> None:
    raw = encode_raw({"v": SCHEMA_VERSION, "t": "ctl", "op": "explode"})
    with pytest.raises(InvalidValue, match=r"ctl\.op: expected one of 'service'"):
        decode(raw)


def test_unknown_error_codes_still_decode() -> None:
    body = {"v": SCHEMA_VERSION, "t": "error", "code": "new", "reason": "r"}
    reply = ErrorReply.from_wire(encode_raw(body))
    assert reply.code == "new" and reply.error_code is None


def test_nested_struct_errors_name_the_path() -> None:
    body = {"v": SCHEMA_VERSION, **SAMPLES[15].to_map(), "t": "rib_deployments"}
    body["rows"][0]["load"] = "high"
    with pytest.raises(WrongFieldType, match=r"rib_deployments\.rows\[0\]\.load: expected integer"):
        decode(encode_raw(body))
    body["rows"][0]["load"] = 1
    body["rows"][0]["extra"] = {"when": b"bytes"}
    with pytest.raises(WrongFieldType, match="JSON-like"):
        decode(encode_raw(body))


# -- message checks and helpers --------------------------------------------------------------------
def test_messages_check_values_when_built_locally_too() -> None:
    with pytest.raises(InvalidValue, match=r"robot.*required"):
        CtlRequest(op=CtlOp.SERVICE, epoch=1)
    with pytest.raises(InvalidValue, match=r"fault.*required"):
        CtlRequest(op=CtlOp.FAULT)
    with pytest.raises(InvalidValue, match="probability"):
        FaultSpec(drop=1.5)
    with pytest.raises(InvalidValue, match="echo_bytes"):
        ProbeRequest(sender="r", sent_at=0.0, echo_bytes=10**9)
    with pytest.raises(InvalidValue, match="action"):
        dataclasses.replace(SAMPLES[20], action="teleport")  # type: ignore[type-var]


def test_encode_refuses_unregistered_objects() -> None:
    with pytest.raises(WrongFieldType, match="not a registered message"):
        encode(FaultSpec())  # type: ignore[arg-type]


def test_registration_check_gives_readable_refusals() -> None:
    ok = SAMPLES[4]
    assert isinstance(ok, RegisterRequest)
    assert check_registration(ok, service="vision", model_digest=DIGEST) is None
    old = dataclasses.replace(ok, protocol_version=PROTOCOL_VERSION + 1)
    reason = check_registration(old, service="vision")
    assert reason is not None and "speaks protocol" in reason and "edge-1" in reason
    lacking = dataclasses.replace(ok, capabilities=("infer",))
    assert "lacks required capabilities: ctl, probe" in str(
        check_registration(lacking, service="vision")
    )
    other = check_registration(ok, service="lidar")
    assert other is not None and "'vision'" in other and "'lidar'" in other
    digest = check_registration(ok, service="vision", model_digest="00" * 32)
    assert digest is not None and "same model" in digest
    stranger = check_registration(ok, service="vision", known_ids=frozenset({"edge-2"}))
    assert stranger is not None and "known: edge-2" in stranger


def test_telemetry_jsonl_has_the_documented_fields_in_order() -> None:
    record = SAMPLES[20]
    assert isinstance(record, TelemetryRecord)
    line = record.to_jsonl()
    assert tuple(line) == JSONL_FIELDS
    assert line["action"] == "cut:2" and line["deployment"] == "edge-1"
    assert record.cut == 2


def test_action_labels() -> None:
    assert action_label(None) == "P"
    assert action_label(3) == "cut:3"
    assert parse_action("P") is None
    assert parse_action("cut:12") == 12
    for bad in ("cut:", "cut:-1", "p", "3"):
        with pytest.raises(ValueError):
            parse_action(bad)


def test_to_jsonable_summarises_tensors_and_bytes() -> None:
    view = to_jsonable(SAMPLES[0])
    assert view["tensors"]["a"] == {
        "codec": "raw",
        "dtype": "float32",
        "shape": [1, 3, 4, 4],
        "data": {"bytes": 192},
        "scale": None,
        "zero_point": None,
    }
    assert view["tensors"]["c"]["scale"] == {"dtype": "float32", "shape": [2]}
    assert to_jsonable(SAMPLES[1])["outputs"]["logits"] == {"dtype": "float32", "shape": [1, 10]}
    probe = to_jsonable(SAMPLES[6])
    assert probe["padding"] == {"bytes": 512}
    assert to_jsonable(SAMPLES[7])["states"] == {"robot-1": "standby", "robot-2": "service"}


@pytest.mark.parametrize("cls", [RouteChange, CtlRequest, ProbeRequest, TelemetryRecord])
def test_a_service_that_is_no_key_chunk_is_refused_by_name(cls: type[Message]) -> None:
    """The messages that name a service (several per fleet) check it as the id it is in the
    service key `svc/<service>/<robot>/infer`."""
    sample = next(m for m in SAMPLES if type(m) is cls)
    with pytest.raises(WireError, match="service"):
        decode(
            encode_raw({"v": SCHEMA_VERSION, "t": cls.TYPE, **sample.to_map(), "service": "a/b"})
        )
