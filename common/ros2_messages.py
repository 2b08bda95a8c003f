"""ROS 2 messages to arrays and back: the one place that reads and writes them.

Why: elasticfog takes frames from ROS 2 topics and rosbags and hands results to ROS 2 planners,
Foxglove and `ros2 bag play`. Those speak the ROS 2 message types in CDR (little endian, with the
4-byte encapsulation header), so every message is built and read by rosbags' Jazzy type store
(`rosbags.typesys`), never by hand-written CDR, and the type names and RIHS01 hashes peers check
(rmw_zenoh's key space) come from that same store.

What:
- `decode_image` (sensor_msgs/msg/Image: rgb8, bgr8, mono8, rgba8, bgra8, rows `step` bytes
  apart) and `decode_compressed_image` (sensor_msgs/msg/CompressedImage: JPEG, PNG, decoded by
  the wire's image codecs) give a `StampedFrame`: a BGR uint8 H×W×3 frame, as the robot's own
  sources yield, and the header's stamp in ns since the epoch. `decode_frame` picks by type.
- `encode_compressed_image`: a frame as a JPEG CompressedImage with a given `Header`.
- `encode_float32_multi_array`: a model output as std_msgs/msg/Float32MultiArray, one layout
  dimension per axis (labelled `axis0`, `axis1`, ... unless labels are given);
  `decode_float32_multi_array` reads one back. `encode_image_32fc1`: an output of shape 1×1×H×W or
  H×W (`is_image_shaped`; not 1×C: a vector) as a 32FC1 sensor_msgs/msg/Image with a header.
- `encode_twist` / `decode_twist`: geometry_msgs/msg/Twist as a `Twist`.
- `type_hash` (RIHS01_<sha256>) and `dds_type_name` (e.g. `sensor_msgs::msg::dds_::Image_`) of
  each `MessageType`.

Every decode raises only `Ros2MessageError` subclasses (they are `WireError`s, so ValueErrors),
with one line naming the problem: truncated or malformed CDR (`MalformedMessage`), an encoding or
format this module does not read (`UnknownEncoding`, `UnknownImageFormat`), an empty image
(`EmptyImage`), data that disagrees with the declared size or layout (`LayoutMismatch`), an image
over the size limit (`ImageTooLarge`), undecodable JPEG/PNG bytes (`CorruptImage`), values out of
range (`BadMessageValue`).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import struct
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import cv2
import numpy as np

from common.wire import EncodedTensor, WireError, decode_encoded
from common.wire.errors import ErrorCode

NS_PER_S = 1_000_000_000
# A decoded frame may take at most this many bytes (BGR): an 8K camera frame is 99.5 MB. Bounds
# what a CompressedImage header may make the decoder allocate.
MAX_FRAME_BYTES = 128 * 1024 * 1024
# Quality of the JPEG CompressedImages this module writes (recordings of a run's input): near the
# camera's own look at a fifth of PNG's bytes.
JPEG_QUALITY = 90
# What a frame recorded as CompressedImage says it is (sensor_msgs/msg/CompressedImage: "jpeg").
JPEG_FORMAT = "jpeg"
FLOAT32_ENCODING = "32FC1"
# int32 seconds in a builtin_interfaces/msg/Time.
_STAMP_SEC_MIN = -(2**31)
_STAMP_SEC_MAX = 2**31 - 1
# Channels of each raw encoding this module reads, and how each becomes BGR (None: as it is).
_ENCODINGS: dict[str, tuple[int, int | None]] = {
    "rgb8": (3, cv2.COLOR_RGB2BGR),
    "bgr8": (3, None),
    "mono8": (1, cv2.COLOR_GRAY2BGR),
    "rgba8": (4, cv2.COLOR_RGBA2BGR),
    "bgra8": (4, cv2.COLOR_BGRA2BGR),
}
KNOWN_ENCODINGS = tuple(_ENCODINGS)
KNOWN_FORMATS = ("jpeg", "png")
_JPEG_MAGIC = b"\xff\xd8"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IHDR = struct.Struct(">I4sIIBB")  # chunk length, b"IHDR", width, height, depth, color type
_PNG_GRAY, _PNG_RGB = 0, 2  # the PNG color types the wire's PNG codec reads at depth 8
_JPEG_CHANNELS = {"Gray": 1, "YCbCr": 3, "RGB": 3}  # header colorspace -> channels
# Any quality names the JPEG codec on the decode side: the quality is not needed to decode.
_JPEG_CODEC = "jpeg80"
_PNG_CODEC = "png"


class MessageType(str, enum.Enum):
    """The ROS 2 message types elasticfog reads or writes (the value is the ROS type name)."""

    IMAGE = "sensor_msgs/msg/Image"
    COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
    FLOAT32_MULTI_ARRAY = "std_msgs/msg/Float32MultiArray"
    TWIST = "geometry_msgs/msg/Twist"
    TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
    CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
    TENSOR_LIST = "isaac_ros_tensor_list_interfaces/msg/TensorList"
    CLASSIFICATION = "vision_msgs/msg/Classification"


# The message types a frame is read from.
FRAME_TYPES = (MessageType.IMAGE, MessageType.COMPRESSED_IMAGE)

# Types that are not in ROS 2 Jazzy's core, registered in the type store from their definitions
# (the fields of each upstream .msg, comments left out: they do not enter the RIHS01 hash):
# vision_msgs 4.1.1 (ros-perception/vision_msgs, Jazzy) and Isaac ROS's tensor list
# (NVIDIA-ISAAC-ROS/isaac_ros_common, isaac_ros_tensor_list_interfaces 4.4.0).
EXTRA_DEFINITIONS: dict[str, str] = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/Classification": "std_msgs/Header header\nObjectHypothesis[] results\n",
    "isaac_ros_tensor_list_interfaces/msg/TensorShape": "uint8 rank\nuint32[] dims\n",
    "isaac_ros_tensor_list_interfaces/msg/Tensor": (
        "string name\nTensorShape shape\nint32 data_type\nuint64[] strides\nuint8[] data\n"
    ),
    "isaac_ros_tensor_list_interfaces/msg/TensorList": (
        "std_msgs/Header header\nTensor[] tensors\n"
    ),
}

# Isaac ROS's tensor data types (isaac_ros_tensor_list_interfaces/msg/Tensor.msg's comment): the
# numpy dtype of each code. A float16 or bool output is written as float32 or uint8.
TENSOR_DATA_TYPES: dict[int, np.dtype[Any]] = {
    1: np.dtype("<i1"),
    2: np.dtype("<u1"),
    3: np.dtype("<i2"),
    4: np.dtype("<u2"),
    5: np.dtype("<i4"),
    6: np.dtype("<u4"),
    7: np.dtype("<i8"),
    8: np.dtype("<u8"),
    9: np.dtype("<f4"),
    10: np.dtype("<f8"),
}
_TENSOR_CODES = {dtype.str: code for code, dtype in TENSOR_DATA_TYPES.items()}
_TENSOR_WIDENED: dict[str, np.dtype[Any]] = {"f2": np.dtype("<f4"), "b1": np.dtype("<u1")}
# How many classes a Classification names (the top of a 1×N output).
TOP_CLASSES = 5


# -- errors ----------------------------------------------------------------------------------------
class Ros2MessageError(WireError):
    """A ROS 2 message that cannot be read (or a value that cannot be written as one)."""


class MalformedMessage(Ros2MessageError):
    """Not CDR of the expected type: truncated, bad encapsulation, lengths out of bounds, bytes
    left over."""

    code: ClassVar[ErrorCode] = ErrorCode.MALFORMED


class UnknownEncoding(Ros2MessageError):
    """An Image encoding this module does not read (see KNOWN_ENCODINGS)."""

    code = ErrorCode.BAD_VALUE


class UnknownImageFormat(Ros2MessageError):
    """A CompressedImage that is neither JPEG nor PNG (or a JPEG/PNG kind that is not read)."""

    code = ErrorCode.BAD_VALUE


class EmptyImage(Ros2MessageError):
    """An image of zero height or width."""

    code = ErrorCode.SHAPE_MISMATCH


class LayoutMismatch(Ros2MessageError):
    """An Image whose step or data length disagrees with its width, height and encoding, or a
    multi-array whose layout disagrees with its data."""

    code = ErrorCode.SHAPE_MISMATCH


class ImageTooLarge(Ros2MessageError):
    """An image that would decode to more than the limit (MAX_FRAME_BYTES by default)."""

    code = ErrorCode.TOO_LARGE


class CorruptImage(Ros2MessageError):
    """JPEG or PNG bytes that do not decode."""

    code = ErrorCode.CORRUPT_PAYLOAD


class BadCameraInfo(Ros2MessageError):
    """A CameraInfo that gives no usable geometry: a zero or negative focal length, non-finite
    values, a stereo right camera whose P[3] (−fx·baseline) is not negative."""

    code = ErrorCode.BAD_VALUE


class BadMessageValue(Ros2MessageError):
    """A value out of range: a stamp beyond int32 seconds, a non-finite velocity, an array that
    is not numeric or not image-shaped where one must be."""

    code = ErrorCode.BAD_VALUE


# -- values ----------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, slots=True)
class Header:
    """A std_msgs/msg/Header: the stamp in ns since the epoch and the frame id."""

    stamp_ns: int
    frame_id: str = ""


@dataclasses.dataclass(frozen=True, slots=True)
class StampedFrame:
    """A frame read from a message: BGR uint8 H×W×3 (C-contiguous) and its header."""

    image: np.ndarray
    header: Header

    @property
    def stamp_ns(self) -> int:
        """The header's stamp, ns since the epoch."""
        return self.header.stamp_ns


