"""Per-tensor codecs for the tensors that cross the network, decoded strictly.

Why: at most cuts the tensor a robot sends is the biggest part of a frame's cost on a thin
uplink, and the right trade between robot CPU and bytes depends on the tensor: a float feature map
halves with `fp16` and quarters with `int8` (an error of at most half a quantization step), the
zeros a ReLU leaves behind shrink further with zstd, and a camera image (cut 0) is a job for JPEG
or PNG. So each tensor of an `InferRequest` carries the name of its codec, and the receiver needs
no configuration to read it.

What: the codec names are a contract between peers (exact spelling): `raw`, `fp16`, `int8`,
`int8+zstd`, `raw+zstd`, `jpeg<Q>` for Q in 1..100 (e.g. `jpeg80`), `png`, `h264`.

- `raw`: the tensor's bytes (little-endian, C order), any allowed dtype.
- `fp16`: a float32/float64 tensor sent as float16, decoded back to its declared dtype.
- `int8`: affine quantization of a float tensor to uint8 (0..255), x ≈ (q - zero_point) * scale,
  per channel where the tensor has channels (axis 1 of an ONNX N×C×H×W or N×C×L tensor), per
  tensor otherwise. `scale` and `zero_point` travel with the data (float32, one per channel); the
  range always includes 0, so zero_point is a whole number in 0..255 and zeros decode exactly.
- `int8+zstd`, `raw+zstd`: the same bytes, then a zstandard frame.
- `jpeg<Q>` (libjpeg-turbo via simplejpeg, quality Q) and `png` (OpenCV): uint8 images only,
  channels last, shapes (H,W), (H,W,1), (H,W,3), (1,H,W,1), (1,H,W,3).
- `h264` (PyAV's libx264, `common.wire.video_codec`): the same images with even sides. A video
  codec: a P-frame is decoded by its stream's decoder (the request's `video` field says where
  the frame stands in its stream); alone, as here, a tensor is a keyframe coded on its own.

`EncodedTensor` is the wire record: codec, the decoded tensor's dtype and shape, the encoded data
and the quantization parameters. `encode_tensor_as(array, codec)` makes one; `decode_encoded(enc,
max_bytes=...)` gives the array back (C-contiguous, of the declared dtype and shape; a `raw` tensor
is a read-only view of the received bytes, the others are fresh arrays).

Strict decode, in two stages, both raising only `WireError` subclasses:
- `check_encoded` (cheap, no data decoded; run whenever an `InferRequest` is built or decoded):
  known codec (`UnknownCodec`), allowed dtype (`BadDtype`), sane shape (`ShapeMismatch`), codec
  applies to dtype and shape (`CodecMismatch`), data length for the fixed-size codecs raw, fp16 and
  int8 (`ShapeMismatch`), quantization parameters present only for int8, one finite positive
  scale and one whole zero point in 0..255 per channel (`BadQuantization`).
- `decode_encoded`: a tensor whose declared size exceeds the receiver's `max_bytes` is refused
  before anything is decompressed or decoded (`TensorTooLarge`); a zstd frame must declare exactly
  the expected size and is decompressed with that bound, so a bomb cannot expand; corrupt data
  is `CorruptPayload`; a JPEG or PNG header whose size or channels disagree with the declared shape
  is `ShapeMismatch`, read before the pixels are decoded.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import math
import struct
import threading
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import zstandard

from common.wire.codec import DTYPES, MAX_TENSOR_NDIM, Buffer, Struct, key_path
from common.wire.errors import (
    BadDtype,
    BadQuantization,
    CodecMismatch,
    CorruptPayload,
    InvalidValue,
    ShapeMismatch,
    TensorTooLarge,
    UnknownCodec,
    WrongFieldType,
)
from common.wire.video_codec import (
    CODEC_H264,
    decode_keyframe,
    encode_keyframe,
    video_shape_ok,
)

CODEC_RAW = "raw"
CODEC_FP16 = "fp16"
CODEC_INT8 = "int8"
CODEC_INT8_ZSTD = "int8+zstd"
CODEC_RAW_ZSTD = "raw+zstd"
CODEC_PNG = "png"
JPEG_PREFIX = "jpeg"
JPEG_QUALITY_MIN = 1
JPEG_QUALITY_MAX = 100
VALID_CODECS_TEXT = (
    f"{CODEC_RAW}, {CODEC_FP16}, {CODEC_INT8}, {CODEC_INT8_ZSTD}, {CODEC_RAW_ZSTD}, "
    f"{JPEG_PREFIX}<Q> (Q = {JPEG_QUALITY_MIN}..{JPEG_QUALITY_MAX}), {CODEC_PNG}, {CODEC_H264}"
)

# zstd level 1: on a ReLU feature map and its int8 codes, level 3 (zstd's default) saves under 2%
# more bytes for 1.7-2x the robot CPU (measured with benchmarks/codec_bench.py).
ZSTD_LEVEL = 1
# PNG's zlib level 1, the fastest: on a photograph levels 3 and 6 save 2% and 4% of the bytes for
# 1.4x and 3x the encode time.
PNG_COMPRESSION_LEVEL = 1
# Chroma at half resolution in both directions, as cameras do: on a photograph at quality 80,
# a fifth fewer bytes than 4:4:4 for 2 dB of PSNR.
JPEG_SUBSAMPLING = "420"
# JPEG cannot hold a side longer than 65535 pixels; PNG is held to the same.
MAX_IMAGE_SIDE_PX = 65_535
QUANT_LEVELS = 255  # uint8 codes 0..255
FLOAT16_MAX = float(np.finfo(np.float16).max)
_FLOAT16_EXPONENT = 0x7C00  # exponent bits of an IEEE half
_FLOAT32_TINY = float(np.finfo(np.float32).tiny)  # smallest normal float32: the smallest scale
# numpy cannot hold an array of this many bytes, counting every dimension as at least 1 (it
# refuses [0, 2**62] for a 2-byte dtype although the array holds nothing).
_INTP_LIMIT = 2**63


_FP16_SOURCES = frozenset({"float32", "float64"})
_INT8_SOURCES = frozenset({"float16", "float32", "float64"})
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IHDR = struct.Struct(">I4sIIBB")  # chunk length, b"IHDR", width, height, depth, color type
_PNG_CHUNK_HEAD = struct.Struct(">I4s")  # chunk length, chunk type
_PNG_CHUNK_OVERHEAD = 12  # length, type and CRC around a chunk's data
_PNG_COLOR_TYPES = {1: 0, 3: 2}  # channels -> PNG color type (0 = gray, 2 = RGB)
_JPEG_COLORSPACES = {1: ("Gray",), 3: ("YCbCr", "RGB")}  # channels -> header colorspaces


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class EncodedTensor(Struct):
    """One tensor as it crosses the network: `codec` names how `data` encodes the tensor of
    `dtype` and `shape` (the decoded tensor's); `scale` and `zero_point` (float32, one per
    channel) are there for int8 only.

    `data` is bytes when decoded from the wire; a locally encoded tensor may hold a memoryview
    of the array it came from (raw) or of the codec's output, which msgpack packs without a copy,
    so the source array must not change until the message is encoded.
    """

    codec: str
    dtype: str
    shape: list[int]
    data: Buffer
    scale: np.ndarray | None = None
    zero_point: np.ndarray | None = None

    @property
    def nbytes(self) -> int:
        """Bytes on the wire for the data and the quantization parameters."""
        params = sum(p.nbytes for p in (self.scale, self.zero_point) if p is not None)
        return memoryview(self.data).nbytes + params

    @classmethod
    def raw(cls, array: np.ndarray) -> EncodedTensor:
        """The array as `raw` (its bytes as they are, without a copy where it is contiguous)."""
        return encode_tensor_as(array, CODEC_RAW)


# -- the codecs ------------------------------------------------------------------------------------
class Codec(abc.ABC):
    """A codec of the contract: `encode` an array, `decode` an `EncodedTensor` back."""

    name: str
    lossy: bool
    video: bool = False
    """A video codec: its frames depend on the frames before them (`h264`)."""

    @abc.abstractmethod
    def applies_to(self, dtype: np.dtype[Any], shape: Sequence[int]) -> bool:
        """Whether this codec can carry a tensor of this dtype and shape."""

    def encode(self, array: np.ndarray) -> EncodedTensor:
        """The encoded tensor; WireError if the array is not one this codec carries."""
        array = _as_array(array)
        if not self.applies_to(array.dtype, array.shape):
            raise CodecMismatch(_mismatch("tensor", self.name, array.dtype, list(array.shape)))
        return self._encode(array)

    def decode(self, enc: EncodedTensor, *, max_bytes: int, where: str = "tensor") -> np.ndarray:
        """The tensor of `enc` (which must name this codec), checked; `max_bytes` bounds the
        decoded size, refused before anything is decompressed or decoded."""
        if enc.codec != self.name:
            raise CodecMismatch(f"{where}: codec {enc.codec!r} given to the {self.name} decoder")
        dtype, count = _check(enc, self, where)
        _check_size(enc, count * dtype.itemsize, max_bytes, where)
        return self._decode(enc, dtype, count, where)

    def check(self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str) -> None:
        """Checks that need no decoding (data length, parameters); `count` = elements."""
        if enc.scale is not None or enc.zero_point is not None:
            raise BadQuantization(f"{where}: scale/zero_point given for a {self.name} tensor")

    @abc.abstractmethod
    def _encode(self, array: np.ndarray) -> EncodedTensor: ...

    @abc.abstractmethod
    def _decode(
        self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str
    ) -> np.ndarray: ...


class _ArrayCodec(Codec):
    """raw, fp16 and int8: the tensor becomes a flat array of a fixed item size, then optionally
    a zstd frame. Subclasses say how an array becomes that flat array and back."""

    def __init__(self, name: str, *, lossy: bool, zstd: bool) -> None:
        self.name = name
        self.lossy = lossy
        self.zstd = zstd

    @abc.abstractmethod
    def _wire_itemsize(self, dtype: np.dtype[Any]) -> int: ...

    @abc.abstractmethod
    def _to_wire(
        self, array: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(flat C-contiguous array to send, scale, zero_point)."""

    @abc.abstractmethod
    def _from_wire(
        self, data: Buffer, enc: EncodedTensor, dtype: np.dtype[Any], where: str
    ) -> np.ndarray: ...

    def check(self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str) -> None:
        super().check(enc, dtype, count, where)
        if not self.zstd:
            _check_length(enc, count * self._wire_itemsize(dtype), where)

    def _encode(self, array: np.ndarray) -> EncodedTensor:
        wire, scale, zero_point = self._to_wire(array)
        # A flat uint8 view packs as one msgpack bin without a tobytes() copy.
        data: Buffer = wire.view(np.uint8).data if wire.nbytes else b""
        if self.zstd:
            data = _zstd().compress(data)
        return EncodedTensor(
            codec=self.name,
            dtype=_dtype_name(array.dtype),
            shape=list(array.shape),
            data=data,
            scale=scale,
            zero_point=zero_point,
        )

    def _decode(
        self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str
    ) -> np.ndarray:
        data = enc.data
        if self.zstd:
            data = _decompress(data, count * self._wire_itemsize(dtype), where)
        return self._from_wire(data, enc, dtype, where)


