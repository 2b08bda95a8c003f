"""Frame sources of the robot daemon, and the conversion of a frame to the model's input.

A source yields uint8 BGR frames (H×W×3, OpenCV's layout) one at a time:

- `synthetic[:key=F][,every=N]`: seeded frames with controllable entropy. Key frames are
  textured (noise, gradients and blocks: normalized grey-level entropy near 1); the others are
  flat (one grey level with a little noise: entropy near 0.2). `key=F` draws each frame as a key
  frame with probability F (default 0.25, from the seed); `every=N` makes every N-th frame a key
  frame instead. The same seed gives the same frames, so runs can be compared.
- `video:PATH`: a video file read with OpenCV, looped at its end (a file stands in for a camera,
  so `--frames N` is honoured whatever the file's length).
- `camera:N`: the camera with index N through OpenCV.

A source that cannot be opened is a `UserError` naming it. `InputAdapter` resizes a frame to the
model's input (N×C×H×W or N×H×W×C, 1 or 3 channels) and scales it to [0, 1] for float inputs.
"""

from __future__ import annotations

import abc
import contextlib
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from common.errors import UserError
from common.partition import TensorSpec

SYNTHETIC = "synthetic"
VIDEO_PREFIX = "video:"
CAMERA_PREFIX = "camera:"
DEFAULT_KEY_FRACTION = 0.25
# Flat frames: one grey level, moving slowly, with noise of this amplitude (grey levels): a few
# histogram bins are used, so the normalized entropy stays around 0.2-0.3.
FLAT_NOISE_LEVELS = 3
KEY_BLOCKS = 12
CAMERA_READ_TRIES = 3
MAX_SOURCE_SIDE_PX = 8192
CHANNELS = (1, 3)


class SourceError(UserError):
    """A frame source that cannot be opened or read."""


