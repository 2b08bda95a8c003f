"""A stereo frame: the two views of a camera pair taken together, as the robot's sources hand it on.

Mono sources yield a bare uint8 BGR array (H×W×3); stereo sources (`nav.stereo_sources`) a
`StereoFrame` whose views are named like the image inputs they feed (`left`, `right`, the
inputs of zoo:stereo), so the robot matches views to inputs by name, and whose one timestamp is
when the pair was taken (both views show the same instant: a rectified pair must).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

LEFT_VIEW = "left"
RIGHT_VIEW = "right"
STEREO_VIEWS = (LEFT_VIEW, RIGHT_VIEW)


@dataclass(frozen=True)
class StereoFrame:
    """The views of one stereo frame (uint8 BGR, H×W×3 each, by name, left first) and the wall
    clock (`time.time()`, seconds) when they were taken."""

    views: Mapping[str, np.ndarray]
    stamp_s: float

    @property
    def first(self) -> np.ndarray:
        """The first view (the left one): what a frame's entropy is measured on."""
        return next(iter(self.views.values()))


CameraFrame = np.ndarray | StereoFrame
"""What a frame source yields: one image, or the views of a stereo pair."""


def first_view(frame: CameraFrame) -> np.ndarray:
    """The image of a mono frame, the first (left) view of a stereo one."""
    return frame.first if isinstance(frame, StereoFrame) else frame
