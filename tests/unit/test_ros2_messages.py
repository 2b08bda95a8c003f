"""ROS 2 messages to arrays and back (common/ros2_messages.py), on real photographs.

Messages are built by rosbags' type store as a ROS 2 publisher's would be, and what this project
writes is read back by the same store (and, for type hashes, checked against the values ROS 2
Jazzy publishes).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import simplejpeg
import skimage.data

from common import ros2_messages as rm
from common.wire import WireError

# Published by ROS 2 Jazzy (rmw_zenoh's docs/design.md for String; `ros2 topic info -v` for the
# images): the store must give the same, or rmw_zenoh peers never match our keys.
GOLDEN_HASHES = {
    "std_msgs/msg/String": (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    ),
    rm.MessageType.IMAGE: "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    rm.MessageType.COMPRESSED_IMAGE: (
        "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a"
    ),
}
STAMP_NS = 1_732_000_000_123_456_789
# JPEG at quality 90 on a photograph: well over this PSNR (dB); a channel swap falls far below.
MIN_JPEG_PSNR_DB = 30.0


@pytest.fixture(scope="module")
def photo_bgr() -> np.ndarray:
    """skimage's astronaut, 512×512, shrunk to 96×128 and made BGR (the robot's layout)."""
    rgb = cv2.resize(skimage.data.astronaut(), (128, 96), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def ros_header(stamp_ns: int = STAMP_NS, frame_id: str = "camera") -> object:
    types = rm.typestore().types
    sec, nanosec = divmod(stamp_ns, rm.NS_PER_S)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def image_cdr(
    pixels: np.ndarray,
    encoding: str,
    *,
    pad: int = 0,
    height: int | None = None,
    width: int | None = None,
    step: int | None = None,
    data: np.ndarray | None = None,
) -> bytes:
    """A sensor_msgs/msg/Image of `pixels` (H×W×C) in CDR, rows padded by `pad` bytes; the
    keyword arguments override fields to make bad messages."""
    h, w = pixels.shape[:2]
    rows = pixels.reshape(h, w * pixels.shape[2])
    padded = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    msg = rm.typestore().types["sensor_msgs/msg/Image"](
        header=ros_header(),
        height=h if height is None else height,
        width=w if width is None else width,
        encoding=encoding,
        is_bigendian=0,
        step=padded.shape[1] if step is None else step,
        data=padded.reshape(-1) if data is None else data,
    )
    return bytes(rm.typestore().serialize_cdr(msg, "sensor_msgs/msg/Image"))


def compressed_cdr(data: bytes, fmt: str) -> bytes:
    msg = rm.typestore().types["sensor_msgs/msg/CompressedImage"](
        header=ros_header(), format=fmt, data=np.frombuffer(data, np.uint8)
    )
    return bytes(rm.typestore().serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


# -- raw images ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("encoding", "from_bgr"),
    [
        ("rgb8", cv2.COLOR_BGR2RGB),
        ("bgr8", None),
        ("rgba8", cv2.COLOR_BGR2RGBA),
        ("bgra8", cv2.COLOR_BGR2BGRA),
    ],
)
@pytest.mark.parametrize("pad", [0, 5])
def test_colour_images_decode_to_the_same_bgr_frame(
    photo_bgr: np.ndarray, encoding: str, from_bgr: int | None, pad: int
) -> None:
    pixels = photo_bgr if from_bgr is None else cv2.cvtColor(photo_bgr, from_bgr)
    frame = rm.decode_image(image_cdr(pixels, encoding, pad=pad))
    assert frame.image.dtype == np.uint8 and frame.image.flags.c_contiguous
    np.testing.assert_array_equal(frame.image, photo_bgr)
    assert frame.stamp_ns == STAMP_NS and frame.header.frame_id == "camera"


def test_mono_images_decode_to_grey_bgr(photo_bgr: np.ndarray) -> None:
    grey = cv2.cvtColor(photo_bgr, cv2.COLOR_BGR2GRAY)
    frame = rm.decode_image(image_cdr(grey[:, :, None], "mono8", pad=3))
    assert frame.image.shape == (*grey.shape, 3)
    for channel in range(3):
        np.testing.assert_array_equal(frame.image[:, :, channel], grey)


@pytest.mark.parametrize("encoding", ["16UC1", "yuv422", "bayer_rggb8", "32FC1", ""])
def test_an_unknown_encoding_is_refused_naming_the_known_ones(
    photo_bgr: np.ndarray, encoding: str
) -> None:
    with pytest.raises(rm.UnknownEncoding, match="known: rgb8, bgr8, mono8, rgba8, bgra8"):
        rm.decode_image(image_cdr(photo_bgr, encoding))


def test_an_empty_image_is_refused() -> None:
    empty = np.zeros((0, 0, 3), np.uint8)
    with pytest.raises(rm.EmptyImage, match="0×0"):
        rm.decode_image(image_cdr(empty, "bgr8", height=0, width=0, step=0))


def test_a_step_shorter_than_a_row_is_refused(photo_bgr: np.ndarray) -> None:
    with pytest.raises(rm.LayoutMismatch, match="step 100 is less than a row"):
        rm.decode_image(image_cdr(photo_bgr, "bgr8", step=100))


def test_data_that_disagrees_with_height_and_step_is_refused(photo_bgr: np.ndarray) -> None:
    short = photo_bgr.reshape(-1)[:-1]
    with pytest.raises(rm.LayoutMismatch, match="data has"):
        rm.decode_image(image_cdr(photo_bgr, "bgr8", data=short))


def test_an_image_over_the_limit_is_refused(photo_bgr: np.ndarray) -> None:
    with pytest.raises(rm.ImageTooLarge, match="over the limit of 1000"):
        rm.decode_image(image_cdr(photo_bgr, "bgr8"), max_bytes=1000)


def test_every_truncation_of_an_image_is_a_named_one_line_error() -> None:
    payload = image_cdr(np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3), "rgb8")
    for cut in range(len(payload)):
        with pytest.raises(rm.MalformedMessage) as caught:
            rm.decode_image(payload[:cut])
        assert "\n" not in str(caught.value) and "sensor_msgs/msg/Image" in str(caught.value)


def test_bytes_after_the_message_are_refused(photo_bgr: np.ndarray) -> None:
    with pytest.raises(rm.MalformedMessage):
        rm.decode_image(image_cdr(photo_bgr, "bgr8") + b"\x00" * 16)


def test_decode_errors_are_wire_errors() -> None:
    """Callers that catch WireError (bad input, keep serving) catch these too."""
    assert issubclass(rm.Ros2MessageError, WireError)
    with pytest.raises(ValueError):
        rm.decode_image(b"\x00\x01\x00\x00")


# -- compressed images -----------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["jpeg", "bgr8; jpeg compressed bgr8", "JPG", ""])
def test_jpeg_compressed_images_decode_to_bgr(photo_bgr: np.ndarray, fmt: str) -> None:
    _, jpeg = cv2.imencode(".jpg", photo_bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    frame = rm.decode_compressed_image(compressed_cdr(jpeg.tobytes(), fmt))
    assert frame.image.shape == photo_bgr.shape and frame.stamp_ns == STAMP_NS
    assert psnr_db(frame.image, photo_bgr) > MIN_JPEG_PSNR_DB


@pytest.mark.parametrize("fmt", ["png", "rgb8; png compressed rgb8", ""])
def test_png_compressed_images_decode_exactly(photo_bgr: np.ndarray, fmt: str) -> None:
    _, png = cv2.imencode(".png", photo_bgr)
    frame = rm.decode_compressed_image(compressed_cdr(png.tobytes(), fmt))
    np.testing.assert_array_equal(frame.image, photo_bgr)


def test_grey_compressed_images_decode_to_grey_bgr(photo_bgr: np.ndarray) -> None:
    grey = cv2.cvtColor(photo_bgr, cv2.COLOR_BGR2GRAY)
    _, png = cv2.imencode(".png", grey)
    frame = rm.decode_compressed_image(compressed_cdr(png.tobytes(), "png"))
    np.testing.assert_array_equal(frame.image, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    jpeg = simplejpeg.encode_jpeg(grey[:, :, None], quality=95, colorspace="GRAY")
    frame = rm.decode_compressed_image(compressed_cdr(jpeg, "jpeg"))
    assert psnr_db(frame.image[:, :, 0], grey) > MIN_JPEG_PSNR_DB


@pytest.mark.parametrize("fmt", ["tiff", "webp", "16UC1; compressedDepth png"])
def test_an_unknown_format_is_refused_naming_the_known_ones(
    photo_bgr: np.ndarray, fmt: str
) -> None:
    _, png = cv2.imencode(".png", photo_bgr)
    with pytest.raises(rm.UnknownImageFormat, match="known: jpeg, png"):
        rm.decode_compressed_image(compressed_cdr(png.tobytes(), fmt))


def test_a_png_with_alpha_is_refused_by_name(photo_bgr: np.ndarray) -> None:
    _, png = cv2.imencode(".png", cv2.cvtColor(photo_bgr, cv2.COLOR_BGR2BGRA))
    with pytest.raises(rm.UnknownImageFormat, match="color type 6"):
        rm.decode_compressed_image(compressed_cdr(png.tobytes(), "png"))


@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_corrupt_or_truncated_compressed_data_is_refused(photo_bgr: np.ndarray, fmt: str) -> None:
    _, data = cv2.imencode(f".{fmt}", photo_bgr)
    for cut in (0, 7, 40, data.size // 2):
        with pytest.raises(rm.CorruptImage) as caught:
            rm.decode_compressed_image(compressed_cdr(data.tobytes()[:cut], fmt))
        assert "\n" not in str(caught.value)


def test_a_compressed_image_over_the_limit_is_refused_before_decoding(
    photo_bgr: np.ndarray,
) -> None:
    _, jpeg = cv2.imencode(".jpg", photo_bgr)
    with pytest.raises(rm.ImageTooLarge):
        rm.decode_compressed_image(compressed_cdr(jpeg.tobytes(), "jpeg"), max_bytes=1000)


def test_decode_frame_picks_the_decoder_by_type(photo_bgr: np.ndarray) -> None:
    raw = rm.decode_frame(rm.MessageType.IMAGE, image_cdr(photo_bgr, "bgr8"))
    np.testing.assert_array_equal(raw.image, photo_bgr)
    _, png = cv2.imencode(".png", photo_bgr)
    packed = rm.decode_frame(rm.MessageType.COMPRESSED_IMAGE, compressed_cdr(png.tobytes(), ""))
    np.testing.assert_array_equal(packed.image, photo_bgr)
    with pytest.raises(rm.BadMessageValue, match="carries no frame"):
        rm.decode_frame(rm.MessageType.TWIST, rm.encode_twist(rm.Twist()))


# -- frames and outputs out ------------------------------------------------------------------------
def test_a_frame_becomes_a_jpeg_compressed_image_with_its_header(photo_bgr: np.ndarray) -> None:
    payload = rm.encode_compressed_image(photo_bgr, rm.Header(STAMP_NS, "cam0"))
    msg = rm.typestore().deserialize_cdr(payload, "sensor_msgs/msg/CompressedImage")
    assert msg.format == "jpeg" and bytes(msg.data[:2]) == b"\xff\xd8"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(STAMP_NS, rm.NS_PER_S)
    back = rm.decode_compressed_image(payload)
    assert back.header == rm.Header(STAMP_NS, "cam0")
    assert psnr_db(back.image, photo_bgr) > MIN_JPEG_PSNR_DB


def test_a_stamp_beyond_int32_seconds_is_refused(photo_bgr: np.ndarray) -> None:
    with pytest.raises(rm.BadMessageValue, match="int32 seconds"):
        rm.encode_compressed_image(photo_bgr, rm.Header(2**31 * rm.NS_PER_S))


@pytest.mark.parametrize(
    ("array", "labels"),
    [
        (np.linspace(-1, 1, 1000, dtype=np.float32).reshape(1, 1000), None),
        (np.arange(2 * 3 * 4 * 5, dtype=np.float64).reshape(2, 3, 4, 5), ["n", "c", "h", "w"]),
        (np.array([3, 1, 2], dtype=np.int64), None),
        (np.float32(0.25), None),
    ],
)
def test_outputs_round_trip_as_float32_multi_arrays(
    array: np.ndarray, labels: list[str] | None
) -> None:
    payload = rm.encode_float32_multi_array(array, labels)
    back, got_labels = rm.decode_float32_multi_array(payload)
    np.testing.assert_array_equal(back, np.asarray(array, np.float32))
    expected = labels or [f"axis{i}" for i in range(np.ndim(array))]
    assert list(got_labels) == expected
    msg = rm.typestore().deserialize_cdr(payload, "std_msgs/msg/Float32MultiArray")
    shape = np.shape(array)
    assert [d.stride for d in msg.layout.dim] == [math.prod(shape[i:]) for i in range(len(shape))]


def test_a_non_numeric_output_or_wrong_labels_are_refused() -> None:
    with pytest.raises(rm.BadMessageValue, match="not numeric"):
        rm.encode_float32_multi_array(np.array(["a"]))
    with pytest.raises(rm.BadMessageValue, match="1 labels for an array of 2 axes"):
        rm.encode_float32_multi_array(np.zeros((2, 2)), ["x"])


@pytest.mark.parametrize("shape", [(1, 1, 6, 8), (6, 8)])
def test_image_shaped_outputs_become_32fc1_images(shape: tuple[int, ...]) -> None:
    disparity = np.linspace(0, 64, 48, dtype=np.float32).reshape(shape)
    assert rm.is_image_shaped(shape)
    payload = rm.encode_image_32fc1(disparity, rm.Header(STAMP_NS, "left"))
    msg = rm.typestore().deserialize_cdr(payload, "sensor_msgs/msg/Image")
    assert (msg.height, msg.width, msg.encoding, msg.step, msg.is_bigendian) == (
        6,
        8,
        "32FC1",
        32,
        0,
    )
    assert msg.header.frame_id == "left" and msg.header.stamp.nanosec == STAMP_NS % rm.NS_PER_S
    pixels = np.frombuffer(msg.data.tobytes(), "<f4").reshape(6, 8)
    np.testing.assert_array_equal(pixels, disparity.reshape(6, 8))


@pytest.mark.parametrize(
    "shape", [(1, 3, 6, 8), (2, 1, 6, 8), (48,), (1, 6, 8), (0, 8), (1, 1000), (8, 1)]
)
def test_other_outputs_are_not_images(shape: tuple[int, ...]) -> None:
    assert not rm.is_image_shaped(shape)
    with pytest.raises(rm.BadMessageValue, match="is not an image"):
        rm.encode_image_32fc1(np.zeros(shape, np.float32), rm.Header(0))


def test_twists_round_trip_and_non_finite_velocities_are_refused() -> None:
    twist = rm.Twist(linear=(0.5, 0.0, 0.0), angular=(0.0, 0.0, -0.25))
    assert rm.decode_twist(rm.encode_twist(twist)) == twist
    with pytest.raises(rm.BadMessageValue, match="finite"):
        rm.encode_twist(rm.Twist(linear=(math.nan, 0.0, 0.0)))
    types = rm.typestore().types
    vector = types["geometry_msgs/msg/Vector3"]
    bad = types["geometry_msgs/msg/Twist"](linear=vector(math.inf, 0, 0), angular=vector(0, 0, 0))
    payload = bytes(rm.typestore().serialize_cdr(bad, "geometry_msgs/msg/Twist"))
    with pytest.raises(rm.BadMessageValue, match="non-finite"):
        rm.decode_twist(payload)
    with pytest.raises(rm.MalformedMessage):
        rm.decode_twist(payload[:20])


# -- type names and hashes -------------------------------------------------------------------------
def test_type_hashes_are_the_ones_ros2_jazzy_publishes() -> None:
    for msgtype, expected in GOLDEN_HASHES.items():
        if isinstance(msgtype, rm.MessageType):
            assert rm.type_hash(msgtype) == expected
        else:
            assert rm.typestore().hash_rihs01(msgtype) == expected
    for msgtype in rm.MessageType:
        assert rm.type_hash(msgtype).startswith("RIHS01_") and len(rm.type_hash(msgtype)) == 71


def test_dds_type_names_follow_rmw_zenoh() -> None:
    assert rm.dds_type_name(rm.MessageType.IMAGE) == "sensor_msgs::msg::dds_::Image_"
    assert rm.dds_type_name(rm.MessageType.TWIST) == "geometry_msgs::msg::dds_::Twist_"
    assert (
        rm.dds_type_name(rm.MessageType.FLOAT32_MULTI_ARRAY)
        == "std_msgs::msg::dds_::Float32MultiArray_"
    )


def test_message_type_names_the_known_types() -> None:
    assert rm.message_type("sensor_msgs/msg/Image") is rm.MessageType.IMAGE
    with pytest.raises(rm.BadMessageValue, match="known: sensor_msgs/msg/Image"):
        rm.message_type("sensor_msgs/msg/PointCloud2")


# -- stamped standard messages ---------------------------------------------------------------------
# The RIHS01 hashes of the types this project registers from their upstream definitions, as
# zenoh-ros2-sdk (an rmw_zenoh written apart from this project, with its own type hashing)
# computes them from upstream's .msg files, comments included (vision_msgs 4.1.1, Isaac ROS
# 4.4.0); the core ones as rosbags' Jazzy store gives them.
STANDARD_HASHES = {
    rm.MessageType.CLASSIFICATION: (
        "RIHS01_f74db28d0eaef3afb78f48bf2161cd709a1383a0309d3454383b25be11345143"
    ),
    rm.MessageType.TENSOR_LIST: (
        "RIHS01_498b4418eed651d1eb843a154ac3dd6b7612b3fa851e1bd930f9f0c2e862cf6c"
    ),
    rm.MessageType.CAMERA_INFO: (
        "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275"
    ),
    rm.MessageType.TWIST_STAMPED: (
        "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64"
    ),
}
HEADER = rm.Header(STAMP_NS, "camera_optical")


def test_standard_type_hashes() -> None:
    for msgtype, expected in STANDARD_HASHES.items():
        assert rm.type_hash(msgtype) == expected
    assert rm.dds_type_name(rm.MessageType.TENSOR_LIST) == (
        "isaac_ros_tensor_list_interfaces::msg::dds_::TensorList_"
    )


@pytest.mark.parametrize(
    ("dtype", "code"),
    [
        (np.int8, 1),
        (np.uint8, 2),
        (np.int16, 3),
        (np.uint16, 4),
        (np.int32, 5),
        (np.uint32, 6),
        (np.int64, 7),
        (np.uint64, 8),
        (np.float32, 9),
        (np.float64, 10),
    ],
)
def test_tensor_list_round_trip_with_isaac_ros_codes(dtype: type, code: int) -> None:
    array = (np.arange(24).reshape(2, 3, 4) % 100).astype(dtype)
    payload = rm.encode_tensor_list({"output.1": array, "scalar": np.asarray(dtype(7))}, HEADER)
    msg = rm.typestore().deserialize_cdr(payload, rm.MessageType.TENSOR_LIST.value)
    tensor = msg.tensors[0]
    assert (tensor.name, tensor.data_type, int(tensor.shape.rank)) == ("output.1", code, 3)
    assert list(tensor.shape.dims) == [2, 3, 4]
    assert list(tensor.strides) == [12 * array.itemsize, 4 * array.itemsize, array.itemsize]
    header, tensors = rm.decode_tensor_list(payload)
    assert header == HEADER
    assert tensors["output.1"].dtype == array.dtype and np.array_equal(tensors["output.1"], array)
    assert tensors["scalar"].shape == () and tensors["scalar"] == 7


def test_tensor_list_widens_float16_and_bool_and_refuses_the_rest() -> None:
    _, tensors = rm.decode_tensor_list(
        rm.encode_tensor_list(
            {"h": np.array([0.5, 2.0], np.float16), "b": np.array([True, False])}, HEADER
        )
    )
    assert tensors["h"].dtype == np.float32 and tensors["h"].tolist() == [0.5, 2.0]
    assert tensors["b"].dtype == np.uint8 and tensors["b"].tolist() == [1, 0]
    with pytest.raises(rm.BadMessageValue, match="not a tensor type"):
        rm.encode_tensor_list({"c": np.zeros(2, np.complex64)}, HEADER)


def _tensor_list_with(**changes: object) -> bytes:
    payload = rm.encode_tensor_list({"t": np.zeros((2, 3), np.float32)}, HEADER)
    msg = rm.typestore().deserialize_cdr(payload, rm.MessageType.TENSOR_LIST.value)
    tensor = msg.tensors[0]
    for name, value in changes.items():
        if name == "rank":
            tensor.shape.rank = value
        else:
            setattr(tensor, name, value)
    return bytes(rm.typestore().serialize_cdr(msg, rm.MessageType.TENSOR_LIST.value))


@pytest.mark.parametrize(
    ("changes", "error", "named"),
    [
        ({"data_type": 11}, rm.BadMessageValue, "data type 11"),
        ({"rank": 3}, rm.LayoutMismatch, "rank 3, 2 dims"),
        ({"strides": np.array([4, 4], np.uint64)}, rm.LayoutMismatch, "C-order byte strides"),
        ({"data": np.zeros(5, np.uint8)}, rm.LayoutMismatch, "5 bytes"),
    ],
)
def test_a_tensor_list_that_disagrees_with_itself_is_named(
    changes: dict[str, object], error: type[Exception], named: str
) -> None:
    with pytest.raises(error, match=named):
        rm.decode_tensor_list(_tensor_list_with(**changes))


def test_classification_is_the_softmax_top_5() -> None:
    logits = np.array([[0.5, 3.0, -1.0, 2.0, 2.0, 0.0, 4.0]], np.float32)
    top = rm.top_classes(logits)
    expected = np.exp(logits[0] - logits.max()) / np.exp(logits[0] - logits.max()).sum()
    assert [c for c, _ in top] == ["6", "1", "3", "4", "0"]  # a tie: the lower index first
    assert [s for _, s in top] == pytest.approx([expected[int(c)] for c, _ in top])
    header, results = rm.decode_classification(rm.encode_classification(top, HEADER))
    assert header == HEADER and [c for c, _ in results] == [c for c, _ in top]
    assert [s for _, s in results] == pytest.approx([s for _, s in top])
    assert rm.top_classes(np.array([1.0, 2.0]))[0][0] == "1"
    assert rm.is_class_scores((1, 1000)) and rm.is_class_scores((3,))
    assert not rm.is_class_scores((1, 1)) and not rm.is_class_scores((2, 3))
    with pytest.raises(rm.BadMessageValue, match="no classifier's scores"):
        rm.top_classes(np.array([[1.0, float("nan")]]))


def _camera_info(fx: float = 500.0, fy: float = 500.0, **fields: object) -> bytes:
    k = (fx, 0.0, 320.0, 0.0, fy, 240.0, 0.0, 0.0, 1.0)
    p = (fx, 0.0, 320.0, 0.0, 0.0, fy, 240.0, 0.0, 0.0, 0.0, 1.0, 0.0)
    info = rm.CameraInfo(HEADER, 480, 640, k=k, p=p, d=(0.1, 0.0, 0.0, 0.0, 0.0))
    msg = rm.typestore().deserialize_cdr(
        rm.encode_camera_info(info), rm.MessageType.CAMERA_INFO.value
    )
    for name, value in fields.items():
        setattr(msg, name, value)
    return bytes(rm.typestore().serialize_cdr(msg, rm.MessageType.CAMERA_INFO.value))


def test_camera_info_round_trip_and_bad_geometry_named() -> None:
    info = rm.decode_camera_info(_camera_info())
    assert (info.header, info.height, info.width, info.fx, info.cx, info.cy) == (
        HEADER,
        480,
        640,
        500.0,
        320.0,
        240.0,
    )
    assert info.d == (0.1, 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(rm.BadCameraInfo, match="not a calibrated camera"):
        rm.decode_camera_info(_camera_info(fx=0.0))
    with pytest.raises(rm.BadCameraInfo, match="not a calibrated camera"):
        rm.decode_camera_info(_camera_info(fy=-1.0))
    with pytest.raises(rm.BadCameraInfo, match="non-finite"):
        rm.decode_camera_info(_camera_info(d=np.array([float("nan")])))
    with pytest.raises(rm.BadCameraInfo, match="no pixels"):
        rm.decode_camera_info(_camera_info(width=0))


def test_twist_stamped_round_trip() -> None:
    twist = rm.Twist((0.3, 0.0, 0.0), (0.0, 0.0, 0.1))
    assert rm.decode_twist_stamped(rm.encode_twist_stamped(twist, HEADER)) == (HEADER, twist)
    with pytest.raises(rm.BadMessageValue, match="finite velocities"):
        rm.encode_twist_stamped(rm.Twist((math.inf, 0.0, 0.0)), HEADER)