@dataclasses.dataclass(frozen=True, slots=True)
class Roi:
    """A sensor_msgs/msg/RegionOfInterest: a rectangle of the camera image, pixels."""

    x_offset: int = 0
    y_offset: int = 0
    height: int = 0
    width: int = 0


_IDENTITY_3X3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@dataclasses.dataclass(frozen=True, slots=True)
class CameraInfo:
    """A sensor_msgs/msg/CameraInfo: image size, intrinsics K (3×3, row-major), rectification R,
    projection P (3×4: P[3] = −fx·baseline for a stereo right camera), distortion, ROI."""

    header: Header
    height: int
    width: int
    k: tuple[float, ...] = (0.0,) * 9
    p: tuple[float, ...] = (0.0,) * 12
    r: tuple[float, ...] = _IDENTITY_3X3
    d: tuple[float, ...] = ()
    distortion_model: str = ""
    roi: Roi = Roi()

    @property
    def fx(self) -> float:
        return self.k[0]

    @property
    def cx(self) -> float:
        return self.k[2]

    @property
    def cy(self) -> float:
        return self.k[5]

    def baseline_m(self) -> float:
        """The stereo baseline a right camera's projection gives (P[3] = −fx'·B, fx' = P[0]);
        BadCameraInfo when P[3] is not negative (a left camera's 0, or a sign error)."""
        fx, tx = self.p[0], self.p[3]
        if not (math.isfinite(fx) and fx > 0):
            raise BadCameraInfo(f"CameraInfo P[0] (fx) is {fx}: no stereo baseline from it")
        if not (math.isfinite(tx) and tx < 0):
            raise BadCameraInfo(
                f"the right camera's CameraInfo P[3] is {tx}: it must be −fx·baseline (< 0); "
                "a left camera's is 0"
            )
        return -tx / fx


