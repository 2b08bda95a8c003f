"""Judging a disparity map against ground truth, and OpenCV's matchers as baselines.

bad-N is the Middlebury measure: the share of pixels with known ground truth whose disparity is
off by more than N pixels, a missing (invalid) disparity counting as wrong; density is the share
of those pixels that have a disparity at all. The pair is Middlebury 2014's Motorcycle as
scikit-image ships it (``skimage.data.stereo_motorcycle``: 741×500, disparities 7..60 px, unknown
ground truth as inf), so nothing is downloaded.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.errors import UserError

# OpenCV returns disparities in 1/16 px.
_CV_DISPARITY_SCALE = 16.0


@dataclass(frozen=True)
class Accuracy:
    bad: float
    density: float


def bad_pixels(disparity: np.ndarray, truth: np.ndarray, threshold_px: float = 2.0) -> Accuracy:
    """bad-``threshold`` and density of ``disparity`` (NaN: invalid) where ``truth`` is finite."""
    if disparity.shape != truth.shape:
        raise UserError(f"disparity {disparity.shape} and ground truth {truth.shape} differ")
    known = np.isfinite(truth)
    if not known.any():
        raise UserError("the ground truth has no known pixel")
    have = np.isfinite(disparity) & known
    error = np.abs(np.where(have, disparity, 0.0) - np.where(known, truth, 0.0))
    wrong = known & (~have | (error > threshold_px))
    return Accuracy(float(wrong.sum() / known.sum()), float(have.sum() / known.sum()))


def stereo_motorcycle() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left RGB, right RGB, ground-truth disparity with NaN where unknown)."""
    # skimage is slow to import, only this pair needs it, and a robot may not have it.
    from common.extras import Extra, require

    data = require("skimage.data", Extra.DATA, "the stereo pair")
    left, right, truth = data.stereo_motorcycle()
    truth = np.where(np.isfinite(truth), truth, np.nan).astype(np.float32)
    return np.ascontiguousarray(left), np.ascontiguousarray(right), truth


def opencv_disparity(
    left_rgb: np.ndarray, right_rgb: np.ndarray, max_disparity: int, method: str, block_px: int
) -> np.ndarray:
    """StereoBM ("bm") or StereoSGBM ("sgbm") over disparities 0..D−1 (D rounded up to a
    multiple of 16, as OpenCV requires), NaN where OpenCV marks no disparity. Other settings are
    OpenCV's defaults; SGBM's smoothness penalties are the ones its documentation suggests."""
    grey_l = cv2.cvtColor(left_rgb, cv2.COLOR_RGB2GRAY)
    grey_r = cv2.cvtColor(right_rgb, cv2.COLOR_RGB2GRAY)
    n = 16 * -(-max_disparity // 16)
    matcher: cv2.StereoMatcher
    if method == "bm":
        matcher = cv2.StereoBM.create(numDisparities=n, blockSize=block_px)
    elif method == "sgbm":
        matcher = cv2.StereoSGBM.create(
            minDisparity=0,
            numDisparities=n,
            blockSize=block_px,
            P1=8 * block_px * block_px,
            P2=32 * block_px * block_px,
        )
    else:
        raise UserError(f"unknown OpenCV matcher {method!r}: bm or sgbm")
    raw = matcher.compute(grey_l, grey_r).astype(np.float32) / _CV_DISPARITY_SCALE
    # Invalid is (minDisparity − 1); anything beyond D − 1 is outside the range asked for.
    return np.where((raw >= 0) & (raw <= max_disparity - 1), raw, np.nan)
