"""Fuzzing every tensor codec's decode (raw, fp16, int8, int8+zstd, raw+zstd, jpeg<Q>, png) as the
cloud calls it: `decode_encoded(enc, max_bytes=<the cut tensor's size>)`.

Inputs: valid encodings with their data corrupted; declared dtype, shape or codec changed under
the data; int8 quantization parameters of any dtype, shape and value (and parameters given to the
other codecs); size bombs (a zstd frame, JPEG or PNG header or declared shape claiming far more
than the limit). Whatever the input, decode returns an array of the declared dtype and shape or
raises a WireError, within a time bound and a memory bound that does not grow with what a header
claims.
"""

from __future__ import annotations

import dataclasses
import functools
import struct
import zlib
from typing import Any

import numpy as np
import pytest
import zstandard
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.wire import DTYPES, EncodedTensor, TensorTooLarge, WireError, decode_encoded
from common.wire.tensor_codecs import CODECS, applies, encode_tensor_as
from tests.unit.fuzz_support import budget, byte_edits, mutate, run_decoder

# The cloud decodes each tensor into at most its cut tensor's size; 1 MiB keeps bombs obvious.
LIMIT_BYTES = 1024 * 1024
# A decode may hold the data, the decoded tensor and an intermediate of either size (the int8
# codes, the decompressed bytes, OpenCV's BGR image) at once.
MEMORY_FACTOR = 4
ARRAY_CODECS = ["raw", "fp16", "int8", "int8+zstd", "raw+zstd"]
IMAGE_CODECS = ["png", "jpeg1", "jpeg50", "jpeg80", "jpeg100"]


def decode_checked(enc: EncodedTensor, max_bytes: int = LIMIT_BYTES) -> np.ndarray | None:
    """Decode `enc` under the time and memory bounds; the array has the declared form, or a
    WireError was raised (None)."""
    data_bytes = memoryview(enc.data).nbytes
    allowed = MEMORY_FACTOR * (data_bytes + min(_declared_bytes(enc), max_bytes))
    array = run_decoder(
        lambda: decode_encoded(enc, max_bytes=max_bytes), (WireError,), max_bytes=allowed
    )
    if array is not None:
        assert isinstance(array, np.ndarray)
        assert array.dtype == DTYPES[enc.dtype] and list(array.shape) == list(enc.shape)
        assert array.flags.c_contiguous
        assert array.nbytes <= max_bytes
    return array


def _declared_bytes(enc: EncodedTensor) -> int:
    """What the declared dtype and shape add up to (0 where they are nonsense)."""
    try:
        count = 1
        for size in enc.shape:
            count *= max(int(size), 0)
        return count * DTYPES[enc.dtype].itemsize
    except (KeyError, TypeError, ValueError):
        return 0


# -- inputs ----------------------------------------------------------------------------------------
def _float_arrays() -> st.SearchStrategy[np.ndarray]:
    shapes = hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=6)
    elements = st.floats(-1e4, 1e4, allow_nan=False, width=16)
    return hnp.arrays(st.sampled_from(["float16", "float32", "float64"]), shapes, elements=elements)


def _images() -> st.SearchStrategy[np.ndarray]:
    """uint8 images in every layout the image codecs take."""
    layouts = {
        "hw": lambda h, w: (h, w),
        "hw1": lambda h, w: (h, w, 1),
        "hw3": lambda h, w: (h, w, 3),
        "1hw1": lambda h, w: (1, h, w, 1),
        "1hw3": lambda h, w: (1, h, w, 3),
    }
    side = st.integers(1, 20)
    shapes = st.builds(
        lambda h, w, layout: layouts[layout](h, w), side, side, st.sampled_from(sorted(layouts))
    )
    return shapes.flatmap(lambda shape: hnp.arrays(np.uint8, shape))


def _any_arrays() -> st.SearchStrategy[np.ndarray]:
    dtypes = st.sampled_from([np.dtype(d) for d in DTYPES])
    return hnp.arrays(dtypes, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5))


def _encodings() -> st.SearchStrategy[EncodedTensor]:
    """Valid encodings of every codec (the array drawn for the codec's domain)."""
    floats = _float_arrays().flatmap(
        lambda a: st.tuples(
            st.just(a), st.sampled_from([c for c in ARRAY_CODECS if applies(c, a.dtype, a.shape)])
        )
    )
    raw = st.tuples(_any_arrays(), st.sampled_from(["raw", "raw+zstd"]))
    images = st.tuples(_images(), st.sampled_from([*IMAGE_CODECS, "raw+zstd"]))
    pairs = floats | raw | images
    return pairs.map(lambda pair: _plain(encode_tensor_as(*pair)))


