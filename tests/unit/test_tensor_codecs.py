"""Per-tensor codecs: every codec round-trips (exactly where lossless, within its bound where
lossy), each kind of bad encoded tensor gets its own named error through the full decode of an
InferRequest, and random mutations of encoded payloads raise nothing but WireError subclasses."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import cv2
import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from skimage import data as images

from common.wire import (
    CODEC_RAW,
    DTYPES,
    SCHEMA_VERSION,
    BadDtype,
    BadQuantization,
    CodecMismatch,
    CorruptPayload,
    EncodedTensor,
    ErrorReply,
    InvalidValue,
    PayloadTooLarge,
    ShapeMismatch,
    TensorTooLarge,
    UnknownCodec,
    WireError,
    applies,
    codec_names_for,
    decode,
    decode_encoded,
    decode_tensors,
    encode_raw,
    encode_tensor_as,
    error_reply,
    parse_codec,
)
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import CODECS

MAX_BYTES = 64 * 1024 * 1024
FLOAT_CODECS = ["raw", "fp16", "int8", "int8+zstd", "raw+zstd"]
IMAGE_CODECS = ["raw", "raw+zstd", "jpeg<Q>", "png", "h264"]
# jpeg80 of the photographs below measures 32.5-37.3 dB; a regression in quality, subsampling or
# colorspace handling drops well under this.
JPEG80_MIN_PSNR_DB = 30.0
FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# -- fixtures --------------------------------------------------------------------------------------
def photo(name: str, height: int, width: int) -> np.ndarray:
    """A real photograph (skimage ships them, no download) as uint8 1×H×W×3."""
    rgb = getattr(images, name)()
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)[None]


def feature_map(shape: tuple[int, ...] = (1, 8, 12, 16), seed: int = 0) -> np.ndarray:
    """ReLU-like float32 activations: about half zeros, a long tail."""
    rng = np.random.default_rng(seed)
    return np.maximum(rng.normal(0.0, 2.0, size=shape), 0).astype(np.float32)


def request(tensors: dict[str, EncodedTensor]) -> InferRequest:
    return InferRequest(
        robot="robot-1",
        frame=1,
        model_digest="9f" * 32,
        cut=2,
        tensors=tensors,
        deadline_s=0.25,
        sent_at=1.0,
    )


def payload_with(tensor: EncodedTensor | dict[str, Any]) -> bytes:
    """An InferRequest payload carrying `tensor` as "x", packed without the local checks (so a
    bad tensor reaches the receiver as a bad sender would send it)."""
    body = {"v": SCHEMA_VERSION, "t": "infer_request", **request({"ok": _ok()}).to_map()}
    enc = tensor.to_map() if isinstance(tensor, EncodedTensor) else tensor
    body["tensors"] = {"x": _plain(enc)}
    return encode_raw(body)


def decode_fully(data: bytes, max_bytes: int = MAX_BYTES) -> dict[str, np.ndarray]:
    """What a deployment does with a payload: decode the request, then its tensors."""
    message = InferRequest.from_wire(data)
    return decode_tensors(message.tensors, max_bytes=max_bytes)


def round_trip(array: np.ndarray, codec: str) -> tuple[EncodedTensor, np.ndarray]:
    """Encode, send inside an InferRequest, decode; checks the decoded array's form."""
    enc = encode_tensor_as(array, codec)
    got = decode_fully(request({"x": enc}).to_wire())["x"]
    assert got.dtype == DTYPES[array.dtype.name]
    assert got.shape == array.shape
    assert got.flags.c_contiguous
    # Decoding the locally built record gives the same array as decoding the received one.
    assert np.array_equal(decode_encoded(enc, max_bytes=MAX_BYTES), got, equal_nan=True)
    return enc, got


def _ok() -> EncodedTensor:
    return EncodedTensor.raw(np.zeros(2, np.float32))


def _plain(value: Any) -> Any:
    """Memoryviews (data as encoded) as bytes, so the map can be packed again."""
    if isinstance(value, memoryview):
        return bytes(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255**2 / mse)