@dataclasses.dataclass(frozen=True, slots=True)
class Twist:
    """A geometry_msgs/msg/Twist: linear (m/s) and angular (rad/s) velocity, x, y, z."""

    linear: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular: tuple[float, float, float] = (0.0, 0.0, 0.0)


# -- the type store --------------------------------------------------------------------------------
@functools.cache
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy type store (built on first use: most processes never need it)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    extra: dict[str, Any] = {}
    for name, text in EXTRA_DEFINITIONS.items():
        extra.update(get_types_from_msg(text, name))
    store.register(extra)
    return store


def type_hash(msgtype: MessageType) -> str:
    """The type's RIHS01 hash as ROS 2 Jazzy writes it (`RIHS01_<64 hex digits>`)."""
    return _type_hash(MessageType(msgtype).value)


@functools.cache
def _type_hash(name: str) -> str:
    return str(typestore().hash_rihs01(name))


def dds_type_name(msgtype: MessageType) -> str:
    """The type's DDS name, e.g. `sensor_msgs::msg::dds_::Image_` (rmw_zenoh's key space)."""
    package, kind, name = MessageType(msgtype).value.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def message_type(name: str) -> MessageType:
    """The MessageType of a ROS type name; BadMessageValue listing the known ones otherwise."""
    try:
        return MessageType(name)
    except ValueError:
        known = ", ".join(t.value for t in MessageType)
        raise BadMessageValue(
            f"message type {name!r} is not one elasticfog reads; known: {known}"
        ) from None


# -- frames in -------------------------------------------------------------------------------------
def decode_frame(
    msgtype: MessageType, payload: bytes | memoryview, *, max_bytes: int = MAX_FRAME_BYTES
) -> StampedFrame:
    """The frame of an Image or CompressedImage message in CDR (see FRAME_TYPES)."""
    if msgtype == MessageType.IMAGE:
        return decode_image(payload, max_bytes=max_bytes)
    if msgtype == MessageType.COMPRESSED_IMAGE:
        return decode_compressed_image(payload, max_bytes=max_bytes)
    raise BadMessageValue(
        f"{MessageType(msgtype).value} carries no frame; frames come from "
        f"{', '.join(t.value for t in FRAME_TYPES)}"
    )


