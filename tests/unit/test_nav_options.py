"""The navigation options 1–4 as policies (`robotd.policies.nav_options`), the camera pair's
codec in options 1 and 3 (parsed, refused elsewhere, measured by the robot at start), the segment
action they need (`Decision.end`, `CutTable.with_segment`, labels), and the request's optional
end cut on the wire (`InferRequest.end_cut`: absent means to the end, as older peers send it)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from common.errors import UserError
from common.wire import decode, encode_raw
from common.wire.errors import InvalidValue
from common.wire.robot_to_cloud import InferRequest
from common.wire.telemetry import action_label, parse_action_codec, parse_action_segment
from common.wire.tensor_codecs import EncodedTensor
from robotd.calibration import required_codecs
from robotd.policies import PURE_ROBOT, Decision, FrameContext, make_policy, params_model
from robotd.policies.base import CutTable
from robotd.policies.nav_options import OptionParams, nav_option

POINTS = 4


def nav_profile(**changes: Any) -> dict[str, Any]:
    """A stereo-like profile: cuts 0..4, `points` named at 4, the segment 0-4 there."""
    profile: dict[str, Any] = {
        "full_ms": 100.0,
        "cuts": [
            {"index": k, "bytes": b, "prefix_ms": p, "suffix_ms": 100.0 - p}
            for k, b, p in [(0, 450, 0.0), (1, 150, 1.0), (2, 1200, 3.0), (3, 300, 88.0)]
        ]
        + [{"index": POINTS, "bytes": 900, "prefix_ms": 92.0, "suffix_ms": 8.0}],
        "named_cuts": {"points": POINTS},
        "segments": [[0, POINTS], [1, 2]],
    }
    profile.update(changes)
    return profile


def with_pair_codecs(profile: dict[str, Any], *names: str) -> dict[str, Any]:
    """`profile` with the camera pair (cut 0) measured in `names` besides raw, as the robot's
    calibration leaves it when the option names a codec."""
    pair = profile["cuts"][0]
    pair["codecs"] = [{"name": "raw", "bytes": pair["bytes"]}] + [
        {"name": name, "bytes": pair["bytes"] / 10, "encode_ms": 1.0, "decode_ms": 1.0}
        for name in names
    ]
    return profile


def decided(spec: str, params: dict[str, Any] | None = None, **changes: Any) -> Decision:
    profile = with_pair_codecs(nav_profile(**changes), "jpeg80", "png")
    return make_policy(spec, profile, params).decide(FrameContext(index=0))


@pytest.mark.parametrize(
    ("option", "action", "end", "label"),
    [(1, 0, None, "0"), (2, POINTS, None, "4"), (3, 0, POINTS, "0-4"), (4, PURE_ROBOT, None, "P")],
)
def test_each_option_is_its_fixed_action(
    option: int, action: object, end: int | None, label: str
) -> None:
    for decision in (decided("static", {"option": option}), decided(f"option:{option}")):
        assert (decision.action, decision.end, decision.label) == (action, end, label)
        assert not decision.hedge


def test_the_fleet_form_takes_the_option_as_its_only_parameter() -> None:
    assert params_model("static") is OptionParams
    with pytest.raises(UserError, match="policy static params: option: required key is missing"):
        decided("static", {})
    with pytest.raises(UserError, match="option: Input should be less than or equal to 4"):
        decided("static", {"option": 5})
    with pytest.raises(UserError, match="expected option:1, option:2, option:3 or option:4"):
        decided("option:7")


@pytest.mark.parametrize(
    ("option", "codec", "end", "label"),
    [
        (1, "jpeg80", None, "0:jpeg80"),
        (1, "png", None, "0:png"),
        (3, "jpeg80", POINTS, "0-4:jpeg80"),
    ],
)
def test_options_1_and_3_send_the_pair_in_the_codec_they_name(
    option: int, codec: str, end: int | None, label: str
) -> None:
    fleet = decided("static", {"option": option, "codec": codec})
    cli = decided(f"option:{option}:{codec}")
    for decision in (fleet, cli):
        assert (decision.action, decision.codec, decision.end) == (0, codec, end)
        assert decision.label == label and not decision.hedge


def test_without_a_codec_the_pair_crosses_raw() -> None:
    assert decided("static", {"option": 1}).codec == "raw"
    assert decided("option:3").codec == "raw"
    assert decided("option:1:raw").label == "0"


@pytest.mark.parametrize(
    ("spec", "params"),
    [
        ("option:1:jpg80", None),
        ("option:3:fp16", None),  # a codec, but not one an image crosses in
        ("static", {"option": 1, "codec": "jpeg101"}),
    ],
)
def test_an_unknown_pair_codec_is_one_line_listing_the_known_ones(
    spec: str, params: dict[str, Any] | None
) -> None:
    with pytest.raises(UserError) as caught:
        decided(spec, params)
    message = str(caught.value)
    assert "unknown codec for the camera pair" in message
    assert "known: raw, raw+zstd, jpeg<Q>, png" in message
    assert "\n" not in message


@pytest.mark.parametrize(
    ("spec", "params"),
    [("option:2:jpeg80", None), ("option:4:png", None), ("static", {"option": 2, "codec": "png"})],
)
def test_a_codec_is_refused_for_options_that_send_no_pair(
    spec: str, params: dict[str, Any] | None
) -> None:
    with pytest.raises(UserError, match="only options 1 and 3 send the camera pair"):
        decided(spec, params)


def test_malformed_option_specs_say_what_is_expected() -> None:
    with pytest.raises(UserError, match=r"needs a codec after the colon, e\.g\. option:1:jpeg80"):
        decided("option:1:")
    # The CLI form carries its codec in the spec, not in params.
    with pytest.raises(UserError, match=r"option:1 params: codec: unknown key"):
        decided("option:1", {"codec": "png"})


def test_a_profile_without_the_pair_codec_names_the_codecs_it_has() -> None:
    with pytest.raises(
        UserError, match=r"no codec jpeg50 for the camera pair \(cut 0; it has raw, "
    ):
        decided("option:3:jpeg50")


def test_the_robot_measures_the_option_codec_at_the_pair_cut() -> None:
    """The calibration keeps the named codec as an action, else the policy could not be built."""
    assert required_codecs("option:1:jpeg80", 0) == {0: ["jpeg80"]}
    assert required_codecs("static", 0, {"option": 3, "codec": "png"}) == {0: ["png"]}
    assert required_codecs("option:3", 0) == {}
    assert required_codecs("static", 0, {"option": 4}) == {}
    assert required_codecs("static:2:int8", 0) == {2: ["int8"]}  # the baselines' form, unchanged
    assert nav_option("elastic", {"beta": 1.0}) is None


def test_a_model_without_the_named_cut_is_refused_for_every_option() -> None:
    for option in (1, 2, 3, 4):
        with pytest.raises(UserError, match=r"names its 'points' cut \(zoo:stereo does\); this"):
            decided(f"option:{option}", named_cuts={})


def test_option_3_without_the_segment_says_how_to_get_it() -> None:
    with pytest.raises(UserError, match=r"set `cuts: \{segments: true\}` in the fleet file"):
        decided("option:3", segments=[])


def test_a_segment_is_after_its_cut_and_never_hedged() -> None:
    with pytest.raises(ValueError, match="ends after its cut"):
        Decision(2, end=2)
    with pytest.raises(ValueError, match="ends after its cut"):
        Decision(PURE_ROBOT, end=3)
    with pytest.raises(ValueError, match="not hedged"):
        Decision(0, end=3, hedge=True)


def test_a_segment_row_has_its_own_key_in_the_learners_lookups() -> None:
    table = CutTable.from_profile(nav_profile()).with_segment(0, POINTS)
    assert table.labels[-2:] == ("0-4", "P")
    assert table.position(0, end=POINTS) == table.size - 1
    assert table.positions()[(0, "raw", None)] == 0  # the cut
    assert table.positions()[(0, "raw", POINTS)] == table.size - 1  # the segment
    # The robot's part is the prefix and the tail; the cloud's, what lies between; the reply
    # brings the end cut's tensors back.
    assert table.prefix_s[-1] == pytest.approx(0.008)
    assert table.tails[-1] == pytest.approx(0.008)
    assert table.cloud_s[-1] == pytest.approx(0.092)
    assert table.returns[-1] == 900 and table.returns[0] == table.output_bytes
    kept = table.subset([table.size - 1])
    assert kept.ends == (POINTS,) and kept.returns == (900,) and kept.tails == table.tails[-1:]


def test_telemetry_labels_name_the_segment_and_old_readers_get_its_cut() -> None:
    assert action_label(0, "raw", 4) == "cut:0-4"
    assert action_label(0, "jpeg80", 4) == "cut:0-4:jpeg80"
    assert parse_action_segment("cut:0-4:jpeg80") == (0, 4, "jpeg80")
    assert parse_action_codec("cut:0-4") == (0, "raw")
    for bad in ("cut:4-0", "cut:0-", "cut:0-4:", "cut:a-1"):
        with pytest.raises(ValueError, match="not an action label"):
            parse_action_segment(bad)


def request(**changes: Any) -> InferRequest:
    fields: dict[str, Any] = {
        "robot": "robot-1",
        "frame": 3,
        "model_digest": "d" * 64,
        "cut": 0,
        "tensors": {"left": EncodedTensor.raw(np.zeros((1, 2, 2, 3), np.uint8))},
        "deadline_s": 1.0,
        "sent_at": 1.0,
    }
    fields.update(changes)
    return InferRequest(**fields)


def test_the_end_cut_round_trips_and_is_after_the_cut() -> None:
    assert InferRequest.from_wire(request(end_cut=4).to_wire()).end_cut == 4
    assert InferRequest.from_wire(request().to_wire()).end_cut is None
    with pytest.raises(InvalidValue, match=r"infer_request.end_cut: must be after the cut \(2\)"):
        request(cut=2, end_cut=2)


def test_a_request_from_an_older_robot_runs_to_the_end() -> None:
    """Regression guard: a request without the field (an older robot) decodes as before."""
    body = {"v": 2, "t": "infer_request", **request().to_map()}
    del body["end_cut"]
    decoded = decode(encode_raw(body))
    assert isinstance(decoded, InferRequest) and decoded.end_cut is None