# -- names -----------------------------------------------------------------------------------------
def test_codec_names_are_the_contract() -> None:
    fixed = ["raw", "fp16", "int8", "int8+zstd", "raw+zstd", "png", "h264"]
    jpeg = [f"jpeg{q}" for q in range(1, 101)]
    assert sorted(CODECS) == sorted(fixed + jpeg)
    for name in fixed + jpeg:
        assert parse_codec(name).name == name
    assert CODEC_RAW == "raw"
    lossless = {name for name, codec in CODECS.items() if not codec.lossy}
    assert lossless == {"raw", "raw+zstd", "png"}


@pytest.mark.parametrize("name", ["jpeg0", "jpeg101", "jpeg080", "JPEG80", "jpeg", "zstd", "", 3])
def test_unknown_codec_names_list_the_valid_ones(name: Any) -> None:
    with pytest.raises(UnknownCodec) as info:
        parse_codec(name)
    text = str(info.value)
    assert repr(name) in text
    assert "raw, fp16, int8, int8+zstd, raw+zstd, jpeg<Q> (Q = 1..100), png, h264" in text


def test_which_codecs_apply() -> None:
    assert codec_names_for("float32", (1, 64, 60, 80)) == FLOAT_CODECS
    assert codec_names_for("float64", (3,)) == FLOAT_CODECS
    assert codec_names_for("float16", (3,)) == ["raw", "int8", "int8+zstd", "raw+zstd"]
    for shape in [(240, 320), (240, 320, 1), (240, 320, 3), (1, 240, 320, 1), (1, 240, 320, 3)]:
        assert codec_names_for("uint8", shape) == IMAGE_CODECS
    # h264's 4:2:0 chroma needs even sides.
    assert codec_names_for("uint8", (239, 320, 3)) == IMAGE_CODECS[:-1]
    # NCHW, a batch of 2, 4 channels, an empty image: not images.
    for shape in [(1, 3, 240, 320), (2, 240, 320, 3), (240, 320, 4), (0, 320), (320,)]:
        assert codec_names_for("uint8", shape) == ["raw", "raw+zstd"]
    for dtype in ("bool", "int8", "int64", "uint16"):
        assert codec_names_for(dtype, (240, 320, 3)) == ["raw", "raw+zstd"]
    assert applies("jpeg80", "uint8", (240, 320, 3))
    assert not applies("jpeg80", "float32", (240, 320, 3))
    assert not applies("fp16", np.dtype(np.int32), (4,))
    with pytest.raises(UnknownCodec):
        applies("jpg", "uint8", (240, 320, 3))


def test_encoding_refuses_what_a_codec_cannot_carry() -> None:
    with pytest.raises(CodecMismatch, match="codecs for it: raw, fp16, int8, int8\\+zstd"):
        encode_tensor_as(feature_map(), "jpeg80")
    with pytest.raises(CodecMismatch, match="'int8' does not apply to a int64"):
        encode_tensor_as(np.arange(4), "int8")
    with pytest.raises(UnknownCodec):
        encode_tensor_as(feature_map(), "webp")
    with pytest.raises(BadDtype):
        encode_tensor_as(np.zeros(2, np.complex64), "raw")
    with pytest.raises(InvalidValue, match="NaN"):
        encode_tensor_as(np.array([1.0, np.nan], np.float32), "int8")
    with pytest.raises(InvalidValue, match="float16"):
        encode_tensor_as(np.array([1.0, 1e5], np.float32), "fp16")


# -- lossless codecs -------------------------------------------------------------------------------
any_array = hnp.arrays(
    dtype=st.sampled_from(list(DTYPES)),
    shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=6),
)


@settings(max_examples=150, deadline=None)
@given(array=any_array, codec=st.sampled_from(["raw", "raw+zstd"]))
def test_raw_and_zstd_round_trip_exactly(array: np.ndarray, codec: str) -> None:
    enc, got = round_trip(array, codec)
    assert got.tobytes() == array.tobytes()  # bitwise, so NaNs compare equal too
    assert enc.scale is None and enc.zero_point is None


