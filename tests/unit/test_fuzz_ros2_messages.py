"""Fuzzing the ROS 2 message decoders (common/ros2_messages.py): Image, CompressedImage,
Float32MultiArray, Twist, and the stamped standard messages (TwistStamped, CameraInfo, Isaac
ROS's TensorList, vision_msgs' Classification) in CDR, as they arrive from a ROS 2 topic or a bag
record.

Inputs: valid messages (random pixels in every known encoding, JPEG and PNG data, arrays,
velocities) with their bytes corrupted or cut; valid CDR of fields a decoder must refuse (any
encoding, format, size, step and data); size bombs (a JPEG or PNG header claiming far more than
the limit). Whatever the input, a decoder returns a well-formed value or raises a
`Ros2MessageError` (a `WireError`) with a one-line message, within a time bound and a memory
bound that does not grow with what a header claims.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common import ros2_messages as rm
from common.wire import WireError
from tests.unit.fuzz_support import budget, byte_edits, mutate, run_decoder

# Decoded frames are held to 1 MiB here, so that a bomb is obvious.
LIMIT_BYTES = 1024 * 1024
# A decode may hold the payload, the deserialized message, the decoded image and its BGR copy.
MEMORY_FACTOR = 6

DECODERS: dict[str, Callable[[bytes], Any]] = {
    "image": lambda b: rm.decode_image(b, max_bytes=LIMIT_BYTES),
    "compressed": lambda b: rm.decode_compressed_image(b, max_bytes=LIMIT_BYTES),
    "array": rm.decode_float32_multi_array,
    "twist": rm.decode_twist,
    "twist_stamped": rm.decode_twist_stamped,
    "camera_info": rm.decode_camera_info,
    "tensors": rm.decode_tensor_list,
    "classification": rm.decode_classification,
}


def decode_checked(kind: str, payload: bytes) -> Any:
    """Decode under the time and memory bounds; check the value's form when there is one."""
    allowed = MEMORY_FACTOR * (len(payload) + LIMIT_BYTES)
    value = run_decoder(lambda: DECODERS[kind](payload), (WireError,), max_bytes=allowed)
    if isinstance(value, rm.StampedFrame):
        image = value.image
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
        assert image.flags.c_contiguous and image.size > 0 and image.nbytes <= LIMIT_BYTES
        assert isinstance(value.stamp_ns, int)
    elif kind == "array" and value is not None:
        array, labels = value
        assert array.dtype == np.float32 and len(labels) == array.ndim
    elif kind == "twist" and value is not None:
        assert isinstance(value, rm.Twist)
    elif kind == "twist_stamped" and value is not None:
        header, twist = value
        assert isinstance(header, rm.Header) and isinstance(twist, rm.Twist)
        assert all(math.isfinite(v) for v in twist.linear + twist.angular)
    elif kind == "camera_info" and value is not None:
        assert isinstance(value, rm.CameraInfo) and value.fx > 0 and value.k[4] > 0
        assert value.height > 0 and value.width > 0
    elif kind == "tensors" and value is not None:
        header, tensors = value
        assert isinstance(header, rm.Header)
        assert all(t.dtype in rm.TENSOR_DATA_TYPES.values() for t in tensors.values())
    elif kind == "classification" and value is not None:
        header, results = value
        assert all(isinstance(c, str) and math.isfinite(score) for c, score in results)
    return value


def _header(stamp: tuple[int, int], frame_id: str) -> Any:
    types = rm.typestore().types
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=stamp[0], nanosec=stamp[1]),
        frame_id=frame_id,
    )


def _serialize(msg: Any, msgtype: rm.MessageType) -> bytes:
    return bytes(rm.typestore().serialize_cdr(msg, msgtype.value))


_stamps = st.tuples(st.integers(-(2**31), 2**31 - 1), st.integers(0, 2**32 - 1))
_frame_ids = st.text(max_size=8)
_encodings = st.sampled_from([*rm.KNOWN_ENCODINGS, "16UC1", "32FC1", "yuv422", ""]) | st.text(
    max_size=6
)
_pixels = hnp.arrays(
    np.uint8, st.tuples(st.integers(1, 12), st.integers(1, 12), st.sampled_from([1, 3, 4]))
)


_MATCHING = {1: ["mono8"], 3: ["rgb8", "bgr8"], 4: ["rgba8", "bgra8"]}


@st.composite
def _images(draw: st.DrawFn) -> bytes:
    """An Image in CDR: consistent, or with a field or two made inconsistent."""
    pixels = draw(_pixels)
    h, w, c = pixels.shape
    pad = draw(st.integers(0, 4))
    rows = np.concatenate([pixels.reshape(h, w * c), np.zeros((h, pad), np.uint8)], axis=1)
    fields = {"height": h, "width": w, "step": w * c + pad, "data": rows.reshape(-1)}
    fields["encoding"] = draw(st.sampled_from(_MATCHING[c]))
    wrong = {
        "height": st.integers(0, 2**32 - 1),
        "width": st.integers(0, 2**32 - 1),
        "step": st.integers(0, 2**32 - 1),
        "data": hnp.arrays(np.uint8, st.integers(0, 64)),
        "encoding": _encodings,
    }
    for name in draw(st.sets(st.sampled_from(sorted(wrong)), max_size=2)):
        fields[name] = draw(wrong[name])
    msg = rm.typestore().types["sensor_msgs/msg/Image"](
        header=_header(draw(_stamps), draw(_frame_ids)),
        is_bigendian=draw(st.integers(0, 255)),
        **fields,
    )
    return _serialize(msg, rm.MessageType.IMAGE)