class FrameSource(abc.ABC):
    """Yields uint8 BGR frames (H×W×3); `close()` releases the device or file."""

    description: str = "source"

    @abc.abstractmethod
    def read(self) -> np.ndarray:
        """The next frame; SourceError when none can be read."""

    def close(self) -> None:  # noqa: B027 - sources without resources need nothing
        """Release what the source holds."""

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SyntheticSource(FrameSource):
    """Seeded frames: textured key frames among flat ones (see the module docstring)."""

    def __init__(
        self,
        height: int,
        width: int,
        *,
        seed: int = 0,
        key_fraction: float = DEFAULT_KEY_FRACTION,
        key_every: int | None = None,
    ) -> None:
        _check_size(height, width)
        if not 0.0 <= key_fraction <= 1.0 or not math.isfinite(key_fraction):
            raise SourceError(f"synthetic source: key must be in [0, 1], got {key_fraction}")
        if key_every is not None and key_every < 1:
            raise SourceError(f"synthetic source: every must be >= 1, got {key_every}")
        self.height, self.width = height, width
        self.seed = seed
        self.key_fraction = key_fraction
        self.key_every = key_every
        self.index = 0
        self._rng = np.random.default_rng(seed)
        every = f", every={key_every}" if key_every else f", key={key_fraction:g}"
        self.description = f"synthetic {width}x{height} (seed {seed}{every})"

    def read(self) -> np.ndarray:
        n = self.index
        self.index += 1
        if self.key_every is not None:
            key = n % self.key_every == 0
        else:
            key = bool(self._rng.random() < self.key_fraction)
        return self._key_frame() if key else self._flat_frame(n)

    def _key_frame(self) -> np.ndarray:
        h, w, rng = self.height, self.width, self._rng
        frame = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        # Blocks of random colour over the noise: structure as well as texture.
        for _ in range(KEY_BLOCKS):
            y0, x0 = int(rng.integers(0, h)), int(rng.integers(0, w))
            y1 = min(h, y0 + int(rng.integers(1, max(2, h // 3))))
            x1 = min(w, x0 + int(rng.integers(1, max(2, w // 3))))
            colour = rng.integers(0, 256, size=3, dtype=np.uint8)
            frame[y0:y1, x0:x1] = (frame[y0:y1, x0:x1] // 2) + (colour // 2)
        return frame

    def _flat_frame(self, n: int) -> np.ndarray:
        # A slowly drifting grey level, as a camera facing a wall in changing light.
        level = 96 + int(32 * math.sin(n / 25.0))
        noise = self._rng.integers(
            -FLAT_NOISE_LEVELS, FLAT_NOISE_LEVELS + 1, size=(self.height, self.width, 1)
        )
        grey = np.clip(level + noise, 0, 255).astype(np.uint8)
        return np.repeat(grey, 3, axis=2)


class VideoSource(FrameSource):
    """A video file through OpenCV, looped at its end."""

    def __init__(self, path: str | Path, *, loop: bool = True) -> None:
        self.path = Path(path)
        self.loop = loop
        self.description = f"video {self.path}"
        if not self.path.is_file():
            raise SourceError(f"video file not found: {self.path}")
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            self._cap.release()
            raise SourceError(f"cannot open video file {self.path} (not a video OpenCV can read)")
        ok, first = self._cap.read()
        if not ok or first is None:
            self._cap.release()
            raise SourceError(f"video file {self.path} has no readable frame")
        self._pending: np.ndarray | None = first
        self.frames_read = 0

    def read(self) -> np.ndarray:
        if self._pending is not None:
            frame, self._pending = self._pending, None
        else:
            ok, frame = self._cap.read()
            if (not ok or frame is None) and self.loop:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                ok, frame = self._cap.read()
            if not ok or frame is None:
                raise SourceError(f"video file {self.path}: no more frames")
        self.frames_read += 1
        return _as_bgr(frame)

    def close(self) -> None:
        self._cap.release()


class CameraSource(FrameSource):
    """A camera by index through OpenCV."""

    def __init__(self, index: int) -> None:
        self.index = index
        self.description = f"camera {index}"
        _quiet_opencv()
        self._cap = cv2.VideoCapture(index)
        if not self._cap.isOpened():
            self._cap.release()
            raise SourceError(f"cannot open camera {index} (no such device, or it is busy)")

    def read(self) -> np.ndarray:
        for _ in range(CAMERA_READ_TRIES):
            ok, frame = self._cap.read()
            if ok and frame is not None:
                return _as_bgr(frame)
        raise SourceError(f"camera {self.index}: no frame after {CAMERA_READ_TRIES} tries")

    def close(self) -> None:
        self._cap.release()


def parse_synthetic_options(spec: str) -> dict[str, Any]:
    """The options of `synthetic:key=F,every=N` as keyword arguments of SyntheticSource."""
    _, _, text = spec.partition(":")
    options: dict[str, Any] = {}
    if not text.strip():
        return options
    for item in text.split(","):
        name, sep, value = (part.strip() for part in item.partition("="))
        if not sep or not value:
            raise SourceError(f"source {spec!r}: expected name=value options, got {item!r}")
        try:
            if name == "key":
                options["key_fraction"] = float(value)
            elif name == "every":
                options["key_every"] = int(value)
            else:
                raise SourceError(f"source {spec!r}: unknown option {name!r}; known: key, every")
        except ValueError:
            raise SourceError(f"source {spec!r}: {name}={value!r} is not a number") from None
    return options


def open_source(spec: str, *, height: int, width: int, seed: int = 0) -> FrameSource:
    """Open the source named by `spec` (synthetic[:OPTIONS], video:PATH or camera:N); synthetic
    frames are made `height`×`width` (the model's input size)."""
    spec = spec.strip()
    if spec == SYNTHETIC or spec.startswith(SYNTHETIC + ":"):
        return SyntheticSource(height, width, seed=seed, **parse_synthetic_options(spec))
    if spec.startswith(VIDEO_PREFIX) and spec[len(VIDEO_PREFIX) :].strip():
        return VideoSource(Path(spec[len(VIDEO_PREFIX) :].strip()).expanduser())
    if spec.startswith(CAMERA_PREFIX):
        text = spec[len(CAMERA_PREFIX) :].strip()
        if not text.isdigit():
            raise SourceError(f"source {spec!r}: camera needs an index, e.g. camera:0")
        return CameraSource(int(text))
    raise SourceError(
        f"unknown frame source {spec!r}; expected synthetic[:key=F,every=N], video:PATH or "
        "camera:INDEX"
    )


class InputAdapter:
    """Turns a BGR uint8 frame into the model's one image input.

    The input must be an image: N×C×H×W (or C×H×W) or N×H×W×C (or H×W×C) with N = 1 and
    C in {1, 3}. Frames are resized to H×W (OpenCV, area interpolation when shrinking), converted
    to RGB or grey, and scaled to [0, 1] for float inputs (uint8 inputs get the raw levels).
    """

    def __init__(self, spec: TensorSpec) -> None:
        self.spec = spec
        self.dtype = np.dtype(spec.dtype)
        shape = tuple(spec.shape)
        layout = _layout(shape)
        if layout is None or self.dtype.kind not in "fu":
            raise UserError(
                f"model input {spec.name!r} ({spec.dtype}, shape {list(shape)}) is not an image "
                "the robot can feed: expected float or uint8, N×C×H×W or N×H×W×C with N = 1 "
                "and 1 or 3 channels"
            )
        self.channels_first, self.channels, self.height, self.width = layout

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        if frame.shape[:2] != (self.height, self.width):
            shrink = frame.shape[0] > self.height or frame.shape[1] > self.width
            interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
            frame = cv2.resize(frame, (self.width, self.height), interpolation=interpolation)
        if self.channels == 1:
            image = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)[:, :, None]
        else:
            image = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        if self.channels_first:
            image = image.transpose(2, 0, 1)
        if self.dtype.kind == "f":
            array = image.astype(self.dtype) / self.dtype.type(255.0)
        else:
            array = image.astype(self.dtype)
        return np.ascontiguousarray(array.reshape(self.spec.shape))


def _layout(shape: tuple[int, ...]) -> tuple[bool, int, int, int] | None:
    """(channels_first, C, H, W) of an image shape, or None."""
    if len(shape) == 4:
        if shape[0] != 1:
            return None
        shape = shape[1:]
    if len(shape) != 3:
        return None
    if shape[0] in CHANNELS and shape[2] not in CHANNELS:
        return True, shape[0], shape[1], shape[2]
    if shape[2] in CHANNELS and shape[0] not in CHANNELS:
        return False, shape[2], shape[0], shape[1]
    if shape[0] in CHANNELS:  # e.g. 3×3×3: take the ONNX convention, channels first
        return True, shape[0], shape[1], shape[2]
    return None


def _as_bgr(frame: np.ndarray) -> np.ndarray:
    """OpenCV frames as uint8 H×W×3 (grey and BGRA converted)."""
    if frame.dtype != np.uint8:
        frame = cv2.convertScaleAbs(frame)
    if frame.ndim == 2:
        return cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    if frame.shape[2] == 4:
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    return frame


def _check_size(height: int, width: int) -> None:
    for name, value in (("height", height), ("width", width)):
        if not 1 <= value <= MAX_SOURCE_SIDE_PX:
            raise SourceError(f"synthetic source: {name} must be 1..{MAX_SOURCE_SIDE_PX}")


def _quiet_opencv() -> None:
    """Keep OpenCV's own warnings (e.g. a missing /dev/video*) off the terminal: the SourceError
    says what went wrong in one line."""
    with contextlib.suppress(AttributeError):  # builds without the logging module
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