class RawCodec(_ArrayCodec):
    """`raw` / `raw+zstd`: the bytes as they are."""

    def applies_to(self, dtype: np.dtype[Any], shape: Sequence[int]) -> bool:
        return _dtype_name(dtype) in DTYPES

    def _wire_itemsize(self, dtype: np.dtype[Any]) -> int:
        return dtype.itemsize

    def _to_wire(
        self, array: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        # Little-endian and C-contiguous, copying only if the array is not already.
        return np.ascontiguousarray(array, DTYPES[_dtype_name(array.dtype)]).reshape(-1), None, None

    def _from_wire(
        self, data: Buffer, enc: EncodedTensor, dtype: np.dtype[Any], where: str
    ) -> np.ndarray:
        array = np.frombuffer(data, dtype=dtype).reshape(enc.shape)
        if dtype.kind == "b" and array.size and array.view(np.uint8).max() > 1:
            raise InvalidValue(f"{where}: bool tensor holds bytes other than 0 and 1")
        return array


class Fp16Codec(_ArrayCodec):
    """`fp16`: float32/float64 sent as float16, decoded back to the declared dtype."""

    def applies_to(self, dtype: np.dtype[Any], shape: Sequence[int]) -> bool:
        return _dtype_name(dtype) in _FP16_SOURCES

    def _wire_itemsize(self, dtype: np.dtype[Any]) -> int:
        return 2

    def _to_wire(
        self, array: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        with np.errstate(over="ignore"):  # overflow is checked below, with a better message
            half = np.ascontiguousarray(array, dtype="<f2").reshape(-1)
        # All exponent bits set = inf or NaN (8x faster than np.isfinite on float16); the rare
        # tensor with some is checked against its source, whose own inf and NaN may pass.
        special = (half.view(np.uint16) & _FLOAT16_EXPONENT) == _FLOAT16_EXPONENT
        if special.any() and not np.array_equal(special, ~np.isfinite(array).reshape(-1)):
            raise InvalidValue(
                f"tensor: values beyond float16's ±{FLOAT16_MAX:g} cannot be sent as fp16; "
                "use raw or int8"
            )
        return half, None, None

    def _from_wire(
        self, data: Buffer, enc: EncodedTensor, dtype: np.dtype[Any], where: str
    ) -> np.ndarray:
        half = np.frombuffer(data, dtype="<f2").reshape(enc.shape)
        return half.astype(dtype)


class Int8Codec(_ArrayCodec):
    """`int8` / `int8+zstd`: per-channel affine quantization to uint8.

    The quantized range is [min(lo, 0), max(hi, 0)] of each channel, as ONNX QuantizeLinear does:
    zero_point is then a whole code, so zeros (a ReLU's output is mostly zeros) decode exactly, and
    every value is within scale/2 of its decoded value.
    """

    def applies_to(self, dtype: np.dtype[Any], shape: Sequence[int]) -> bool:
        return _dtype_name(dtype) in _INT8_SOURCES

    def _wire_itemsize(self, dtype: np.dtype[Any]) -> int:
        return 1

    def check(self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str) -> None:
        if not self.zstd:
            _check_length(enc, count, where)
        _, channels, _ = _channel_groups(enc.shape)
        for field in ("scale", "zero_point"):
            param = getattr(enc, field)
            if param is None:
                raise BadQuantization(f"{where}: {self.name} needs {field}, none given")
            if param.dtype != np.float32 or param.shape != (channels,):
                raise BadQuantization(
                    f"{where}: {field} must be float32 of shape [{channels}] (one per channel), "
                    f"got {param.dtype.name}{list(param.shape)}"
                )
        scale, zero_point = enc.scale, enc.zero_point
        assert scale is not None and zero_point is not None  # checked just above
        if not (np.isfinite(scale) & (scale > 0)).all():
            raise BadQuantization(f"{where}: scale must be finite and > 0")
        in_range = (zero_point >= 0) & (zero_point <= QUANT_LEVELS)
        if not (in_range & (zero_point == np.rint(zero_point))).all():
            raise BadQuantization(f"{where}: zero_point must hold whole numbers in 0..255")

    def _to_wire(
        self, array: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        groups = _channel_groups(array.shape)
        channels = groups[1]
        if array.size == 0:
            scale = np.ones(channels, np.float32)
            return np.empty(0, np.uint8), scale, np.zeros(channels, np.float32)
        x = array.reshape(groups)
        # float64 for the per-channel parameters; the data pass in float32 unless it is float64.
        lo = np.minimum(x.min(axis=(0, 2)), 0).astype(np.float64)
        hi = np.maximum(x.max(axis=(0, 2)), 0).astype(np.float64)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):  # min/max propagate NaN and inf
            raise InvalidValue("tensor: int8 cannot carry NaN or infinite values; use raw or fp16")
        span = hi - lo
        with np.errstate(over="ignore"):
            scale = np.maximum(span / QUANT_LEVELS, _FLOAT32_TINY).astype(np.float32)
        # Rounding to float32 may leave the step a hair short of span/255, which would push the
        # top of the range past code 255: round those up by one ulp.
        short = scale.astype(np.float64) * QUANT_LEVELS < span
        scale[short] = np.nextafter(scale[short], np.float32(np.inf))
        if not np.isfinite(scale).all():
            raise InvalidValue("tensor: values span more than a float32 int8 scale can express")
        zero_point = np.rint(-lo / scale).clip(0, QUANT_LEVELS).astype(np.float32)
        work = np.float64 if array.dtype == np.float64 else np.float32
        codes = np.empty(x.shape, work)
        np.divide(x, scale.astype(work)[None, :, None], out=codes)
        codes += zero_point.astype(work)[None, :, None]
        np.rint(codes, out=codes)
        np.clip(codes, 0, QUANT_LEVELS, out=codes)
        return codes.astype(np.uint8).reshape(-1), scale, zero_point

    def _from_wire(
        self, data: Buffer, enc: EncodedTensor, dtype: np.dtype[Any], where: str
    ) -> np.ndarray:
        assert enc.scale is not None and enc.zero_point is not None  # checked by check()
        groups = _channel_groups(enc.shape)
        codes = np.frombuffer(data, dtype=np.uint8).reshape(groups)
        work = np.float64 if dtype == np.float64 else np.float32
        out = np.subtract(codes, enc.zero_point.astype(work)[None, :, None], dtype=work)
        # A hostile scale may overflow to inf: that is the sender's value, not a decode error.
        with np.errstate(over="ignore"):
            out *= enc.scale.astype(work)[None, :, None]
        if dtype == np.float16:
            # The outer codes of a range that reaches float16's limit decode a hair past it (the
            # zero point is rounded): saturate rather than turn them into inf. The values came
            # from float16, so this only brings a decoded value closer to its source.
            np.clip(out, -FLOAT16_MAX, FLOAT16_MAX, out=out)
        return out.astype(dtype, copy=False).reshape(enc.shape)


class _ImageCodec(Codec):
    """JPEG and PNG: uint8 images, channels last (1 or 3), a leading batch of 1 allowed."""

    def applies_to(self, dtype: np.dtype[Any], shape: Sequence[int]) -> bool:
        return _dtype_name(dtype) == "uint8" and _image_hwc(shape) is not None

    def check(self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str) -> None:
        super().check(enc, dtype, count, where)
        if memoryview(enc.data).nbytes == 0:
            raise CorruptPayload(f"{where}: empty {self.name} data")

    def _hwc(self, shape: Sequence[int]) -> tuple[int, int, int]:
        hwc = _image_hwc(shape)
        assert hwc is not None  # applies_to was checked before
        return hwc

    def _encoded(self, array: np.ndarray, data: Buffer) -> EncodedTensor:
        return EncodedTensor(codec=self.name, dtype="uint8", shape=list(array.shape), data=data)

    def _disagrees(self, where: str, what: str, got: object, enc: EncodedTensor) -> ShapeMismatch:
        return ShapeMismatch(
            f"{where}: {self.name} header says {what} {got}, the declared shape is {enc.shape}"
        )


class JpegCodec(_ImageCodec):
    """`jpeg<Q>`: libjpeg-turbo through simplejpeg, RGB with 4:2:0 chroma or grayscale."""

    lossy = True

    def __init__(self, quality: int) -> None:
        self.quality = quality
        self.name = f"{JPEG_PREFIX}{quality}"

    def _encode(self, array: np.ndarray) -> EncodedTensor:
        import simplejpeg  # imported on first use: most processes never touch images

        h, w, c = self._hwc(array.shape)
        image = np.ascontiguousarray(array).reshape(h, w, c)
        if c == 1:
            data = simplejpeg.encode_jpeg(image, quality=self.quality, colorspace="GRAY")
        else:
            data = simplejpeg.encode_jpeg(
                image, quality=self.quality, colorspace="RGB", colorsubsampling=JPEG_SUBSAMPLING
            )
        return self._encoded(array, data)

    def _decode(
        self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str
    ) -> np.ndarray:
        import simplejpeg

        h, w, c = self._hwc(enc.shape)
        try:
            got_h, got_w, colorspace, _ = simplejpeg.decode_jpeg_header(enc.data)
        except Exception as exc:  # ValueError from libjpeg-turbo, whatever the bytes
            raise CorruptPayload(f"{where}: not a readable JPEG ({_one_line(exc)})") from None
        if (got_h, got_w) != (h, w):
            raise self._disagrees(where, "height×width", f"{got_h}×{got_w}", enc)
        if colorspace not in _JPEG_COLORSPACES[c]:
            raise self._disagrees(where, "colorspace", colorspace, enc)
        # The header matches the declared shape, so the output buffer is the declared size.
        out = np.empty((h, w, c), np.uint8)
        try:
            simplejpeg.decode_jpeg(
                enc.data, colorspace="GRAY" if c == 1 else "RGB", buffer=out, strict=True
            )
        except Exception as exc:
            raise CorruptPayload(f"{where}: corrupt JPEG ({_one_line(exc)})") from None
        return out.reshape(enc.shape)


class PngCodec(_ImageCodec):
    """`png`: lossless, OpenCV's libpng, 8-bit gray or RGB."""

    name = CODEC_PNG
    lossy = False

    def _encode(self, array: np.ndarray) -> EncodedTensor:
        import cv2  # imported on first use: most processes never touch images

        h, w, c = self._hwc(array.shape)
        rgb = np.ascontiguousarray(array).reshape(h, w, c)
        # OpenCV writes a 2-D array as gray, a 3-channel one as BGR.
        image = rgb.reshape(h, w) if c == 1 else cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        ok, png = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION_LEVEL])
        if not ok:
            raise InvalidValue(f"tensor: OpenCV could not encode a {h}×{w}×{c} PNG")
        return self._encoded(array, png.reshape(-1).data)

    def _decode(
        self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str
    ) -> np.ndarray:
        import cv2

        h, w, c = self._hwc(enc.shape)
        head = bytes(memoryview(enc.data)[: len(_PNG_SIGNATURE) + _PNG_IHDR.size])
        if len(head) < len(_PNG_SIGNATURE) + _PNG_IHDR.size or not head.startswith(_PNG_SIGNATURE):
            raise CorruptPayload(f"{where}: not a PNG (no PNG signature and IHDR)")
        length, tag, got_w, got_h, depth, color = _PNG_IHDR.unpack_from(head, len(_PNG_SIGNATURE))
        if (length, tag) != (13, b"IHDR"):
            raise CorruptPayload(f"{where}: not a PNG (IHDR is not the first chunk)")
        if (got_h, got_w) != (h, w):
            raise self._disagrees(where, "height×width", f"{got_h}×{got_w}", enc)
        if depth != 8 or color != _PNG_COLOR_TYPES[c]:
            raise self._disagrees(where, "bit depth/color type", f"{depth}/{color}", enc)
        _check_png_chunks(memoryview(enc.data), where)
        try:
            image = cv2.imdecode(np.frombuffer(enc.data, np.uint8), cv2.IMREAD_UNCHANGED)
        except Exception as exc:  # cv2.error
            raise CorruptPayload(f"{where}: corrupt PNG ({_one_line(exc)})") from None
        if image is None:
            raise CorruptPayload(f"{where}: corrupt or truncated PNG")
        if image.dtype != np.uint8 or image.size != h * w * c:  # e.g. a tRNS chunk added alpha
            raise CorruptPayload(f"{where}: PNG decodes to {image.dtype.name}{list(image.shape)}")
        if c == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        return np.ascontiguousarray(image).reshape(enc.shape)