def _png_bomb(width: int, height: int, color: int) -> bytes:
    """A PNG whose IHDR claims width×height and whose IDAT is a few bytes of deflate."""

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, color, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\x00" * 64))
        + chunk(b"IEND", b"")
    )


def _jpeg_bomb(width: int, height: int) -> bytes:
    """A small JPEG with the frame header's size rewritten to width×height."""
    _, jpeg = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    data = bytearray(jpeg.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


@st.composite
def _compressed_data(draw: st.DrawFn) -> tuple[bytes, str]:
    """JPEG or PNG bytes (real, or a size bomb) and a format field."""
    kind = draw(st.sampled_from(["jpeg", "png", "png-bomb", "jpeg-bomb"]))
    side = st.integers(1, 65535)
    if kind == "png-bomb":
        data = _png_bomb(draw(side), draw(side), draw(st.sampled_from([0, 2, 3, 4, 6])))
    elif kind == "jpeg-bomb":
        data = _jpeg_bomb(draw(side), draw(side))
    else:
        pixels = draw(_pixels.filter(lambda p: p.shape[2] != 4 or kind == "png"))
        _, encoded = cv2.imencode(f".{kind}", pixels)
        data = encoded.tobytes()
    fmt = draw(
        st.sampled_from(["jpeg", "png", "", "bgr8; jpeg compressed bgr8", "compressedDepth"])
        | st.text(max_size=8)
    )
    return data, fmt


@st.composite
def _compressed(draw: st.DrawFn) -> bytes:
    data, fmt = draw(_compressed_data())
    msg = rm.typestore().types["sensor_msgs/msg/CompressedImage"](
        header=_header(draw(_stamps), draw(_frame_ids)),
        format=fmt,
        data=np.frombuffer(data, np.uint8),
    )
    return _serialize(msg, rm.MessageType.COMPRESSED_IMAGE)


@st.composite
def _arrays(draw: st.DrawFn) -> bytes:
    array = draw(hnp.arrays(np.float32, hnp.array_shapes(min_dims=0, max_dims=4, max_side=5)))
    payload = rm.encode_float32_multi_array(array)
    if draw(st.booleans()):  # a layout that disagrees with the data
        msg = rm.typestore().deserialize_cdr(payload, rm.MessageType.FLOAT32_MULTI_ARRAY.value)
        for dim in msg.layout.dim:
            dim.size = draw(st.integers(0, 2**32 - 1))
        msg.layout.data_offset = draw(st.integers(0, 2**32 - 1))
        payload = _serialize(msg, rm.MessageType.FLOAT32_MULTI_ARRAY)
    return payload


_twists = st.builds(
    lambda values: rm.typestore().serialize_cdr(
        rm.typestore().types["geometry_msgs/msg/Twist"](
            linear=rm.typestore().types["geometry_msgs/msg/Vector3"](*values[:3]),
            angular=rm.typestore().types["geometry_msgs/msg/Vector3"](*values[3:]),
        ),
        rm.MessageType.TWIST.value,
    ),
    st.lists(st.floats(), min_size=6, max_size=6),
).map(bytes)

_finite_or_not = st.floats() | st.floats(allow_nan=False, allow_infinity=False, width=32)


@st.composite
def _twists_stamped(draw: st.DrawFn) -> bytes:
    types = rm.typestore().types
    values = draw(st.lists(_finite_or_not, min_size=6, max_size=6))
    msg = types["geometry_msgs/msg/TwistStamped"](
        header=_header(draw(_stamps), draw(_frame_ids)),
        twist=types["geometry_msgs/msg/Twist"](
            linear=types["geometry_msgs/msg/Vector3"](*values[:3]),
            angular=types["geometry_msgs/msg/Vector3"](*values[3:]),
        ),
    )
    return _serialize(msg, rm.MessageType.TWIST_STAMPED)


@st.composite
def _camera_infos(draw: st.DrawFn) -> bytes:
    """A CameraInfo: calibrated, or with a zero, negative or non-finite focal length."""
    types = rm.typestore().types
    fx, fy = draw(st.sampled_from([500.0, 0.0, -1.0])), draw(st.sampled_from([500.0, 0.0]))
    k = [fx, 0.0, 320.0, 0.0, fy, 240.0, 0.0, 0.0, 1.0]
    p = [fx, 0.0, 320.0, draw(_finite_or_not), 0.0, fy, 240.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    if draw(st.booleans()):
        k[draw(st.integers(0, 8))] = draw(_finite_or_not)
    msg = types["sensor_msgs/msg/CameraInfo"](
        header=_header(draw(_stamps), draw(_frame_ids)),
        height=draw(st.integers(0, 4096)),
        width=draw(st.integers(0, 4096)),
        distortion_model=draw(st.sampled_from(["plumb_bob", "", "rational_polynomial"])),
        d=np.asarray(draw(st.lists(_finite_or_not, max_size=8)), np.float64),
        k=np.asarray(k, np.float64),
        r=np.eye(3).reshape(-1),
        p=np.asarray(p, np.float64),
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    return _serialize(msg, rm.MessageType.CAMERA_INFO)


_tensor_dtypes = st.sampled_from(
    [np.uint8, np.int8, np.int16, np.uint16, np.int32, np.uint32, np.int64, np.float32, np.float64]
)


@st.composite
def _tensor_lists(draw: st.DrawFn) -> bytes:
    """A TensorList of real tensors, or with a tensor's type, rank, dims, strides or data
    made inconsistent."""
    outputs = {
        f"t{i}": draw(hnp.arrays(draw(_tensor_dtypes), hnp.array_shapes(max_dims=3, max_side=4)))
        for i in range(draw(st.integers(0, 3)))
    }
    header = rm.Header(draw(st.integers(0, 2**31 * 10**9 - 1)), draw(_frame_ids))
    payload = rm.encode_tensor_list(outputs, header)
    if outputs and draw(st.booleans()):
        msg = rm.typestore().deserialize_cdr(payload, rm.MessageType.TENSOR_LIST.value)
        tensor = msg.tensors[draw(st.integers(0, len(msg.tensors) - 1))]
        wrong = draw(st.sampled_from(["data_type", "rank", "dims", "strides", "data", "name"]))
        if wrong == "data_type":
            tensor.data_type = draw(st.integers(-(2**31), 2**31 - 1))
        elif wrong == "rank":
            tensor.shape.rank = draw(st.integers(0, 255))
        elif wrong == "dims":
            tensor.shape.dims = np.asarray(
                draw(st.lists(st.integers(0, 2**32 - 1), max_size=4)), np.uint32
            )
        elif wrong == "strides":
            tensor.strides = np.asarray(
                draw(st.lists(st.integers(0, 2**64 - 1), max_size=4)), np.uint64
            )
        elif wrong == "data":
            tensor.data = draw(hnp.arrays(np.uint8, st.integers(0, 64)))
        else:
            tensor.name = msg.tensors[0].name
        payload = _serialize(msg, rm.MessageType.TENSOR_LIST)
    return payload


@st.composite
def _classifications(draw: st.DrawFn) -> bytes:
    pairs = draw(st.lists(st.tuples(st.text(max_size=6), _finite_or_not), max_size=6))
    types = rm.typestore().types
    msg = types["vision_msgs/msg/Classification"](
        header=_header(draw(_stamps), draw(_frame_ids)),
        results=[types["vision_msgs/msg/ObjectHypothesis"](class_id=c, score=s) for c, s in pairs],
    )
    return _serialize(msg, rm.MessageType.CLASSIFICATION)


MESSAGES = {
    "image": _images(),
    "compressed": _compressed(),
    "array": _arrays(),
    "twist": _twists,
    "twist_stamped": _twists_stamped(),
    "camera_info": _camera_infos(),
    "tensors": _tensor_lists(),
    "classification": _classifications(),
}
_kinds_and_payloads = st.sampled_from(sorted(MESSAGES)).flatmap(
    lambda kind: st.tuples(st.just(kind), MESSAGES[kind])
)


@budget(120)
@given(message=_kinds_and_payloads)
def test_messages_with_any_fields(message: tuple[str, bytes]) -> None:
    decode_checked(*message)


@budget(120)
@given(message=_kinds_and_payloads, edits=byte_edits)
def test_corrupt_messages(message: tuple[str, bytes], edits: list[tuple[int, int, bytes]]) -> None:
    kind, payload = message
    decode_checked(kind, mutate(payload, edits))


@budget(100)
@given(message=_kinds_and_payloads, keep=st.integers(min_value=0, max_value=2**16))
def test_truncated_messages(message: tuple[str, bytes], keep: int) -> None:
    kind, payload = message
    assert decode_checked(kind, payload[: keep % len(payload)]) is None


@budget(100)
@given(kind=st.sampled_from(sorted(DECODERS)), payload=st.binary(max_size=256))
def test_arbitrary_bytes(kind: str, payload: bytes) -> None:
    decode_checked(kind, payload)


@budget(50)
@given(kind=st.sampled_from(sorted(DECODERS)), other=_kinds_and_payloads)
def test_a_message_of_another_type(kind: str, other: tuple[str, bytes]) -> None:
    """A record of the wrong type (a bag's topic holding something else) is refused or read as
    whatever it happens to be, never a crash."""
    decode_checked(kind, other[1])