def test_raw_sends_the_array_bytes_without_a_copy() -> None:
    array = feature_map()
    enc = EncodedTensor.raw(array)
    assert np.shares_memory(np.frombuffer(enc.data, np.uint8), array)
    assert enc.nbytes == array.nbytes


def test_zstd_shrinks_a_relu_feature_map() -> None:
    array = feature_map((1, 64, 60, 80))
    assert encode_tensor_as(array, "raw+zstd").nbytes < 0.7 * array.nbytes


# -- fp16 and int8 ---------------------------------------------------------------------------------
def _floats(dtype: str, bound: float) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(
        dtype=dtype,
        shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=6),
        elements=st.floats(-bound, bound, width=np.dtype(dtype).itemsize * 8),
    )


@settings(max_examples=150, deadline=None)
@given(array=_floats("float32", 65504) | _floats("float64", 65504))
def test_fp16_is_the_float16_rounding(array: np.ndarray) -> None:
    enc, got = round_trip(array, "fp16")
    assert enc.nbytes == 2 * array.size
    assert np.array_equal(got, array.astype(np.float16).astype(array.dtype))


def test_fp16_keeps_inf_and_nan_of_the_source() -> None:
    array = np.array([1.5, np.inf, -np.inf, np.nan], np.float32)
    _, got = round_trip(array, "fp16")
    assert np.array_equal(got, array, equal_nan=True)


def _check_int8_bound(array: np.ndarray, enc: EncodedTensor, got: np.ndarray) -> None:
    """Every element within scale/2 of its channel (plus the rounding of the decoded dtype)."""
    assert enc.scale is not None and enc.zero_point is not None
    shape = array.shape
    groups = (shape[0], shape[1], -1) if len(shape) in (3, 4) else (1, 1, -1)
    channels = shape[1] if len(shape) in (3, 4) else 1
    assert enc.scale.shape == enc.zero_point.shape == (channels,)
    if array.size == 0:
        return
    x = array.astype(np.float64).reshape(groups)
    err = np.abs(got.astype(np.float64).reshape(groups) - x)
    rounding = np.abs(got).astype(np.float64).reshape(groups) * np.finfo(array.dtype).eps
    bound = enc.scale.astype(np.float64)[None, :, None] / 2 * (1 + 1e-6) + rounding
    assert (err <= bound).all(), float((err - bound).max())
    assert (got[array == 0] == 0).all()  # zeros (most of a ReLU's output) decode exactly


@settings(max_examples=150, deadline=None)
@given(
    array=_floats("float32", 1e6) | _floats("float64", 1e6) | _floats("float16", 65504),
    codec=st.sampled_from(["int8", "int8+zstd"]),
)
def test_int8_error_is_at_most_half_a_step(array: np.ndarray, codec: str) -> None:
    enc, got = round_trip(array, codec)
    _check_int8_bound(array, enc, got)


def test_int8_is_per_channel_on_a_feature_map() -> None:
    array = feature_map((1, 64, 60, 80))
    array[:, 5] *= 100  # one loud channel must not coarsen the others
    enc, got = round_trip(array, "int8")
    assert enc.scale is not None and enc.scale[5] > 50 * enc.scale[4]
    assert enc.nbytes == array.size + 2 * 64 * 4
    _check_int8_bound(array, enc, got)
    zstd_enc, _ = round_trip(array, "int8+zstd")
    assert zstd_enc.nbytes < enc.nbytes