def _plain(enc: EncodedTensor) -> EncodedTensor:
    """As the receiver holds it: the data as bytes (a local encoding may keep a memoryview)."""
    return dataclasses.replace(enc, data=bytes(enc.data))


# -- corrupt data ----------------------------------------------------------------------------------
@budget(200)
@given(enc=_encodings(), edits=byte_edits)
def test_corrupt_data(enc: EncodedTensor, edits: list[tuple[int, int, bytes]]) -> None:
    decode_checked(dataclasses.replace(enc, data=mutate(bytes(enc.data), edits)))


@budget(100)
@given(enc=_encodings(), keep=st.integers(min_value=0, max_value=2**16))
def test_truncated_data(enc: EncodedTensor, keep: int) -> None:
    decode_checked(dataclasses.replace(enc, data=enc.data[: keep % (len(enc.data) + 1)]))


# -- the declaration changed under the data --------------------------------------------------------
@budget(200)
@given(
    enc=_encodings(),
    codec=st.none() | st.sampled_from(sorted(CODECS)) | st.text(max_size=8),
    dtype=st.none() | st.sampled_from([*DTYPES, "complex64", "object", "<f4", ""]),
    shape=st.none()
    | st.lists(st.integers(min_value=-2, max_value=40), max_size=5)
    | st.lists(st.sampled_from([0, 1, 3, 2**16, 2**31, 2**62, 2**63]), max_size=17),
)
def test_declaration_changed(
    enc: EncodedTensor, codec: str | None, dtype: str | None, shape: list[int] | None
) -> None:
    changes: dict[str, Any] = {}
    if codec is not None:
        changes["codec"] = codec
    if dtype is not None:
        changes["dtype"] = dtype
    if shape is not None:
        changes["shape"] = shape
    decode_checked(dataclasses.replace(enc, **changes))


# -- quantization parameters -----------------------------------------------------------------------
_params = hnp.arrays(
    st.sampled_from([np.dtype(d) for d in ("float32", "float16", "float64", "int64", "uint8")]),
    hnp.array_shapes(min_dims=0, max_dims=2, min_side=0, max_side=5),
)
_float32_params = hnp.arrays(
    np.float32,
    st.integers(0, 6).map(lambda n: (n,)),
    elements=st.floats(width=32)
    | st.sampled_from([0.0, -1.0, 255.0, 256.0, 0.5, 1e-45, 3.4e38, float("nan"), float("inf")]),
)


@budget(200)
@given(
    source=_float_arrays().filter(lambda a: a.dtype != np.float16),
    codec=st.sampled_from(ARRAY_CODECS),
    scale=st.none() | _params | _float32_params,
    zero_point=st.none() | _params | _float32_params,
)
def test_quantization_parameters(
    source: np.ndarray, codec: str, scale: np.ndarray | None, zero_point: np.ndarray | None
) -> None:
    """Wrong scale/zero_point arrays: any dtype, shape and values, or missing; and parameters
    handed to a codec that takes none."""
    enc = _plain(encode_tensor_as(source, codec))
    decode_checked(dataclasses.replace(enc, scale=scale, zero_point=zero_point))


@budget(80)
@given(
    source=_float_arrays().filter(lambda a: a.ndim in (3, 4) and a.size > 0),
    codec=st.sampled_from(["int8", "int8+zstd"]),
    scale=st.sampled_from([1e-45, 1e-30, 1.0, 1e30, 3.4e38]),
    zero_point=st.sampled_from([0.0, 128.0, 255.0]),
)
def test_extreme_but_legal_quantization(
    source: np.ndarray, codec: str, scale: float, zero_point: float
) -> None:
    """Legal parameters at the ends of float32 decode to the declared form; an overflow to inf
    is the sender's value, not an error (and no warning escapes the decoder)."""
    enc = _plain(encode_tensor_as(source, codec))
    channels = len(enc.scale) if enc.scale is not None else 1
    legal = dataclasses.replace(
        enc,
        scale=np.full(channels, scale, np.float32),
        zero_point=np.full(channels, zero_point, np.float32),
    )
    assert decode_checked(legal) is not None


# -- size bombs ------------------------------------------------------------------------------------
BOMB_BYTES = 256 * 1024 * 1024