class H264Codec(_ImageCodec):
    """`h264`: a uint8 image with even sides as H.264 (`common.wire.video_codec`). Alone, a
    tensor is a keyframe coded and decoded on its own; a stream's P-frames are decoded by the
    stream's decoder (`cloudd.video_streams`), which the request's `video` field names."""

    name = CODEC_H264
    lossy = True
    video = True

    def applies_to(self, dtype: np.dtype[Any], shape: Sequence[int]) -> bool:
        hwc = _image_hwc(shape) if _dtype_name(dtype) == "uint8" else None
        return hwc is not None and video_shape_ok(*hwc)

    def _encode(self, array: np.ndarray) -> EncodedTensor:
        return self._encoded(array, encode_keyframe(array, self._hwc(array.shape)))

    def _decode(
        self, enc: EncodedTensor, dtype: np.dtype[Any], count: int, where: str
    ) -> np.ndarray:
        image = decode_keyframe(bytes(enc.data), self._hwc(enc.shape), where)
        return image.reshape(enc.shape)


# Every codec of the contract, by name, in the contract's order.
CODECS: dict[str, Codec] = {
    codec.name: codec
    for codec in (
        RawCodec(CODEC_RAW, lossy=False, zstd=False),
        Fp16Codec(CODEC_FP16, lossy=True, zstd=False),
        Int8Codec(CODEC_INT8, lossy=True, zstd=False),
        Int8Codec(CODEC_INT8_ZSTD, lossy=True, zstd=True),
        RawCodec(CODEC_RAW_ZSTD, lossy=False, zstd=True),
        *(JpegCodec(q) for q in range(JPEG_QUALITY_MIN, JPEG_QUALITY_MAX + 1)),
        PngCodec(),
        H264Codec(),
    )
}
# One codec per family (the JPEG qualities are one family), in the contract's order.
_FAMILIES: dict[str, Codec] = {
    f"{JPEG_PREFIX}<Q>" if isinstance(codec, JpegCodec) else name: codec
    for name, codec in CODECS.items()
}


