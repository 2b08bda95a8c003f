"""What an application sends a robot: camera frames, on `keys.frames_in` (`ef/<fleet>/in/<robot>`),
read by the robot's `zenoh` source.

A `FrameIn` is one frame: its capture stamp and, per image input of the model, one `ImageIn`:
either encoded (`jpeg` or `png` bytes, the size read from the image) or raw uint8 H×W×C rows
with their `encoding` (`rgb8`, `bgr8`: C = 3; `mono8`: C = 1) and `height` and `width`. A model
with one image input takes the frame's only image whatever its name; a model with several (a
stereo pair) takes the images named like its inputs.

Decoding is strict: `FrameIn.from_wire` checks the envelope, types and sizes (a raw image's byte
count must be height × width × channels); `decode_image` turns one image into OpenCV's uint8 BGR
H×W×3 (what every robot source yields), reading a JPEG's or PNG's header first so an image
larger than the receiver's `max_side_px` is refused before its pixels are decoded. Every failure
is a `WireError` subclass with a one-line reason. `image_in` builds an `ImageIn` from an array
(what the Python client sends).
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from common.wire.codec import Buffer, Message, Struct, key_path, register
from common.wire.errors import CorruptPayload, InvalidValue, ShapeMismatch, UnknownCodec
from common.wire.tensor_codecs import MAX_IMAGE_SIDE_PX

# JPEG quality of `image_in(..., "jpeg")` when none is given: a camera's usual setting.
DEFAULT_JPEG_QUALITY = 90
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IHDR = struct.Struct(">I4sII")  # chunk length, b"IHDR", width, height


class ImageEncoding(str, enum.Enum):
    """How an `ImageIn`'s bytes hold the image (names as ROS 2's `sensor_msgs` spell them)."""

    JPEG = "jpeg"
    PNG = "png"
    RGB8 = "rgb8"
    BGR8 = "bgr8"
    MONO8 = "mono8"

    @property
    def channels(self) -> int | None:
        """Channels of a raw encoding; None for an encoded (compressed) image."""
        return _RAW_CHANNELS.get(self)


_RAW_CHANNELS = {ImageEncoding.RGB8: 3, ImageEncoding.BGR8: 3, ImageEncoding.MONO8: 1}


@dataclass(frozen=True, slots=True, kw_only=True)
class ImageIn(Struct):
    """One image of a frame: `data` in `encoding`; `height` and `width` (pixels) are required
    for a raw encoding and, when given (not 0) for JPEG/PNG, checked against the image."""

    encoding: ImageEncoding
    data: Buffer
    height: int = 0
    width: int = 0

    def __post_init__(self) -> None:
        self._check_non_negative("height", "width")
        for side in ("height", "width"):
            if getattr(self, side) > MAX_IMAGE_SIDE_PX:
                raise self._invalid(side, f"must be at most {MAX_IMAGE_SIDE_PX} px")
        size = memoryview(self.data).nbytes
        channels = self.encoding.channels
        if channels is None:
            if size == 0:
                raise self._invalid("data", f"empty {self.encoding.value} image")
            return
        if self.height < 1 or self.width < 1:
            raise self._invalid(
                "height",
                f"a {self.encoding.value} image needs height and width >= 1, got "
                f"{self.height}×{self.width}",
            )
        expected = self.height * self.width * channels
        if size != expected:
            raise ShapeMismatch(
                f"image_in.data: {self.height}×{self.width} {self.encoding.value} needs "
                f"{expected} bytes, got {size}"
            )


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class FrameIn(Message):
    """One camera frame for a robot: `stamp_ns` its capture stamp (ns since the epoch; the
    result of this frame carries it back), `images` its image per input name."""

    TYPE: ClassVar[str] = "frame_in"
    stamp_ns: int
    images: dict[str, ImageIn]

    def __post_init__(self) -> None:
        self._check_non_negative("stamp_ns")
        if not self.images:
            raise self._invalid("images", "a frame needs at least one image")
        for name, image in self.images.items():
            if not isinstance(image, ImageIn):
                raise self._invalid(
                    "images",
                    f"{key_path('images', name)} is a {type(image).__name__}, expected an ImageIn",
                )


def image_in(
    image: np.ndarray, encoding: ImageEncoding | str = ImageEncoding.JPEG, *, quality: int = 0
) -> ImageIn:
    """`image` (uint8 BGR H×W×3, OpenCV's layout, or grey H×W / H×W×1) as an `ImageIn` in
    `encoding`: JPEG (at `quality`, default DEFAULT_JPEG_QUALITY) or PNG bytes, or raw rows
    (`bgr8` as given, `rgb8` with the channels swapped, `mono8` for a grey image)."""
    import cv2  # imported on first use: most processes never touch images

    try:
        kind = ImageEncoding(encoding)
    except ValueError:
        known = ", ".join(e.value for e in ImageEncoding)
        raise UnknownCodec(f"image encoding {encoding!r} is not one of {known}") from None
    array = np.asarray(image)
    if array.dtype != np.uint8 or array.ndim not in (2, 3) or array.size == 0:
        raise InvalidValue(
            f"image: expected a non-empty uint8 H×W×C array, got {array.dtype}{list(array.shape)}"
        )
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels not in (1, 3):
        raise InvalidValue(f"image: expected 1 or 3 channels, got {channels}")
    height, width = array.shape[:2]
    if kind in (ImageEncoding.JPEG, ImageEncoding.PNG):
        if kind is ImageEncoding.JPEG:
            params = [cv2.IMWRITE_JPEG_QUALITY, quality or DEFAULT_JPEG_QUALITY]
        else:
            params = [cv2.IMWRITE_PNG_COMPRESSION, 1]
        ok, data = cv2.imencode(f".{kind.value}", array, params)
        if not ok:
            raise InvalidValue(f"image: OpenCV could not encode a {height}×{width} {kind.value}")
        return ImageIn(encoding=kind, data=data.tobytes(), height=height, width=width)
    wanted = kind.channels
    if wanted == 1 and channels == 3:
        array = cv2.cvtColor(array, cv2.COLOR_BGR2GRAY)
    elif wanted == 3 and channels == 1:
        array = cv2.cvtColor(array, cv2.COLOR_GRAY2BGR)
    if kind is ImageEncoding.RGB8:
        array = cv2.cvtColor(array, cv2.COLOR_BGR2RGB)
    return ImageIn(
        encoding=kind, data=np.ascontiguousarray(array).tobytes(), height=height, width=width
    )


def decode_image(
    image: ImageIn,
    *,
    max_side_px: int,
    max_bytes: int | None = None,
    fit: tuple[int, int] | None = None,
    where: str = "image",
) -> np.ndarray:
    """The image as uint8 BGR H×W×3; a WireError naming `where` when it cannot be decoded
    (CorruptPayload), is larger than `max_side_px` on a side or than `max_bytes` decoded
    (InvalidValue, read from the header before the pixels are decoded: a small JPEG may claim
    a huge image), or is not of the size it declares (ShapeMismatch).

    `fit` (height, width): the image will be fitted to that size (its centred rectangle of that
    aspect, scaled): a JPEG is then decoded at the smallest of libjpeg-turbo's DCT scales (M/8)
    whose rectangle still covers it, which costs a fraction of a full decode and of the resize
    after it (a 640×480 camera frame for a 224×224 model decodes at 320×240)."""
    import cv2

    kind = image.encoding
    data = memoryview(image.data)
    if kind.channels is not None:
        height, width, channels = image.height, image.width, kind.channels
    elif kind is ImageEncoding.JPEG:
        height, width = _jpeg_size(data, where)
    else:
        height, width = _png_size(data, where)
    if height < 1 or width < 1:
        raise InvalidValue(f"{where}: a {height}×{width} image has no pixels")
    if max(height, width) > max_side_px:
        raise InvalidValue(
            f"{where}: a {height}×{width} image is larger than {max_side_px} px on a side"
        )
    if max_bytes is not None and height * width * 3 > max_bytes:
        raise InvalidValue(
            f"{where}: a {height}×{width} image decodes to more than {max_bytes} bytes"
        )
    if image.height and image.width and (image.height, image.width) != (height, width):
        raise ShapeMismatch(
            f"{where}: the {kind.value} image is {height}×{width}, the message says "
            f"{image.height}×{image.width}"
        )
    if kind is ImageEncoding.JPEG:
        return _decode_jpeg(data, height, width, fit, where)
    if kind.channels is None:
        try:
            decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        except cv2.error as exc:
            reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else "OpenCV error"
            raise CorruptPayload(f"{where}: corrupt {kind.value} ({reason})") from None
        if decoded is None or decoded.shape[:2] != (height, width):
            raise CorruptPayload(f"{where}: corrupt or truncated {kind.value} image")
        return np.asarray(decoded)
    rows = np.frombuffer(data, np.uint8).reshape(height, width, channels)
    if kind is ImageEncoding.BGR8:
        return rows
    if kind is ImageEncoding.RGB8:
        return np.asarray(cv2.cvtColor(rows, cv2.COLOR_RGB2BGR))
    return np.asarray(cv2.cvtColor(rows, cv2.COLOR_GRAY2BGR))


def _decode_jpeg(
    data: memoryview, height: int, width: int, fit: tuple[int, int] | None, where: str
) -> np.ndarray:
    """A JPEG as BGR, at the smallest DCT scale that still covers `fit` (see decode_image)."""
    import simplejpeg

    min_height = min_width = 0
    if fit is not None:
        fit_h, fit_w = fit
        aspect = fit_w / fit_h
        # The centred rectangle of the fit's aspect, and the scale it needs to cover the fit.
        rect_h, rect_w = (
            (height, height * aspect) if width / height > aspect else (width / aspect, width)
        )
        scale = max(fit_h / rect_h, fit_w / rect_w)
        min_height, min_width = math.ceil(height * scale), math.ceil(width * scale)
    try:
        decoded = simplejpeg.decode_jpeg(
            data, colorspace="BGR", min_height=min_height, min_width=min_width, strict=True
        )
    except Exception as exc:  # ValueError from libjpeg-turbo, whatever the bytes
        reason = str(exc).strip().replace("\n", " ") or type(exc).__name__
        raise CorruptPayload(f"{where}: corrupt JPEG ({reason})") from None
    return np.asarray(decoded)


def _jpeg_size(data: memoryview, where: str) -> tuple[int, int]:
    import simplejpeg

    try:
        height, width, _, _ = simplejpeg.decode_jpeg_header(data)
    except Exception as exc:  # ValueError from libjpeg-turbo, whatever the bytes
        reason = str(exc).strip().replace("\n", " ") or type(exc).__name__
        raise CorruptPayload(f"{where}: not a readable JPEG ({reason})") from None
    return int(height), int(width)


def _png_size(data: memoryview, where: str) -> tuple[int, int]:
    head = bytes(data[: len(_PNG_SIGNATURE) + _PNG_IHDR.size])
    if len(head) < len(_PNG_SIGNATURE) + _PNG_IHDR.size or not head.startswith(_PNG_SIGNATURE):
        raise CorruptPayload(f"{where}: not a PNG (no PNG signature and IHDR)")
    length, tag, width, height = _PNG_IHDR.unpack_from(head, len(_PNG_SIGNATURE))
    if (length, tag) != (13, b"IHDR"):
        raise CorruptPayload(f"{where}: not a PNG (IHDR is not the first chunk)")
    return int(height), int(width)


__all__ = [
    "DEFAULT_JPEG_QUALITY",
    "FrameIn",
    "ImageEncoding",
    "ImageIn",
    "decode_image",
    "image_in",
]
