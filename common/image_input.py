"""A camera frame (uint8 BGR, OpenCV's layout) as a model's one image input.

The robot feeds its source's frames through `InputAdapter`, and the codec profiler
(`elasticfog model profile --codecs`) its calibration photographs, so both see the same input.
"""

from __future__ import annotations

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