# -- public functions ------------------------------------------------------------------------------
def parse_codec(name: str) -> Codec:
    """The codec of this name; UnknownCodec (listing the valid names) for any other."""
    codec = CODECS.get(name) if isinstance(name, str) else None
    if codec is None:
        raise UnknownCodec(_unknown(name))
    return codec


def is_video(name: str) -> bool:
    """Whether codec `name` is a video codec (its P-frames need their stream's decoder); False
    for an unknown name."""
    codec = CODECS.get(name) if isinstance(name, str) else None
    return codec is not None and codec.video


def applies(name: str, dtype: str | np.dtype[Any], shape: Sequence[int]) -> bool:
    """Whether codec `name` can carry a tensor of this dtype and shape (UnknownCodec for an
    unknown name: a typo in a configuration must not read as "does not apply")."""
    return parse_codec(name).applies_to(np.dtype(dtype), shape)


def codec_names_for(dtype: str | np.dtype[Any], shape: Sequence[int]) -> list[str]:
    """The codec families that can carry this tensor, JPEG as `jpeg<Q>`, in the contract's
    order (e.g. float32 N×C×H×W: raw, fp16, int8, int8+zstd, raw+zstd)."""
    np_dtype = np.dtype(dtype)
    return [name for name, codec in _FAMILIES.items() if codec.applies_to(np_dtype, shape)]


