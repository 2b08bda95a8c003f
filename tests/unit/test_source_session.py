"""Which sources need the robot daemon's Zenoh session, and what happens without it: a source
fed over Zenoh opened without a session is a one-line SourceError (never a hang waiting for
frames), and the start's codec measurement reads photographs instead of it."""

from __future__ import annotations

import pytest

from common.source_spec import (
    DEFAULT_CAMERA_SOURCE,
    SourceError,
    calibration_source,
    needs_session,
    parse_source,
)
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


def test_calibration_reads_photographs_for_a_source_fed_over_zenoh() -> None:
    assert calibration_source("zenoh") == parse_source(DEFAULT_CAMERA_SOURCE)
    assert calibration_source("synthetic:every=2") == parse_source("synthetic:every=2")


def test_zenoh_takes_no_options() -> None:
    with pytest.raises(SourceError, match="takes no options"):
        parse_source("zenoh:fast")


def test_a_source_fed_over_zenoh_without_a_session_is_a_named_error() -> None:
    with pytest.raises(SourceError, match="over Zenoh"):
        open_source("zenoh", height=8, width=8)