def decode_image(payload: bytes | memoryview, *, max_bytes: int = MAX_FRAME_BYTES) -> StampedFrame:
    """The BGR frame and header of a sensor_msgs/msg/Image in CDR (encodings KNOWN_ENCODINGS)."""
    msg = _deserialize(payload, MessageType.IMAGE)
    header = _header(msg.header)
    encoding = str(msg.encoding)
    if encoding not in _ENCODINGS:
        raise UnknownEncoding(
            f"Image encoding {encoding!r} is not read; known: {', '.join(KNOWN_ENCODINGS)}"
        )
    channels, conversion = _ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height == 0 or width == 0:
        raise EmptyImage(f"Image is {width}×{height} ({encoding}): no pixels")
    _check_frame_size(height, width, max_bytes, "Image")
    row = width * channels
    if step < row:
        raise LayoutMismatch(
            f"Image step {step} is less than a row of {width} {encoding} pixels ({row} bytes)"
        )
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size != step * height:
        raise LayoutMismatch(
            f"Image data has {data.size} bytes; {height} rows of step {step} need {step * height}"
        )
    rows = data.reshape(height, step)[:, :row].reshape(height, width, channels)
    image = rows if conversion is None else cv2.cvtColor(rows, conversion)
    return StampedFrame(np.ascontiguousarray(image), header)


def decode_compressed_image(
    payload: bytes | memoryview, *, max_bytes: int = MAX_FRAME_BYTES
) -> StampedFrame:
    """The BGR frame and header of a sensor_msgs/msg/CompressedImage in CDR (JPEG or PNG)."""
    msg = _deserialize(payload, MessageType.COMPRESSED_IMAGE)
    header = _header(msg.header)
    data = np.asarray(msg.data, dtype=np.uint8).tobytes()
    kind = _compressed_kind(str(msg.format), data)
    image = _decode_jpeg(data, max_bytes) if kind == "jpeg" else _decode_png(data, max_bytes)
    return StampedFrame(image, header)


def _compressed_kind(fmt: str, data: bytes) -> str:
    """`jpeg` or `png`: what the format field names (image_transport writes e.g. `bgr8; jpeg
    compressed bgr8`), else what the bytes start with when the field is empty."""
    words = fmt.lower().replace(";", " ").split()
    if "compresseddepth" in words:
        raise UnknownImageFormat(
            f"CompressedImage format {fmt!r} (a depth image) is not read; "
            f"known: {', '.join(KNOWN_FORMATS)}"
        )
    named = {"jpeg" if w in ("jpeg", "jpg") else w for w in words} & set(KNOWN_FORMATS)
    if len(named) == 1:
        return named.pop()
    if not words:
        if data.startswith(_JPEG_MAGIC):
            return "jpeg"
        if data.startswith(_PNG_SIGNATURE):
            return "png"
    raise UnknownImageFormat(
        f"CompressedImage format {fmt!r} is not read; known: {', '.join(KNOWN_FORMATS)}"
    )


def _decode_jpeg(data: bytes, max_bytes: int) -> np.ndarray:
    import simplejpeg  # imported on first use, as the wire's JPEG codec does

    try:
        height, width, colorspace, _ = simplejpeg.decode_jpeg_header(data)
    except Exception as exc:  # ValueError from libjpeg-turbo, whatever the bytes
        raise CorruptImage(f"CompressedImage: not a readable JPEG ({_one_line(exc)})") from None
    channels = _JPEG_CHANNELS.get(colorspace)
    if channels is None:
        raise UnknownImageFormat(
            f"CompressedImage: a {colorspace} JPEG is not read; known colorspaces: "
            f"{', '.join(_JPEG_CHANNELS)}"
        )
    return _decode_with_codec(_JPEG_CODEC, data, height, width, channels, max_bytes)


def _decode_png(data: bytes, max_bytes: int) -> np.ndarray:
    if not data.startswith(_PNG_SIGNATURE):
        raise CorruptImage("CompressedImage: not a PNG (no PNG signature)")
    if len(data) < len(_PNG_SIGNATURE) + _PNG_IHDR.size:
        raise CorruptImage("CompressedImage: truncated PNG (no IHDR chunk)")
    length, tag, width, height, depth, color = _PNG_IHDR.unpack_from(data, len(_PNG_SIGNATURE))
    if (length, tag) != (13, b"IHDR"):
        raise CorruptImage("CompressedImage: not a PNG (IHDR is not the first chunk)")
    if depth != 8 or color not in (_PNG_GRAY, _PNG_RGB):
        raise UnknownImageFormat(
            f"CompressedImage: a PNG of bit depth {depth} and color type {color} is not read; "
            "known: 8-bit gray or RGB"
        )
    channels = 1 if color == _PNG_GRAY else 3
    return _decode_with_codec(_PNG_CODEC, data, height, width, channels, max_bytes)