def encode_tensor_as(array: np.ndarray, codec: str) -> EncodedTensor:
    """`array` encoded with codec `codec`; a WireError subclass if the name is unknown
    (UnknownCodec), the codec does not apply (CodecMismatch) or the values do not fit it
    (InvalidValue: fp16 overflow, NaN for int8)."""
    return parse_codec(codec).encode(array)


def decode_encoded(enc: EncodedTensor, *, max_bytes: int, name: str = "tensor") -> np.ndarray:
    """The array of `enc`: C-contiguous, of the declared dtype and shape. `max_bytes` bounds the
    decoded size (refused before decoding); `name` names the tensor in error messages. Raises only
    WireError subclasses."""
    codec = CODECS.get(enc.codec)
    if codec is None:
        raise UnknownCodec(f"{name}: {_unknown(enc.codec)}")
    return codec.decode(enc, max_bytes=max_bytes, where=name)


def decode_tensors(
    tensors: Mapping[str, EncodedTensor], *, max_bytes: int, where: str = "tensors"
) -> dict[str, np.ndarray]:
    """Every tensor of a request, decoded; `max_bytes` bounds their decoded sizes together, checked
    for all of them before any is decoded."""
    total = 0
    for name, enc in tensors.items():
        dtype, count = check_encoded(enc, key_path(where, name))
        _check_size(enc, count * dtype.itemsize, max_bytes, key_path(where, name))
        total += count * dtype.itemsize
    if total > max_bytes:
        raise TensorTooLarge(
            f"{where}: {len(tensors)} tensors decode to {total} bytes in all, over the limit of "
            f"{max_bytes} bytes"
        )
    return {
        name: decode_encoded(enc, max_bytes=max_bytes, name=key_path(where, name))
        for name, enc in tensors.items()
    }