# -- images ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["astronaut", "chelsea"])
@pytest.mark.parametrize(("height", "width"), [(240, 320), (224, 224)])
def test_photographs_through_jpeg_and_png(name: str, height: int, width: int) -> None:
    rgb = photo(name, height, width)
    jpeg, got = round_trip(rgb, "jpeg80")
    assert psnr_db(got, rgb) >= JPEG80_MIN_PSNR_DB
    png, got = round_trip(rgb, "png")
    assert np.array_equal(got, rgb)
    assert jpeg.nbytes < png.nbytes < rgb.nbytes
    gray = cv2.cvtColor(rgb[0], cv2.COLOR_RGB2GRAY)
    for shape in [(height, width), (height, width, 1), (1, height, width, 1)]:
        _, got = round_trip(gray.reshape(shape), "png")
        assert np.array_equal(got, gray.reshape(shape))
        _, got = round_trip(gray.reshape(shape), "jpeg80")
        assert psnr_db(got, gray.reshape(shape)) >= JPEG80_MIN_PSNR_DB
    _, got = round_trip(rgb[0], "jpeg95")  # H×W×3 without a batch
    assert psnr_db(got, rgb[0]) > psnr_db(decode_encoded(jpeg, max_bytes=MAX_BYTES), rgb)


# -- strict decode: a named error for each kind of bad tensor --------------------------------------
def _enc(**fields: Any) -> EncodedTensor:
    base: dict[str, Any] = {"codec": "raw", "dtype": "float32", "shape": [2, 2], "data": b"\0" * 16}
    return EncodedTensor(**{**base, **fields})


def _zstd(data: bytes, **options: Any) -> bytes:
    return zstandard.ZstdCompressor(**options).compress(data)


def _with(encoded_as: str, array: np.ndarray, **changes: Any) -> EncodedTensor:
    """`array` encoded with `encoded_as`, then some fields changed."""
    return dataclasses.replace(encode_tensor_as(array, encoded_as), **changes)


def _flip(data: Any, at: int) -> bytes:
    blob = bytearray(data)
    blob[at] ^= 0xFF
    return bytes(blob)


def _zstd_header_claiming(content_bytes: int) -> bytes:
    """A 17-byte zstd frame whose header claims `content_bytes` (it holds 1000 zeros)."""
    magic, single_segment_8_byte_size = b"\x28\xb5\x2f\xfd", b"\xe0"
    rle_block = (1 | 1 << 1 | 1000 << 3).to_bytes(3, "little") + b"\x00"  # last, RLE, 1000 × 0
    return magic + single_segment_8_byte_size + content_bytes.to_bytes(8, "little") + rle_block


_FMAP = feature_map((1, 4, 6, 8))
_RGB = photo("chelsea", 48, 64)
_BIG_RGB = photo("chelsea", 96, 128)
_GRAY = cv2.cvtColor(_RGB[0], cv2.COLOR_RGB2GRAY)
_JPEG = encode_tensor_as(_RGB, "jpeg80")
_PNG = encode_tensor_as(_RGB, "png")
_PNG_BYTES = bytes(_PNG.data)
_INT8 = encode_tensor_as(_FMAP, "int8")
_SCALE = _INT8.scale
assert _SCALE is not None


def _bad(name: str, tensor: EncodedTensor, error: type[WireError], words: str) -> Any:
    return pytest.param(tensor, error, words, id=name)