def _decode_with_codec(
    codec: str, data: bytes, height: int, width: int, channels: int, max_bytes: int
) -> np.ndarray:
    """The wire's image codec decodes (strictly, with its bomb checks); the result becomes BGR."""
    if height == 0 or width == 0:
        raise EmptyImage(f"CompressedImage is {width}×{height}: no pixels")
    _check_frame_size(height, width, max_bytes, "CompressedImage")
    enc = EncodedTensor(codec=codec, dtype="uint8", shape=[height, width, channels], data=data)
    try:
        image = decode_encoded(enc, max_bytes=height * width * channels, name="CompressedImage")
    except WireError as exc:
        raise CorruptImage(str(exc)) from None
    conversion = cv2.COLOR_GRAY2BGR if channels == 1 else cv2.COLOR_RGB2BGR
    return np.ascontiguousarray(cv2.cvtColor(image, conversion))


def _check_frame_size(height: int, width: int, max_bytes: int, what: str) -> None:
    size = height * width * 3
    if size > max_bytes:
        raise ImageTooLarge(
            f"{what} is {width}×{height}: {size} bytes as BGR, over the limit of {max_bytes}"
        )


# -- frames and results out ------------------------------------------------------------------------
def encode_compressed_image(
    frame: np.ndarray, header: Header, *, quality: int = JPEG_QUALITY
) -> bytes:
    """A BGR uint8 H×W×3 (or grey H×W) frame as a JPEG sensor_msgs/msg/CompressedImage in CDR."""
    import simplejpeg

    image = np.ascontiguousarray(frame)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.size == 0:
        raise BadMessageValue(
            f"a frame must be uint8 H×W×3 (BGR) or H×W, got {image.dtype}{list(image.shape)}"
        )
    if image.ndim == 2 or image.shape[2] == 1:
        data = simplejpeg.encode_jpeg(
            image.reshape(*image.shape[:2], 1), quality=quality, colorspace="GRAY"
        )
    elif image.shape[2] == 3:
        data = simplejpeg.encode_jpeg(image, quality=quality, colorspace="BGR")
    else:
        raise BadMessageValue(f"a frame must have 1 or 3 channels, got {image.shape[2]}")
    types = typestore().types
    msg = types[MessageType.COMPRESSED_IMAGE.value](
        header=_ros_header(header),
        format=JPEG_FORMAT,
        data=np.frombuffer(data, np.uint8),
    )
    return _serialize(msg, MessageType.COMPRESSED_IMAGE)