def check_encoded(enc: EncodedTensor, where: str = "tensor") -> tuple[np.dtype[Any], int]:
    """The checks that need no decoding (see the module docstring), with `where` naming the tensor
    in errors; returns the declared dtype and element count."""
    codec = CODECS.get(enc.codec) if isinstance(enc.codec, str) else None
    if codec is None:
        raise UnknownCodec(f"{where}: {_unknown(enc.codec)}")
    return _check(enc, codec, where)


# -- helpers ---------------------------------------------------------------------------------------
def _check(enc: EncodedTensor, codec: Codec, where: str) -> tuple[np.dtype[Any], int]:
    dtype = DTYPES.get(enc.dtype) if isinstance(enc.dtype, str) else None
    if dtype is None:
        raise BadDtype(f"{where}.dtype: {enc.dtype!r} is not allowed; allowed: {', '.join(DTYPES)}")
    count = _element_count(enc.shape, where, dtype.itemsize)
    if not codec.applies_to(dtype, enc.shape):
        raise CodecMismatch(_mismatch(where, codec.name, dtype, enc.shape))
    codec.check(enc, dtype, count, where)
    return dtype, count


def _element_count(shape: Sequence[int], where: str, itemsize: int = 1) -> int:
    """Elements of a declared shape, refusing shapes numpy could not hold in `itemsize`-byte
    elements."""
    if len(shape) > MAX_TENSOR_NDIM:
        raise ShapeMismatch(f"{where}.shape: expected at most {MAX_TENSOR_NDIM} sizes")
    count = 1
    nonzero = 1  # numpy refuses shapes like [0, 2**62, 2**62] although they hold nothing
    for size in shape:
        if type(size) is not int or size < 0:
            raise ShapeMismatch(f"{where}.shape: sizes must be non-negative integers, got {shape}")
        count *= size
        nonzero *= max(size, 1)
    if nonzero * itemsize >= _INTP_LIMIT:
        raise ShapeMismatch(f"{where}.shape: {shape} is too large for an array")
    return count


