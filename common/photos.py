"""Real photographs shipped in the scikit-image wheel (nothing is downloaded), as camera frames.

The robot's `photo` source moves a virtual camera over them
(`robotd.sources.frame_sources.PhotoSource`); the codec profiler measures JPEG sizes and fidelity on
still views of them (`still_views`), as a camera's frames of ordinary scenes, not noise.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

# Photographs of the `photo` source: name → how skimage.data returns it (function, and the item
# of a tuple it returns, if any). All of them ship inside the scikit-image wheel.
PHOTOS: dict[str, tuple[str, int | None]] = {
    "astronaut": ("astronaut", None),
    "coffee": ("coffee", None),
    "chelsea": ("chelsea", None),
    "rocket": ("rocket", None),
    "motorcycle": ("stereo_motorcycle", 0),
    "immunohistochemistry": ("immunohistochemistry", None),
}
# The still views are crops of this share of a photograph's side, at positions spread over it.
VIEW_SHARE = 0.8


@functools.cache
def photo_bgr(name: str) -> np.ndarray:
    """A photograph of PHOTOS as uint8 BGR, loaded once per process (read-only)."""
    # skimage is slow to import, only the photographs need it, and a robot may not have it.
    from common.extras import Extra, require

    skimage_data = require("skimage.data", Extra.DATA, "the photographs")
    function, item = PHOTOS[name]
    loaded = getattr(skimage_data, function)()
    rgb = loaded[item] if item is not None else loaded
    bgr = np.ascontiguousarray(cv2.cvtColor(np.asarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR))
    bgr.setflags(write=False)
    return bgr


def still_views(count: int) -> list[np.ndarray]:
    """`count` uint8 BGR views, taking the photographs in turn (a crop of `VIEW_SHARE` of each
    side, its position moving from view to view), so the content varies as a camera's does."""
    names = list(PHOTOS)
    views = []
    for i in range(count):
        photo = photo_bgr(names[i % len(names)])
        h, w = photo.shape[:2]
        ch, cw = int(h * VIEW_SHARE), int(w * VIEW_SHARE)
        step = (i // len(names)) % 3  # 0, 1, 2: top-left, centre, bottom-right
        y, x = (h - ch) * step // 2, (w - cw) * step // 2
        views.append(np.ascontiguousarray(photo[y : y + ch, x : x + cw]))
    return views