@functools.cache
def _zstd_bomb(with_size: bool) -> bytes:
    """A zstd frame of 256 MiB of zeros, a few KiB on the wire."""
    compressor = zstandard.ZstdCompressor(level=1, write_content_size=with_size)
    chunk = bytes(1024 * 1024)
    out = compressor.compressobj(size=BOMB_BYTES if with_size else -1)
    parts = [out.compress(chunk) for _ in range(BOMB_BYTES // len(chunk))]
    return b"".join([*parts, out.flush()])


@pytest.mark.parametrize("codec", ["raw+zstd", "int8+zstd"])
@pytest.mark.parametrize("with_size", [True, False], ids=["sized-frame", "unsized-frame"])
@pytest.mark.parametrize("declared", ["small", "huge"])
def test_zstd_bomb_is_refused_unopened(codec: str, with_size: bool, declared: str) -> None:
    """A 256 MiB frame declared as a 64-element tensor, or a tensor declared 256 MiB with a
    1 MiB limit: refused without decompressing (memory stays near the frame's size)."""
    bomb = _zstd_bomb(with_size)
    shape = [1, 1, 8, 8] if declared == "small" else [1, 1, 16384, 16384]
    dtype = "uint8" if codec == "raw+zstd" else "float32"
    scale = None if codec == "raw+zstd" else np.ones(1, np.float32)
    zero_point = None if codec == "raw+zstd" else np.zeros(1, np.float32)
    enc = EncodedTensor(
        codec=codec, dtype=dtype, shape=shape, data=bomb, scale=scale, zero_point=zero_point
    )
    expected = TensorTooLarge if declared == "huge" else WireError
    with pytest.raises(expected):
        run_decoder(lambda: decode_encoded(enc, max_bytes=LIMIT_BYTES), (), max_bytes=LIMIT_BYTES)


def _png_header(width: int, height: int, color: int = 2) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, color, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr
    crc = struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    idat = zlib.compress(bytes(64))
    idat_chunk = struct.pack(">I", len(idat)) + b"IDAT" + idat
    idat_crc = struct.pack(">I", zlib.crc32(b"IDAT" + idat))
    return b"\x89PNG\r\n\x1a\n" + chunk + crc + idat_chunk + idat_crc + b"\0\0\0\0IEND\xaeB`\x82"


def _jpeg_claiming(height: int, width: int) -> bytes:
    """A real 8×8 JPEG whose frame header (SOF0) is rewritten to claim height × width."""
    small = bytearray(encode_tensor_as(np.zeros((8, 8, 3), np.uint8), "jpeg80").data)
    sof = small.index(b"\xff\xc0")
    small[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(small)


@pytest.mark.parametrize(
    ("codec", "data", "shape"),
    [
        ("png", _png_header(65535, 65535), [65535, 65535, 3]),
        ("png", _png_header(65535, 65535), [8, 8, 3]),
        ("png", _png_header(8, 8), [8, 8, 3]),
        ("jpeg80", _jpeg_claiming(65535, 65535), [65535, 65535, 3]),
        ("jpeg80", _jpeg_claiming(65535, 65535), [8, 8, 3]),
        ("jpeg80", _jpeg_claiming(16, 16), [16, 16, 3]),
    ],
    ids=[
        "png-huge-declared",
        "png-header-disagrees",
        "png-truncated-pixels",
        "jpeg-huge-declared",
        "jpeg-header-disagrees",
        "jpeg-missing-pixels",
    ],
)
def test_image_headers_claiming_more_than_they_hold(
    codec: str, data: bytes, shape: list[int]
) -> None:
    """An image header of 65535² pixels is refused by the declared size or by the declared shape
    before any pixel is decoded; one that agrees with a small declared shape decodes within it
    or is corrupt."""
    enc = EncodedTensor(codec=codec, dtype="uint8", shape=shape, data=data)
    decode_checked(enc)
    if shape[0] == 65535:
        with pytest.raises(TensorTooLarge):
            decode_encoded(enc, max_bytes=LIMIT_BYTES)


def test_png_chunk_claiming_gigabytes_is_refused_before_opencv() -> None:
    """Regression: a 10×4 PNG whose IDAT length field says 3.6 GB made OpenCV's reader reserve
    3.5 GB and spend 3 s on 116 bytes; the chunk walk refuses it first."""
    png = bytearray(encode_tensor_as(np.zeros((10, 4), np.uint8), "png").data)
    at = png.index(b"IDAT") - 4
    png[at : at + 4] = struct.pack(">I", 3_690_987_581)
    enc = EncodedTensor(codec="png", dtype="uint8", shape=[10, 4], data=bytes(png))
    with pytest.raises(WireError, match="claims 3690987581 bytes"):
        run_decoder(lambda: decode_encoded(enc, max_bytes=LIMIT_BYTES), (), max_bytes=64 * 1024)