def _check_size(enc: EncodedTensor, decoded_bytes: int, max_bytes: int, where: str) -> None:
    if decoded_bytes > max_bytes:
        raise TensorTooLarge(
            f"{where}: {enc.codec} tensor {enc.dtype}{enc.shape} decodes to {decoded_bytes} "
            f"bytes, over the limit of {max_bytes} bytes"
        )


def _check_length(enc: EncodedTensor, expected: int, where: str) -> None:
    got = memoryview(enc.data).nbytes
    if got != expected:
        raise ShapeMismatch(
            f"{where}: shape {enc.shape} of {enc.dtype} as {enc.codec} needs {expected} bytes, "
            f"got {got}"
        )


def _check_png_chunks(data: memoryview, where: str) -> None:
    """Every chunk up to IEND lies within `data`. OpenCV's PNG reader reserves what a chunk's
    length field says before reading it: a 116-byte PNG whose IDAT claimed 3.6 GB made it take
    3.5 GB of memory and 3 s (found by tests/unit/test_fuzz_codecs.py)."""
    pos, end = len(_PNG_SIGNATURE), data.nbytes
    while pos < end:
        if end - pos < _PNG_CHUNK_OVERHEAD:
            raise CorruptPayload(f"{where}: corrupt or truncated PNG (a chunk cut at byte {pos})")
        length, tag = _PNG_CHUNK_HEAD.unpack_from(data, pos)
        left = end - pos - _PNG_CHUNK_OVERHEAD
        if length > left:
            raise CorruptPayload(
                f"{where}: corrupt or truncated PNG (chunk {tag!r} at byte {pos} claims "
                f"{length} bytes, {left} follow)"
            )
        pos += _PNG_CHUNK_OVERHEAD + length
        if tag == b"IEND":
            return
    raise CorruptPayload(f"{where}: corrupt or truncated PNG (no IEND chunk)")


def _channel_groups(shape: Sequence[int]) -> tuple[int, int, int]:
    """(batch, channels, rest): ONNX puts channels on axis 1 of N×C×H×W and N×C×L tensors, whose
    parameters are then per channel; any other rank has one group (per tensor)."""
    if len(shape) in (3, 4):
        return shape[0], shape[1], math.prod(shape[2:])
    return 1, 1, math.prod(shape)