def encode_float32_multi_array(array: np.ndarray, labels: Sequence[str] | None = None) -> bytes:
    """An output array as std_msgs/msg/Float32MultiArray in CDR: its values as float32 in C
    order, a layout dimension per axis (label, size, stride as the message's docs define it)."""
    values = np.asarray(array)
    if values.dtype.kind not in "biuf":
        raise BadMessageValue(f"a {values.dtype} array is not numeric: no Float32MultiArray")
    names = [f"axis{i}" for i in range(values.ndim)] if labels is None else list(labels)
    if len(names) != values.ndim:
        raise BadMessageValue(f"{len(names)} labels for an array of {values.ndim} axes")
    types = typestore().types
    dims = [
        types["std_msgs/msg/MultiArrayDimension"](
            label=label, size=size, stride=math.prod(values.shape[i:])
        )
        for i, (label, size) in enumerate(zip(names, values.shape, strict=True))
    ]
    msg = types[MessageType.FLOAT32_MULTI_ARRAY.value](
        layout=types["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0),
        data=np.ascontiguousarray(values, dtype="<f4").reshape(-1),
    )
    return _serialize(msg, MessageType.FLOAT32_MULTI_ARRAY)


def decode_float32_multi_array(payload: bytes | memoryview) -> tuple[np.ndarray, tuple[str, ...]]:
    """The float32 array (shaped by the layout's dimensions) and the dimensions' labels of a
    std_msgs/msg/Float32MultiArray in CDR."""
    msg = _deserialize(payload, MessageType.FLOAT32_MULTI_ARRAY)
    shape = tuple(int(d.size) for d in msg.layout.dim)
    labels = tuple(str(d.label) for d in msg.layout.dim)
    data = np.asarray(msg.data, dtype=np.float32)
    offset = int(msg.layout.data_offset)
    if offset > data.size or data.size - offset != math.prod(shape):
        raise LayoutMismatch(
            f"Float32MultiArray has {data.size} values from offset {offset}; its layout "
            f"{list(shape)} needs {math.prod(shape)}"
        )
    return np.ascontiguousarray(data[offset:]).reshape(shape), labels


def is_image_shaped(shape: Sequence[int]) -> bool:
    """Whether an output of this shape is also published as a 32FC1 Image: 1×1×H×W, or H×W with
    both sides over 1 (a 1×C or N×1 output, a classifier's scores, is a vector, not an image)."""
    dims = tuple(shape)
    if len(dims) == 4:
        return dims[:2] == (1, 1) and 0 not in dims
    return len(dims) == 2 and min(dims) > 1


def encode_image_32fc1(array: np.ndarray, header: Header) -> bytes:
    """An image-shaped output (see is_image_shaped) as a 32FC1 sensor_msgs/msg/Image in CDR."""
    values = np.asarray(array)
    if not is_image_shaped(values.shape) or values.dtype.kind not in "biuf":
        raise BadMessageValue(
            f"a {values.dtype}{list(values.shape)} output is not an image: 32FC1 Images carry "
            "numeric 1×1×H×W or H×W outputs"
        )
    height, width = values.shape[-2:]
    pixels = np.ascontiguousarray(values.reshape(height, width), dtype="<f4")
    msg = typestore().types[MessageType.IMAGE.value](
        header=_ros_header(header),
        height=height,
        width=width,
        encoding=FLOAT32_ENCODING,
        is_bigendian=0,  # the data is little endian whatever the host
        step=width * 4,
        data=pixels.view(np.uint8).reshape(-1),
    )
    return _serialize(msg, MessageType.IMAGE)


# -- Twist -----------------------------------------------------------------------------------------
def encode_twist(twist: Twist) -> bytes:
    """A Twist as geometry_msgs/msg/Twist in CDR."""
    types = typestore().types
    vector = types["geometry_msgs/msg/Vector3"]
    for part in (twist.linear, twist.angular):
        if len(part) != 3 or not all(math.isfinite(v) for v in part):
            raise BadMessageValue(f"a Twist takes 3 finite velocities a part, got {part}")
    msg = types[MessageType.TWIST.value](
        linear=vector(*map(float, twist.linear)), angular=vector(*map(float, twist.angular))
    )
    return _serialize(msg, MessageType.TWIST)


def decode_twist(payload: bytes | memoryview) -> Twist:
    """The Twist of a geometry_msgs/msg/Twist in CDR; non-finite velocities are refused."""
    msg = _deserialize(payload, MessageType.TWIST)
    linear = (float(msg.linear.x), float(msg.linear.y), float(msg.linear.z))
    angular = (float(msg.angular.x), float(msg.angular.y), float(msg.angular.z))
    if not all(math.isfinite(v) for v in linear + angular):
        raise BadMessageValue(
            f"Twist has a non-finite velocity: linear {linear}, angular {angular}"
        )
    return Twist(linear, angular)


def encode_twist_stamped(twist: Twist, header: Header) -> bytes:
    """A Twist with a header as geometry_msgs/msg/TwistStamped in CDR."""
    types = typestore().types
    inner = typestore().deserialize_cdr(encode_twist(twist), MessageType.TWIST.value)
    msg = types[MessageType.TWIST_STAMPED.value](header=_ros_header(header), twist=inner)
    return _serialize(msg, MessageType.TWIST_STAMPED)


def decode_twist_stamped(payload: bytes | memoryview) -> tuple[Header, Twist]:
    """The header and Twist of a geometry_msgs/msg/TwistStamped in CDR; non-finite velocities
    are refused."""
    msg = _deserialize(payload, MessageType.TWIST_STAMPED)
    linear = (float(msg.twist.linear.x), float(msg.twist.linear.y), float(msg.twist.linear.z))
    angular = (float(msg.twist.angular.x), float(msg.twist.angular.y), float(msg.twist.angular.z))
    if not all(math.isfinite(v) for v in linear + angular):
        raise BadMessageValue(
            f"TwistStamped has a non-finite velocity: linear {linear}, angular {angular}"
        )
    return _header(msg.header), Twist(linear, angular)


# -- CameraInfo ------------------------------------------------------------------------------------
def encode_camera_info(info: CameraInfo) -> bytes:
    """A CameraInfo as sensor_msgs/msg/CameraInfo in CDR."""
    types = typestore().types
    for name, values, size in (("K", info.k, 9), ("R", info.r, 9), ("P", info.p, 12)):
        if len(values) != size or not all(math.isfinite(v) for v in values):
            raise BadMessageValue(f"CameraInfo {name} takes {size} finite values, got {values}")
    roi = info.roi
    msg = types[MessageType.CAMERA_INFO.value](
        header=_ros_header(info.header),
        height=info.height,
        width=info.width,
        distortion_model=info.distortion_model,
        d=np.asarray(info.d, dtype=np.float64),
        k=np.asarray(info.k, dtype=np.float64),
        r=np.asarray(info.r, dtype=np.float64),
        p=np.asarray(info.p, dtype=np.float64),
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=roi.x_offset,
            y_offset=roi.y_offset,
            height=roi.height,
            width=roi.width,
            do_rectify=False,
        ),
    )
    return _serialize(msg, MessageType.CAMERA_INFO)


