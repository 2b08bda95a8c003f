"""Normalized grey-level entropy of frames (robotd.frame_path.entropy)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.errors import UserError
from robotd.frame_path.entropy import frame_entropy


def test_flat_frame_has_zero_entropy() -> None:
    assert frame_entropy(np.full((240, 320), 77, dtype=np.uint8)) == 0.0


def test_two_equal_levels_carry_one_bit_of_eight() -> None:
    frame = np.zeros((10, 20), dtype=np.uint8)
    frame[:, 10:] = 200
    assert frame_entropy(frame) == pytest.approx(1 / 8)


def test_all_levels_equally_often_is_maximal() -> None:
    frame = np.arange(256 * 4, dtype=np.int64).reshape(32, 32).astype(np.uint8)
    assert frame_entropy(frame) == pytest.approx(1.0)


def test_colour_frame_uses_its_grey_image() -> None:
    rng = np.random.default_rng(3)
    grey = rng.integers(0, 256, size=(48, 64), dtype=np.uint8)
    bgr = np.repeat(grey[:, :, None], 3, axis=2)
    bgra = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
    expected = frame_entropy(grey)
    assert frame_entropy(bgr) == pytest.approx(expected)
    assert frame_entropy(bgra) == pytest.approx(expected)
    assert frame_entropy(grey[:, :, None]) == pytest.approx(expected)


def test_busier_frames_score_higher_and_stay_in_range() -> None:
    rng = np.random.default_rng(0)
    smooth = np.tile(np.linspace(100, 140, 320).astype(np.uint8), (240, 1))
    noisy = rng.integers(0, 256, size=(240, 320), dtype=np.uint8)
    colour_noise = rng.integers(0, 256, size=(240, 320, 3), dtype=np.uint8)
    low, high = frame_entropy(smooth), frame_entropy(noisy)
    assert 0.0 < low < high <= 1.0
    assert high > 0.99  # uniform grey noise is close to 8 bits
    # Averaging three noisy channels narrows the grey histogram: still busy, a bit lower.
    assert low < frame_entropy(colour_noise) < high


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (np.zeros((4, 4), dtype=np.float32), "uint8"),
        (np.zeros((4, 4, 2), dtype=np.uint8), "shape"),
        (np.zeros((0, 4), dtype=np.uint8), "empty"),
        ([[1, 2], [3, 4]], "numpy array"),
    ],
)
def test_bad_frames_are_named(frame: object, message: str) -> None:
    with pytest.raises(UserError, match=message):
        frame_entropy(frame)  # type: ignore[arg-type]
