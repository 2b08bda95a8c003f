"""Which sources need the robot daemon's Zenoh session, and what happens without it: a source
fed over Zenoh opened without a session is a one-line SourceError (never a hang waiting for
frames), and the start's codec measurement never opens it a second time (nor reads packaged
photographs instead: its codecs are measured on the first frames it serves)."""

from __future__ import annotations

import pytest

from common.image_input import ImageInputs
from common.partition import TensorSpec
from common.source_spec import SourceError, needs_session, parse_source
from robotd.calibration import calibration_frames
from robotd.sources.opening import open_source


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("zenoh", True),
        (" zenoh ", True),
        ("photo", False),
        ("synthetic", False),
        ("video:zenoh.mp4", False),
        ("stereo:world", False),
    ],
)
def test_sources_fed_over_zenoh_need_the_session(spec: str, expected: bool) -> None:
    assert needs_session(spec) is expected


@pytest.mark.parametrize("spec", ["zenoh", "ros2:/camera/image_raw"])
def test_a_source_fed_over_zenoh_is_not_opened_again_for_calibration(spec: str) -> None:
    """Regression guard (issue 33): its calibration frames were scikit-image's photographs,
    which a robot installed from the runtime lock does not have."""
    inputs = ImageInputs([TensorSpec("image", "uint8", (1, 8, 8, 3))])
    with pytest.raises(SourceError, match="first frames it serves"):
        calibration_frames(spec, inputs, 2, seed=0)


def test_a_source_read_by_the_robot_gives_its_own_calibration_frames() -> None:
    inputs = ImageInputs([TensorSpec("image", "uint8", (1, 8, 8, 3))])
    frames = calibration_frames("synthetic:every=2", inputs, 2, seed=0)
    assert len(frames) == 2 and frames[0]["image"].shape == (1, 8, 8, 3)


def test_zenoh_takes_no_options() -> None:
    with pytest.raises(SourceError, match="takes no options"):
        parse_source("zenoh:fast")


def test_a_source_fed_over_zenoh_without_a_session_is_a_named_error() -> None:
    with pytest.raises(SourceError, match="over Zenoh"):
        open_source("zenoh", height=8, width=8)