BAD_TENSORS = [
    # names and applicability
    _bad("unknown codec", _enc(codec="jpeg101"), UnknownCodec, "unknown tensor codec 'jpeg101'"),
    _bad("codec typo", _enc(codec="Raw"), UnknownCodec, "valid: raw, fp16"),
    _bad("jpeg for float", _enc(codec="jpeg80"), CodecMismatch, "'jpeg80' does not apply"),
    _bad(
        "png for NCHW",
        _with("raw", np.zeros((1, 3, 4, 4), np.uint8), codec="png"),
        CodecMismatch,
        "codecs for it: raw, raw+zstd",
    ),
    _bad("fp16 for int", _enc(codec="fp16", dtype="int32"), CodecMismatch, "int32"),
    _bad("bad dtype", _enc(dtype="complex64"), BadDtype, "tensors.x.dtype: 'complex64'"),
    # sizes
    _bad(
        "size bomb",
        _enc(codec="raw+zstd", shape=[1, 2**40], data=_zstd(b"\0" * 16)),
        TensorTooLarge,
        "decodes to 4398046511104 bytes, over the limit of 67108864",
    ),
    _bad(
        "bomb with garbage",
        _enc(
            codec="int8+zstd",
            shape=[2**30, 2**30],
            data=b"junk",
            scale=np.ones(1, np.float32),
            zero_point=np.zeros(1, np.float32),
        ),
        TensorTooLarge,
        "over the limit",
    ),  # refused before the data is even looked at
    _bad(
        "zstd header claims 10 GB",
        _enc(codec="raw+zstd", dtype="uint8", shape=[1000], data=_zstd_header_claiming(10**10)),
        CorruptPayload,
        "declares 10000000000 bytes, expected 1000",
    ),
    _bad(
        "zstd holds less",
        _enc(codec="raw+zstd", data=_zstd(b"\0" * 12)),
        CorruptPayload,
        "declares 12 bytes, expected 16",
    ),
    _bad(
        "zstd without size",
        _enc(
            codec="raw+zstd",
            dtype="uint8",
            shape=[1000],
            data=_zstd(b"\0" * 1000, write_content_size=False),
        ),
        CorruptPayload,
        "declares no size",
    ),
    _bad(
        "not zstd",
        _enc(codec="raw+zstd", data=b"definitely not zstd"),
        CorruptPayload,
        "not a zstd frame",
    ),
    _bad(
        "zstd flipped byte",
        _with("raw+zstd", _FMAP, data=_flip(encode_tensor_as(_FMAP, "raw+zstd").data, 40)),
        CorruptPayload,
        "corrupt zstd data",
    ),
    _bad(
        "zstd trailing",
        _enc(codec="raw+zstd", data=_zstd(b"\0" * 16) + b"more"),
        CorruptPayload,
        "unused data",
    ),
    _bad("raw length", _enc(data=b"\0" * 12), ShapeMismatch, "needs 16 bytes, got 12"),
    _bad("fp16 length", _enc(codec="fp16", data=b"\0" * 16), ShapeMismatch, "needs 8 bytes"),
    _bad("int8 length", _with("int8", _FMAP, data=b"\0" * 10), ShapeMismatch, "needs 192 bytes"),
    _bad("huge empty shape", _enc(shape=[0, 2**62, 2**62], data=b""), ShapeMismatch, "too large"),
    # Regression (found by the fuzz test): numpy counts the dtype's bytes, so [0, 2**62] of a
    # 2-byte dtype is too large although 2**62 elements alone would not be.
    _bad(
        "huge empty fp16 shape",
        _with("raw", np.zeros(0, np.float16), shape=[0, 2**62]),
        ShapeMismatch,
        "too large",
    ),
    _bad("bool not 0/1", _enc(dtype="bool", shape=[4], data=b"\0\1\2\0"), InvalidValue, "bool"),
    # int8 parameters
    _bad("scale missing", _with("int8", _FMAP, scale=None), BadQuantization, "needs scale"),
    _bad(
        "scale length",
        _with("int8", _FMAP, scale=_SCALE[:3]),
        BadQuantization,
        "scale must be float32 of shape [4] (one per channel), got float32[3]",
    ),
    _bad(
        "scale float64",
        _with("int8", _FMAP, scale=_SCALE.astype(np.float64)),
        BadQuantization,
        "got float64[4]",
    ),
    _bad(
        "scale nan",
        _with("int8", _FMAP, scale=np.full(4, np.nan, np.float32)),
        BadQuantization,
        "scale must be finite and > 0",
    ),
    _bad(
        "scale zero",
        _with("int8", _FMAP, scale=np.zeros(4, np.float32)),
        BadQuantization,
        "finite and > 0",
    ),
    _bad("scale negative", _with("int8", _FMAP, scale=-_SCALE), BadQuantization, "> 0"),
    _bad(
        "zero point 300",
        _with("int8", _FMAP, zero_point=np.full(4, 300, np.float32)),
        BadQuantization,
        "whole numbers in 0..255",
    ),
    _bad(
        "zero point 1.5",
        _with("int8", _FMAP, zero_point=np.full(4, 1.5, np.float32)),
        BadQuantization,
        "whole numbers",
    ),
    _bad("scale on raw", _enc(scale=np.ones(1, np.float32)), BadQuantization, "for a raw tensor"),
    # images
    _bad(
        "jpeg garbage",
        _with("jpeg80", _RGB, data=b"\xff\xd8 not really a jpeg"),
        CorruptPayload,
        "not a readable JPEG",
    ),
    _bad(
        "jpeg truncated",
        _with("jpeg80", _RGB, data=bytes(_JPEG.data)[: len(_JPEG.data) // 2]),
        CorruptPayload,
        "corrupt JPEG",
    ),
    _bad(
        "jpeg bigger than declared",
        _with("jpeg80", _RGB, data=encode_tensor_as(_BIG_RGB, "jpeg80").data),
        ShapeMismatch,
        "header says height×width 96×128, the declared shape is [1, 48, 64, 3]",
    ),
    _bad(
        "jpeg gray declared rgb",
        _with("jpeg80", _RGB, data=encode_tensor_as(_GRAY, "jpeg80").data),
        ShapeMismatch,
        "colorspace Gray",
    ),
    _bad("jpeg empty", _with("jpeg80", _RGB, data=b""), CorruptPayload, "empty jpeg80 data"),
    _bad(
        "png truncated",
        _with("png", _RGB, data=_PNG_BYTES[: len(_PNG_BYTES) // 2]),
        CorruptPayload,
        "corrupt or truncated PNG",
    ),
    _bad(
        "png not png", _with("png", _RGB, data=b"GIF89a" + b"\0" * 40), CorruptPayload, "not a PNG"
    ),
    _bad(
        "png bigger than declared",
        _with("png", _RGB, data=encode_tensor_as(_BIG_RGB, "png").data),
        ShapeMismatch,
        "header says height×width 96×128",
    ),
    _bad(
        "png rgb declared gray",
        _with("png", _GRAY, data=_PNG.data),
        ShapeMismatch,
        "bit depth/color type 8/2",
    ),
]


@pytest.mark.parametrize(("tensor", "error", "words"), BAD_TENSORS)
def test_bad_tensors_get_a_named_error(
    tensor: EncodedTensor, error: type[WireError], words: str
) -> None:
    with pytest.raises(error) as info:
        decode_fully(payload_with(tensor))
    assert type(info.value) is error
    assert words in str(info.value)
    assert "tensors.x" in str(info.value)  # names the tensor
    assert "\n" not in str(info.value)
    reply = ErrorReply.from_wire(error_reply(info.value))
    assert reply.code == error.code.value and reply.reason == str(info.value)


def test_new_error_codes() -> None:
    assert UnknownCodec.code.value == "unknown_codec"
    assert CodecMismatch.code.value == "codec_mismatch"
    assert CorruptPayload.code.value == "corrupt_payload"
    assert BadQuantization.code.value == "bad_quantization"
    assert TensorTooLarge.code.value == "too_large" and issubclass(TensorTooLarge, PayloadTooLarge)


def test_a_request_checks_its_tensors_when_built_locally_too() -> None:
    with pytest.raises(InvalidValue, match="'x' is a ndarray, expected an EncodedTensor"):
        request({"x": _FMAP})  # type: ignore[dict-item]
    with pytest.raises(UnknownCodec, match=r"infer_request\.tensors\.x"):
        request({"x": _enc(codec="jpeg0")})


def test_size_limits() -> None:
    enc = encode_tensor_as(_FMAP, "int8+zstd")
    assert decode_encoded(enc, max_bytes=_FMAP.nbytes).shape == _FMAP.shape
    with pytest.raises(TensorTooLarge, match="decodes to 768 bytes, over the limit of 767"):
        decode_encoded(enc, max_bytes=_FMAP.nbytes - 1, name="feat")
    both = {"a": enc, "b": EncodedTensor.raw(_FMAP)}
    assert len(decode_tensors(both, max_bytes=2 * _FMAP.nbytes)) == 2
    with pytest.raises(TensorTooLarge, match="2 tensors decode to 1536 bytes in all"):
        decode_tensors(both, max_bytes=2 * _FMAP.nbytes - 1)


# -- fuzz ------------------------------------------------------------------------------------------
FUZZ_REQUESTS = [
    request({"x": encode_tensor_as(_FMAP, codec)}).to_wire() for codec in FLOAT_CODECS
] + [
    request({"x": encode_tensor_as(_RGB, "jpeg80"), "g": encode_tensor_as(_GRAY, "png")}).to_wire(),
    request({"x": encode_tensor_as(_RGB, "png"), "g": encode_tensor_as(_GRAY, "jpeg50")}).to_wire(),
]


def decode_fully_or_wire_error(data: bytes) -> None:
    """Any outcome but a non-WireError exception; what decodes has the declared form."""
    try:
        message = decode(data)
        assert isinstance(message, InferRequest)
        arrays = decode_tensors(message.tensors, max_bytes=MAX_BYTES)
    except WireError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    for name, array in arrays.items():
        enc = message.tensors[name]
        assert array.dtype.name == enc.dtype and list(array.shape) == enc.shape
        assert array.flags.c_contiguous


@FUZZ
@given(
    data=st.sampled_from(FUZZ_REQUESTS),
    cuts=st.lists(
        st.tuples(st.integers(min_value=0), st.binary(min_size=1, max_size=4)),
        min_size=1,
        max_size=4,
    ),
    truncate=st.integers(min_value=0),
)
def test_mutated_payloads_raise_only_wire_errors(
    data: bytes, cuts: list[tuple[int, bytes]], truncate: int
) -> None:
    mutated = bytearray(data)
    for position, replacement in cuts:
        at = position % (len(mutated) + 1)
        mutated[at : at + len(replacement)] = replacement
    if truncate % 4 == 0:
        mutated = mutated[: truncate % (len(mutated) + 1)]
    decode_fully_or_wire_error(bytes(mutated))


@FUZZ
@given(
    data=st.sampled_from(FUZZ_REQUESTS),
    field=st.sampled_from(["data", "data", "data", "shape", "codec", "dtype", "scale"]),
    position=st.integers(min_value=0),
    replacement=st.binary(max_size=8),
    number=st.integers(min_value=-2, max_value=2**20),
    name=st.sampled_from(sorted(CODECS)),
)
def test_mutated_tensor_fields_raise_only_wire_errors(
    data: bytes, field: str, position: int, replacement: bytes, number: int, name: str
) -> None:
    """Mutations aimed at the encoded tensor itself, past the msgpack structure."""
    message = InferRequest.from_wire(data)
    enc = message.tensors["x"].to_map()
    if field == "data":
        blob = bytearray(enc["data"])
        at = position % (len(blob) + 1)
        blob[at : at + max(len(replacement), 1)] = replacement
        enc["data"] = bytes(blob)
    elif field == "shape":
        enc["shape"] = [*enc["shape"]]
        enc["shape"][position % len(enc["shape"])] = number
    elif field == "codec":
        enc["codec"] = name
    elif field == "dtype":
        enc["dtype"] = ["uint8", "float16", "float32", "int64", "bool"][position % 5]
    else:
        enc["scale"] = {
            "dtype": "float32",
            "shape": [len(replacement) // 4],
            "bytes": replacement[: len(replacement) // 4 * 4],
        }
    body = {"v": SCHEMA_VERSION, "t": "infer_request", **_plain(message.to_map())}
    body["tensors"]["x"] = _plain(enc)
    decode_fully_or_wire_error(encode_raw(body))
