"""Camera frames (uint8 BGR, OpenCV's layout) as a model's image inputs.

`InputAdapter` turns one frame into one image input. `ImageInputs` holds one adapter per image
input of a model and feeds them: a model with one input takes a mono frame (whatever the input's
name), a model with several takes the named views of a stereo frame, matched by name (`left`,
`right` for zoo:stereo). The robot feeds its source's frames through them, and the codec
profiler (`elasticfog model profile --codecs`) its calibration photographs, so both see the same
input.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from common.errors import UserError
from common.partition import TensorSpec

CHANNELS = (1, 3)


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

    def image(self, array: np.ndarray) -> np.ndarray:
        """The BGR uint8 H×W×3 image a model input made by this adapter holds: its inverse at
        the model's size (what the model saw; a recording of a run's input shows that)."""
        image = np.asarray(array).reshape(self.spec.shape)
        if image.ndim == 4:
            image = image[0]
        if self.channels_first:
            image = image.transpose(1, 2, 0)
        if self.dtype.kind == "f":
            image = np.clip(np.rint(image.astype(np.float32) * 255.0), 0, 255)
        image = np.ascontiguousarray(image, dtype=np.uint8)
        if self.channels == 1:
            return cv2.cvtColor(image[:, :, 0], cv2.COLOR_GRAY2BGR)
        return cv2.cvtColor(image, cv2.COLOR_RGB2BGR)


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


class ImageInputs:
    """One `InputAdapter` per image input of a model (all of one height and width: the views of
    a camera pair); `feeds` turns a frame into the model's input.

    A model with one input takes mono frames. A model with several takes stereo frames whose
    views are named like its inputs: `check_views` says, at start, in one line, when a source's
    views do not fit (a mono source on a stereo model, a stereo source on a mono one)."""

    def __init__(self, specs: Sequence[TensorSpec], model: str = "the model") -> None:
        if not specs:
            raise UserError(f"model {model} has no input to feed")
        self.model = model
        self.adapters = {spec.name: InputAdapter(spec) for spec in specs}
        first = next(iter(self.adapters.values()))
        self.height, self.width = first.height, first.width
        sizes = {f"{a.width}x{a.height}" for a in self.adapters.values()}
        if len(sizes) > 1:
            raise UserError(
                f"model {model}'s image inputs {self._listed()} differ in size "
                f"({', '.join(sorted(sizes))}); the views of a frame share one size"
            )

    @property
    def names(self) -> tuple[str, ...]:
        """The model's image inputs, in the model's order."""
        return tuple(self.adapters)

    @property
    def views(self) -> tuple[str, ...] | None:
        """The views a frame must carry: None for a one-input model (a mono frame), else the
        inputs' names."""
        return None if len(self.adapters) == 1 else self.names

    def check_views(self, views: Sequence[str] | None, source: str) -> None:
        """UserError (one line) unless frames with these views (None: mono) feed the model."""
        if views is None and self.views is None:
            return
        if views is None:
            raise UserError(
                f"source {source} gives one image a frame; model {self.model} takes "
                f"{len(self.adapters)} image inputs ({self._listed()}): use a stereo source "
                "(stereo:world, stereo:motorcycle, stereo:LEFT,RIGHT)"
            )
        if self.views is None:
            raise UserError(
                f"source {source} gives {len(views)} views a frame ({', '.join(views)}); "
                f"model {self.model} takes one image input ({self._listed()}): use a mono source"
            )
        if sorted(views) != sorted(self.names):
            raise UserError(
                f"source {source} gives views {', '.join(views)}; model {self.model}'s image "
                f"inputs are {self._listed()}: views are matched to inputs by name"
            )

    def feeds(self, frame: np.ndarray | Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The model's input for one mono frame, or for the views of a stereo frame by name."""
        if isinstance(frame, np.ndarray):
            if self.views is not None:
                self.check_views(None, "of this frame")
            ((name, adapter),) = self.adapters.items()
            return {name: adapter(frame)}
        self.check_views(tuple(frame), "of this frame")
        return {name: adapter(frame[name]) for name, adapter in self.adapters.items()}

    def _listed(self) -> str:
        return ", ".join(self.adapters)