def decode_camera_info(payload: bytes | memoryview) -> CameraInfo:
    """The CameraInfo of a sensor_msgs/msg/CameraInfo in CDR, its geometry checked:
    BadCameraInfo for a zero (uncalibrated) or negative focal length, a non-finite K or P, an
    image of no pixels."""
    msg = _deserialize(payload, MessageType.CAMERA_INFO)
    k = tuple(float(v) for v in msg.k)
    p = tuple(float(v) for v in msg.p)
    r = tuple(float(v) for v in msg.r)
    d = tuple(float(v) for v in msg.d)
    height, width = int(msg.height), int(msg.width)
    if height == 0 or width == 0:
        raise BadCameraInfo(f"CameraInfo is for a {width}×{height} image: no pixels")
    if not all(math.isfinite(v) for v in k + p + r + d):
        raise BadCameraInfo("CameraInfo has a non-finite value in K, P, R or D")
    if not (k[0] > 0 and k[4] > 0):
        raise BadCameraInfo(
            f"CameraInfo focal length fx {k[0]}, fy {k[4]}: not a calibrated camera (a zero K "
            "is an uncalibrated one)"
        )
    roi = msg.roi
    return CameraInfo(
        _header(msg.header),
        height,
        width,
        k=k,
        p=p,
        r=r,
        d=d,
        distortion_model=str(msg.distortion_model),
        roi=Roi(int(roi.x_offset), int(roi.y_offset), int(roi.height), int(roi.width)),
    )


# -- TensorList (Isaac ROS) ------------------------------------------------------------------------
def tensor_of(array: np.ndarray) -> np.ndarray:
    """`array` as a tensor of one of TENSOR_DATA_TYPES, little endian, C order (float16 as
    float32, bool as uint8); BadMessageValue for any other dtype."""
    values = np.asarray(array)
    kind = values.dtype.kind + str(values.dtype.itemsize)
    dtype: np.dtype[Any] = _TENSOR_WIDENED.get(kind) or values.dtype.newbyteorder("<")
    if dtype.str not in _TENSOR_CODES:
        known = ", ".join(str(d) for d in TENSOR_DATA_TYPES.values())
        raise BadMessageValue(f"a {values.dtype} output is not a tensor type; known: {known}")
    return values.astype(dtype, order="C", copy=False)  # a 0-d output stays 0-d


def encode_tensor_list(outputs: Mapping[str, np.ndarray], header: Header) -> bytes:
    """Outputs by name as isaac_ros_tensor_list_interfaces/msg/TensorList in CDR: one Tensor
    each (its name, rank and dims, the data type code, byte strides in C order, the bytes)."""
    types = typestore().types
    tensors = []
    for name, array in outputs.items():
        values = tensor_of(array)
        tensors.append(
            types["isaac_ros_tensor_list_interfaces/msg/Tensor"](
                name=name,
                shape=types["isaac_ros_tensor_list_interfaces/msg/TensorShape"](
                    rank=values.ndim, dims=np.asarray(values.shape, dtype=np.uint32)
                ),
                data_type=_TENSOR_CODES[values.dtype.str],
                strides=np.asarray(values.strides, dtype=np.uint64),
                data=values.reshape(-1).view(np.uint8),
            )
        )
    msg = types[MessageType.TENSOR_LIST.value](header=_ros_header(header), tensors=tensors)
    return _serialize(msg, MessageType.TENSOR_LIST)