def _image_hwc(shape: Sequence[int]) -> tuple[int, int, int] | None:
    """(height, width, channels) of an image shape the image codecs take, else None."""
    dims = list(shape)
    if len(dims) == 4 and dims[0] == 1:
        dims = dims[1:]
    if len(dims) == 2:
        dims = [*dims, 1]
    if len(dims) != 3:
        return None
    h, w, c = dims
    if c not in (1, 3) or not (1 <= h <= MAX_IMAGE_SIDE_PX and 1 <= w <= MAX_IMAGE_SIDE_PX):
        return None
    return h, w, c


def image_hwc(shape: Sequence[int]) -> tuple[int, int, int] | None:
    """(height, width, channels) of a shape the image codecs take ((H,W), (H,W,C), (1,H,W,C)
    with C 1 or 3), else None."""
    return _image_hwc(shape)


def _as_array(array: Any) -> np.ndarray:
    if isinstance(array, np.generic):  # a numpy scalar (e.g. from a reduction) is a 0-d tensor
        array = np.asarray(array)
    if not isinstance(array, np.ndarray):
        raise WrongFieldType(f"tensor: expected a numpy array, got {type(array).__name__}")
    if _dtype_name(array.dtype) not in DTYPES:
        raise BadDtype(
            f"tensor: dtype {array.dtype.name!r} is not allowed; allowed: {', '.join(DTYPES)}"
        )
    return array


@functools.cache
def _dtype_name(dtype: np.dtype[Any]) -> str:
    """`dtype.name`, which numpy computes in Python at several µs a call: cached per dtype."""
    return dtype.name


def _mismatch(where: str, codec: str, dtype: np.dtype[Any], shape: Sequence[int]) -> str:
    fits = ", ".join(codec_names_for(dtype, shape)) or "none"
    return (
        f"{where}: codec {codec!r} does not apply to a {dtype.name} tensor of shape "
        f"{list(shape)}; codecs for it: {fits}"
    )


def _unknown(name: object) -> str:
    return f"unknown tensor codec {name!r}; valid: {VALID_CODECS_TEXT}"


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# zstd contexts are not thread-safe and cost a few µs to make: one pair per thread.
_ZSTD_LOCAL = threading.local()


def _zstd() -> zstandard.ZstdCompressor:
    compressor = getattr(_ZSTD_LOCAL, "compressor", None)
    if compressor is None:
        # The content size lets the receiver check the size before decompressing; the checksum
        # (4 bytes, xxhash) makes a corrupted frame an error rather than wrong values.
        compressor = _ZSTD_LOCAL.compressor = zstandard.ZstdCompressor(
            level=ZSTD_LEVEL, write_content_size=True, write_checksum=True
        )
    return compressor


def _unzstd() -> zstandard.ZstdDecompressor:
    decompressor = getattr(_ZSTD_LOCAL, "decompressor", None)
    if decompressor is None:
        decompressor = _ZSTD_LOCAL.decompressor = zstandard.ZstdDecompressor()
    return decompressor


def _decompress(data: Buffer, expected: int, where: str) -> bytes:
    """One zstd frame holding exactly `expected` bytes. python-zstandard sizes its output from the
    frame header and ignores `max_output_size` when the header gives a size, so the header is
    checked first; a frame without a size (ours always have one) is refused."""
    try:
        declared = zstandard.frame_content_size(data)
    except Exception as exc:  # ZstdError: not a zstd frame header
        raise CorruptPayload(f"{where}: not a zstd frame ({_one_line(exc)})") from None
    if declared != expected:
        said = "no size" if declared < 0 else f"{declared} bytes"
        raise CorruptPayload(f"{where}: zstd frame declares {said}, expected {expected} bytes")
    try:
        out = _unzstd().decompress(data, max_output_size=expected, allow_extra_data=False)
    except Exception as exc:  # ZstdError: corrupt frame, trailing bytes, wrong size
        raise CorruptPayload(f"{where}: corrupt zstd data ({_one_line(exc)})") from None
    if len(out) != expected:
        raise CorruptPayload(
            f"{where}: zstd data decompresses to {len(out)} bytes, expected {expected}"
        )
    return out


__all__ = [
    "CODECS",
    "CODEC_FP16",
    "CODEC_H264",
    "CODEC_INT8",
    "CODEC_INT8_ZSTD",
    "CODEC_PNG",
    "CODEC_RAW",
    "CODEC_RAW_ZSTD",
    "Codec",
    "EncodedTensor",
    "applies",
    "check_encoded",
    "codec_names_for",
    "decode_encoded",
    "decode_tensors",
    "encode_tensor_as",
    "image_hwc",
    "is_video",
    "parse_codec",
]
