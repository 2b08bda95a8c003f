"""A stereo camera's two topics paired by header stamp (robotd/sources/ros2_stereo.py), without
sessions: pairs within the slop, the unpaired counted, stamps out of order refused by name; the
geometry from the two CameraInfos in the model's view, a right camera with a positive P[3] named;
at 30 fps with ±5 ms of jitter on each image, at least 99% of the pairs are made."""

from __future__ import annotations

import numpy as np
import pytest

from common import ros2_messages as rm
from robotd.sources.ros2_stereo import StampOutOfOrder, StereoPairing, stereo_geometry
from robotd.sources.stereo_frame import LEFT_VIEW, RIGHT_VIEW

MS = 1_000_000
T0 = 1_700_000_000_000_000_000
IMAGE = np.zeros((2, 2, 3), np.uint8)


def frame(stamp_ns: int, frame_id: str = "") -> rm.StampedFrame:
    return rm.StampedFrame(IMAGE, rm.Header(stamp_ns, frame_id))


def test_images_within_the_slop_pair_and_the_others_are_counted() -> None:
    pairing = StereoPairing(10 * MS)
    assert pairing.add(LEFT_VIEW, frame(T0, "l")) is None
    pair = pairing.add(RIGHT_VIEW, frame(T0 + 4 * MS, "r"))
    assert pair is not None and (pair.left.header.frame_id, pair.right.header.frame_id) == (
        "l",
        "r",
    )
    # A left image with no right one within 10 ms: left waiting, then dropped as unpaired once a
    # right image too late for it comes.
    assert pairing.add(LEFT_VIEW, frame(T0 + 33 * MS)) is None
    assert pairing.add(RIGHT_VIEW, frame(T0 + 66 * MS)) is None
    assert pairing.unpaired == 1
    pair = pairing.add(LEFT_VIEW, frame(T0 + 67 * MS))
    assert pair is not None and pair.right.stamp_ns == T0 + 66 * MS
    assert (pairing.paired, pairing.unpaired) == (2, 1)


def test_the_nearest_waiting_image_is_taken_and_older_ones_dropped() -> None:
    pairing = StereoPairing(10 * MS)
    for ms in (0, 5, 8):  # three right images wait (a left one was lost)
        pairing.add(RIGHT_VIEW, frame(T0 + ms * MS))
    pair = pairing.add(LEFT_VIEW, frame(T0 + 9 * MS))
    assert pair is not None and pair.right.stamp_ns == T0 + 8 * MS
    assert pairing.unpaired == 2


def test_a_stamp_out_of_order_is_refused_by_name_and_not_kept() -> None:
    pairing = StereoPairing(10 * MS)
    pairing.add(LEFT_VIEW, frame(T0 + 33 * MS))
    with pytest.raises(StampOutOfOrder, match="not after the previous left one"):
        pairing.add(LEFT_VIEW, frame(T0))
    with pytest.raises(StampOutOfOrder):
        pairing.add(LEFT_VIEW, frame(T0 + 33 * MS))  # repeated
    assert pairing.add(RIGHT_VIEW, frame(T0 + 34 * MS)) is not None


def test_waiting_is_bounded() -> None:
    pairing = StereoPairing(1 * MS, max_waiting=4)
    for k in range(10):  # left images only: none can pair
        pairing.add(LEFT_VIEW, frame(T0 + k * 33 * MS))
    assert pairing.unpaired == 6


def test_30_fps_with_5_ms_jitter_pairs_at_least_99_percent() -> None:
    rng = np.random.default_rng(7)
    pairing = StereoPairing(10 * MS)
    frames = 3000
    events = []
    for k in range(frames):
        for side in (LEFT_VIEW, RIGHT_VIEW):
            stamp = T0 + round(k * 1e9 / 30) + int(rng.uniform(-5, 5) * MS)
            # Each image arrives after its stamp, with its own delay: sides interleave freely.
            events.append((stamp + int(rng.uniform(0, 8) * MS), side, stamp))
    for _, side, stamp in sorted(events):
        pairing.add(side, frame(stamp))
    assert pairing.paired / frames >= 0.99, (pairing.paired, pairing.unpaired)


def info(p3: float = 0.0, fx: float = 277.0, height: int = 480, width: int = 640) -> rm.CameraInfo:
    k = (fx, 0.0, 319.5, 0.0, fx, 239.5, 0.0, 0.0, 1.0)
    p = (fx, 0.0, 319.5, p3, 0.0, fx, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0)
    return rm.CameraInfo(rm.Header(T0), height, width, k=k, p=p)


def test_geometry_from_the_camera_infos_in_the_models_view() -> None:
    geometry = stereo_geometry(info(), info(p3=-277.0 * 0.06), 120, 160)
    # 640×480 to 160×120: no crop, a quarter of the size.
    assert geometry.fx_px == pytest.approx(277.0 / 4)
    assert geometry.cx_px == pytest.approx(79.5) and geometry.cy_px == pytest.approx(59.5)
    assert geometry.baseline_m == pytest.approx(0.06)
    # A square model input: the centred 480×480 crop, scaled by 1/4.
    square = stereo_geometry(info(), info(p3=-277.0 * 0.06), 120, 120)
    assert square.cx_px == pytest.approx((319.5 - 80 + 0.5) / 4 - 0.5)


@pytest.mark.parametrize("p3", [0.0, 16.6, float("nan")])
def test_a_right_camera_without_a_negative_p3_is_named(p3: float) -> None:
    with pytest.raises(rm.BadCameraInfo, match="P\\[3\\]"):
        stereo_geometry(info(), info(p3=p3), 120, 160)