def decode_tensor_list(payload: bytes | memoryview) -> tuple[Header, dict[str, np.ndarray]]:
    """The header and tensors by name of an isaac_ros_tensor_list_interfaces/msg/TensorList in
    CDR. Strict: a data type that is not one of TENSOR_DATA_TYPES (BadMessageValue), a rank that
    is not the number of dims, strides that are not the C-order byte strides of the dims, data
    of another size than the dims and type give (LayoutMismatch), a name twice."""
    msg = _deserialize(payload, MessageType.TENSOR_LIST)
    tensors: dict[str, np.ndarray] = {}
    for tensor in msg.tensors:
        name = str(tensor.name)
        dtype = TENSOR_DATA_TYPES.get(int(tensor.data_type))
        if dtype is None:
            raise BadMessageValue(
                f"Tensor {name!r}: data type {int(tensor.data_type)} is not one of "
                f"{sorted(TENSOR_DATA_TYPES)}"
            )
        dims = tuple(int(d) for d in tensor.shape.dims)
        if int(tensor.shape.rank) != len(dims):
            raise LayoutMismatch(f"Tensor {name!r}: rank {tensor.shape.rank}, {len(dims)} dims")
        strides = tuple(int(v) for v in tensor.strides)
        expected = tuple(dtype.itemsize * math.prod(dims[i + 1 :]) for i in range(len(dims)))
        if strides != expected:
            raise LayoutMismatch(
                f"Tensor {name!r}: strides {list(strides)} are not the C-order byte strides "
                f"{list(expected)} of {list(dims)} {dtype}"
            )
        data = np.asarray(tensor.data, dtype=np.uint8)
        if data.size != math.prod(dims) * dtype.itemsize:
            raise LayoutMismatch(
                f"Tensor {name!r}: {data.size} bytes; {list(dims)} {dtype} need "
                f"{math.prod(dims) * dtype.itemsize}"
            )
        if name in tensors:
            raise BadMessageValue(f"TensorList names tensor {name!r} twice")
        tensors[name] = data.view(dtype).reshape(dims)
    return _header(msg.header), tensors


# -- Classification (vision_msgs) ------------------------------------------------------------------
def is_class_scores(shape: Sequence[int]) -> bool:
    """Whether an output of this shape is a classifier's scores: 1×N or N, N ≥ 2."""
    dims = tuple(shape)
    return (len(dims) == 1 and dims[0] >= 2) or (len(dims) == 2 and dims[0] == 1 and dims[1] >= 2)


def top_classes(scores: np.ndarray, count: int = TOP_CLASSES) -> list[tuple[str, float]]:
    """The `count` best classes of a 1×N output as (class id: the index as text, its softmax
    probability), best first (ties: the lower index first)."""
    values = np.asarray(scores, dtype=np.float64).reshape(-1)
    if not is_class_scores(np.asarray(scores).shape) or not np.all(np.isfinite(values)):
        raise BadMessageValue(
            f"a {list(np.asarray(scores).shape)} output with non-finite values or of another "
            "shape than 1×N (N ≥ 2) is no classifier's scores"
        )
    exp = np.exp(values - values.max())
    probs = exp / exp.sum()
    best = np.argsort(-probs, kind="stable")[:count]
    return [(str(int(i)), float(probs[i])) for i in best]


def encode_classification(hypotheses: Sequence[tuple[str, float]], header: Header) -> bytes:
    """(class id, score) pairs as vision_msgs/msg/Classification in CDR."""
    types = typestore().types
    results = [
        types["vision_msgs/msg/ObjectHypothesis"](class_id=class_id, score=float(score))
        for class_id, score in hypotheses
    ]
    msg = types[MessageType.CLASSIFICATION.value](header=_ros_header(header), results=results)
    return _serialize(msg, MessageType.CLASSIFICATION)


def decode_classification(payload: bytes | memoryview) -> tuple[Header, list[tuple[str, float]]]:
    """The header and (class id, score) pairs of a vision_msgs/msg/Classification in CDR;
    BadMessageValue for a score that is not a number."""
    msg = _deserialize(payload, MessageType.CLASSIFICATION)
    results = [(str(h.class_id), float(h.score)) for h in msg.results]
    if not all(math.isfinite(score) for _, score in results):
        raise BadMessageValue("Classification has a non-finite score")
    return _header(msg.header), results


# -- helpers ---------------------------------------------------------------------------------------
def _deserialize(payload: bytes | memoryview, msgtype: MessageType) -> Any:
    from rosbags.serde import SerdeError

    try:
        return typestore().deserialize_cdr(bytes(payload), msgtype.value)
    except SerdeError as exc:
        raise MalformedMessage(f"{msgtype.value}: not its CDR ({_one_line(exc)})") from None
    except (ValueError, TypeError, IndexError, struct.error, UnicodeDecodeError) as exc:
        # rosbags' generated deserializers raise these on some bytes (invalid UTF-8 strings...).
        raise MalformedMessage(
            f"{msgtype.value}: not its CDR ({type(exc).__name__}: {_one_line(exc)})"
        ) from None


def _serialize(msg: Any, msgtype: MessageType) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype.value))


def _header(header: Any) -> Header:
    stamp_ns = int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)
    return Header(stamp_ns, str(header.frame_id))


def _ros_header(header: Header) -> Any:
    sec, nanosec = divmod(int(header.stamp_ns), NS_PER_S)
    if not _STAMP_SEC_MIN <= sec <= _STAMP_SEC_MAX:
        raise BadMessageValue(f"stamp {header.stamp_ns} ns is beyond a ROS 2 Time's int32 seconds")
    types = typestore().types
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
        frame_id=header.frame_id,
    )


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__
