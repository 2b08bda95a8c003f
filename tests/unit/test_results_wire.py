"""The messages between a robot and its applications (`common.wire.robot_to_app`,
`common.wire.app_to_robot`): results round-trip in every result codec within its bound, lossy
codecs are refused by name, outputs a codec cannot carry go raw; frames in every image encoding
decode to the BGR image that was sent (exactly, or within JPEG's error), and every kind of bad
frame is a named WireError with a one-line reason. Also the robot's fitting of a frame to the
model's size, and the top-5 rows `elasticfog results` prints."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from common.wire import (
    CorruptPayload,
    InvalidValue,
    ShapeMismatch,
    UnknownCodec,
    WireError,
    decode_tensors,
    encode_raw,
)
from common.wire.app_to_robot import FrameIn, ImageEncoding, ImageIn, decode_image, image_in
from common.wire.robot_to_app import (
    FP16_RELATIVE_ERROR,
    FrameResultMessage,
    ServedBy,
    encode_output,
    result_codec,
)
from robotd.results.cli import top_k
from robotd.sources.frame_sources import fit_frame

MAX_SIDE_PX = 8192
LIMIT_BYTES = 1 << 24


def photo(height: int = 48, width: int = 64) -> np.ndarray:
    """A smooth colour image (JPEG keeps it within a few levels)."""
    y, x = np.mgrid[0:height, 0:width]
    return np.stack(
        [(x * 255 // max(1, width - 1)), (y * 255 // max(1, height - 1)), (x + y) % 256], axis=2
    ).astype(np.uint8)


def result_message(outputs: dict[str, np.ndarray], codec: str) -> FrameResultMessage:
    return FrameResultMessage(
        robot="robot-1",
        frame=3,
        stamp_ns=1_700_000_000_000_000_001,
        served_by=ServedBy.ROBOT,
        deployment=None,
        action="P",
        cut=None,
        codec=None,
        fallback=False,
        latency_s=0.01,
        published_ns=1_700_000_000_010_000_000,
        outputs={name: encode_output(a, codec) for name, a in outputs.items()},
    )


@pytest.mark.parametrize(
    ("name", "codec"), [("raw", "raw"), ("fp16", "fp16"), ("zstd", "raw+zstd")]
)
def test_results_round_trip_within_their_codec_bound(name: str, codec: str) -> None:
    rng = np.random.default_rng(0)
    logits = rng.standard_normal((1, 1000)).astype(np.float32) * 10
    disparity = rng.random((1, 1, 24, 32)).astype(np.float32) * 64
    classes = np.array([[3, 1, 4]], dtype=np.int64)
    message = result_message({"logits": logits, "disparity": disparity, "cls": classes}, codec)
    back = FrameResultMessage.from_wire(message.to_wire())
    assert back.stamp_ns == message.stamp_ns and back.served_by is ServedBy.ROBOT
    assert back.outputs["logits"].codec == codec
    # fp16 cannot carry integers: they go raw.
    assert back.outputs["cls"].codec == ("raw" if codec == "fp16" else codec)
    outputs = decode_tensors(back.outputs, max_bytes=LIMIT_BYTES)
    np.testing.assert_array_equal(outputs["cls"], classes)
    for key, want in (("logits", logits), ("disparity", disparity)):
        got = outputs[key]
        assert got.dtype == want.dtype and got.shape == want.shape
        if codec == "fp16":
            np.testing.assert_allclose(got, want, rtol=FP16_RELATIVE_ERROR, atol=0)
        else:
            np.testing.assert_array_equal(got, want)
    assert result_codec(name) == codec


def test_fp16_overflow_goes_raw() -> None:
    big = np.array([1e6, -3.0], dtype=np.float32)
    assert encode_output(big, "fp16").codec == "raw"


@pytest.mark.parametrize("codec", ["int8", "int8+zstd", "jpeg80", "png", "gzip"])
def test_lossy_or_unknown_result_codecs_are_refused_by_name(codec: str) -> None:
    with pytest.raises(UnknownCodec, match=re.escape(f"results codec '{codec}' is not allowed")):
        result_codec(codec)


@pytest.mark.parametrize("encoding", ["png", "rgb8", "bgr8"])
def test_lossless_frames_decode_to_the_image_sent(encoding: str) -> None:
    image = photo()
    message = FrameIn(stamp_ns=42, images={"image": image_in(image, encoding)})
    back = FrameIn.from_wire(message.to_wire())
    assert back.stamp_ns == 42
    np.testing.assert_array_equal(
        decode_image(back.images["image"], max_side_px=MAX_SIDE_PX), image
    )


def test_mono8_and_jpeg_frames_decode_to_bgr() -> None:
    image = photo()
    grey = decode_image(image_in(image, "mono8"), max_side_px=MAX_SIDE_PX)
    assert grey.shape == image.shape and (grey[:, :, 0] == grey[:, :, 2]).all()
    jpeg = decode_image(image_in(image, "jpeg", quality=95), max_side_px=MAX_SIDE_PX)
    assert jpeg.shape == image.shape
    assert np.abs(jpeg.astype(int) - image.astype(int)).mean() < 4


def test_a_jpeg_decodes_at_the_smallest_scale_that_covers_the_fit() -> None:
    jpeg = image_in(photo(480, 640), "jpeg")
    assert decode_image(jpeg, max_side_px=MAX_SIDE_PX, fit=(224, 224)).shape == (240, 320, 3)
    assert decode_image(jpeg, max_side_px=MAX_SIDE_PX, fit=(112, 112)).shape == (120, 160, 3)
    assert decode_image(jpeg, max_side_px=MAX_SIDE_PX, fit=(300, 300)).shape == (300, 400, 3)  # 5/8
    # A wide fit of a tall image: the rectangle is the image's width, which must stay >= 200.
    tall = image_in(photo(640, 480), "jpeg")
    assert decode_image(tall, max_side_px=MAX_SIDE_PX, fit=(100, 200)).shape == (320, 240, 3)


def test_bad_frames_are_named_errors() -> None:
    good = image_in(photo(), "jpeg")
    data = bytes(good.data)
    cases: list[tuple[type[WireError], object]] = [
        (CorruptPayload, lambda: ImageIn(encoding=ImageEncoding.JPEG, data=data[:40])),
        (CorruptPayload, lambda: ImageIn(encoding=ImageEncoding.PNG, data=b"not a png at all...")),
        (
            ShapeMismatch,
            lambda: ImageIn(encoding=ImageEncoding.RGB8, data=b"abc", height=2, width=2),
        ),
        (InvalidValue, lambda: ImageIn(encoding=ImageEncoding.MONO8, data=b"", height=0, width=0)),
        (ShapeMismatch, lambda: ImageIn(encoding=ImageEncoding.JPEG, data=data, height=5, width=5)),
    ]
    for error, make in cases:
        with pytest.raises(error) as info:
            decode_image(make(), max_side_px=MAX_SIDE_PX)  # type: ignore[operator]
        assert "\n" not in str(info.value)
    with pytest.raises(InvalidValue, match="larger than 32 px"):
        decode_image(good, max_side_px=32)
    with pytest.raises(InvalidValue, match="expected one of"):
        FrameIn.from_wire(
            encode_raw(
                {
                    "v": 2,
                    "t": "frame_in",
                    "stamp_ns": 1,
                    "images": {"x": {"encoding": "yuv422", "data": b"x"}},
                }
            )
        )
    with pytest.raises(InvalidValue, match="at least one image"):
        FrameIn(stamp_ns=1, images={})


def test_a_frame_is_fitted_to_the_model_without_stretching() -> None:
    image = photo(480, 640)
    assert fit_frame(image, 480, 640) is image
    fitted = fit_frame(image, 224, 224)
    assert fitted.shape == (224, 224, 3)
    # The centred 480×480 square, shrunk: its left edge is the image's column 80.
    square = image[:, 80:560]
    np.testing.assert_allclose(fitted[:, 0].mean(0), square[:, :2].mean((0, 1)), atol=6)


def test_a_fitted_frame_is_anti_aliased_at_whole_and_other_ratios() -> None:
    """Stripes one pixel wide, shrunk 2x (a box average) and 480 -> 224 (a low-pass filter
    first): grey, not the moiré plain sampling gives."""
    stripes = np.zeros((480, 480, 3), np.uint8)
    stripes[:, ::2] = 255
    assert np.all(fit_frame(stripes, 240, 240) == 128)  # each box is one black, one white
    fitted = fit_frame(stripes, 224, 224).astype(np.float64)
    sampled = cv2.resize(stripes, (224, 224), interpolation=cv2.INTER_LINEAR).astype(np.float64)
    assert abs(fitted.mean() - 127.5) < 2
    assert fitted.std() < 0.2 * sampled.std()


def test_top5_of_a_vector_and_of_each_row() -> None:
    row = np.array([0.1, 5.0, 3.0, 4.0, -1.0, 2.0, 1.0], dtype=np.float32)
    assert top_k(row) == [[(1, 5.0), (3, 4.0), (2, 3.0), (5, 2.0), (6, 1.0)]]
    assert top_k(np.stack([row, -row]))[1][0] == (4, 1.0)  # type: ignore[index]
    assert top_k(np.zeros((1, 1, 4, 4), np.float32)) is None


def test_a_result_line_names_the_frame_its_path_and_each_outputs_top5() -> None:
    from robotd.results.cli import result_json, result_line
    from robotd.results.client import Result

    logits = np.array([[0.1, 5.0, 3.0, 4.0, -1.0, 2.0, 1.0]], dtype=np.float32)
    disparity = np.zeros((1, 1, 4, 6), np.float32)
    message = result_message({"logits": logits, "disparity": disparity}, "raw")
    result = Result(message, {"logits": logits, "disparity": disparity}, received_ns=1)
    line = result_line(result)
    assert line.startswith("frame 3  stamp 1700000000000000001 (")
    assert "served_by robot  action P  latency 10.0 ms" in line
    assert "logits [1, 7] top5 1:5 3:4 2:3 5:2 6:1" in line
    assert line.endswith("disparity [1, 1, 4, 6]")
    obj = result_json(result)
    assert obj["stamp_ns"] == message.stamp_ns and obj["served_by"] == "robot"
    assert obj["outputs"]["logits"]["top5"] == [[(1, 5.0), (3, 4.0), (2, 3.0), (5, 2.0), (6, 1.0)]]
    assert obj["outputs"]["disparity"] == {
        "dtype": "float32",
        "shape": [1, 1, 4, 6],
        "codec": "raw",
        "top5": None,
    }
