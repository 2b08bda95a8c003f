"""Normalized grey-level entropy of a camera frame, the key-frame signal of ElasticAction.

H = -Σ p_i log2 p_i over the 256-bin grey-level histogram (OpenCV `calcHist`), divided by its
maximum, 8 bits, so the result lies in [0, 1]: 0 for a flat frame, near 1 for a busy one.
Colour frames are converted with OpenCV's BGR weights; for RGB input the grey image differs only
in how red and blue are weighted, which moves the entropy by a hair.
"""

from __future__ import annotations

import cv2
import numpy as np

from common.errors import UserError

GREY_LEVELS = 256
MAX_ENTROPY_BITS = 8.0  # log2(256)


def frame_entropy(frame: np.ndarray) -> float:
    """Normalized grey-level entropy in [0, 1] of a uint8 frame (H×W, H×W×1, H×W×3 or H×W×4)."""
    if not isinstance(frame, np.ndarray):
        raise UserError(f"frame must be a numpy array, got {type(frame).__name__}")
    if frame.dtype != np.uint8:
        raise UserError(f"frame must be uint8, got {frame.dtype}")
    if frame.size == 0:
        raise UserError("frame is empty")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if frame.ndim == 3 and frame.shape[2] == 3:
        grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    elif frame.ndim == 3 and frame.shape[2] == 4:
        grey = cv2.cvtColor(frame, cv2.COLOR_BGRA2GRAY)
    elif frame.ndim == 2:
        grey = frame
    else:
        raise UserError(f"frame must be H×W or H×W×{{1,3,4}}, got shape {frame.shape}")
    hist = cv2.calcHist([np.ascontiguousarray(grey)], [0], None, [GREY_LEVELS], [0, GREY_LEVELS])
    counts = hist.ravel()
    p = counts[counts > 0] / float(grey.size)
    bits = float(-(p * np.log2(p)).sum())
    return min(max(bits / MAX_ENTROPY_BITS, 0.0), 1.0)
