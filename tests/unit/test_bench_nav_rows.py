"""`bench nav`'s result rows from synthetic telemetry: the JSON contract's keys and the
Tables III-IV figures (update rate from completion times, t_o / t_p / t_c / t_f from the
record's transfer, cloud, prefix + tail and latency), and its option checks (`--t-dead` among
them)."""

from __future__ import annotations

import math

import pytest
from typer.testing import CliRunner

from common.cli import app
from common.errors import UserError
from experiments.fleet import POLICY_VARIANTS, PolicyVariant
from experiments.nav_rows import (
    DEFAULT_T_DEAD_S,
    NO_TIMING,
    ROW_KEYS,
    LoopFigures,
    check_t_dead,
    contract_row,
    parse_options,
    parse_resolutions,
    robot_policy,
    timing,
    update_hz,
)
from nav.shared_control import DEFAULT_DEADLINE_S

CONTRACT = {
    "option",
    "resolution",
    "update_hz",
    "t_o_s",
    "t_p_s",
    "t_c_s",
    "t_f_s",
    "collisions",
    "maneuvers",
    "lost",
}


def record(frame: int, at: float, **times: float) -> dict[str, object]:
    """A telemetry line of an option-3 frame: prefix on the robot, a segment in the cloud,
    the tail on the robot."""
    base = {"prefix_s": 0.0, "transfer_s": 0.0, "cloud_s": 0.0, "suffix_local_s": 0.0}
    base.update(times)
    latency = sum(base.values())
    return {"frame": frame, "at": at, "action": "cut:0-4", "latency_s": latency, **base}


def test_row_has_exactly_the_contract_keys_and_the_measured_means() -> None:
    window = [
        record(5, 10.0, prefix_s=0.01, transfer_s=0.20, cloud_s=0.30, suffix_local_s=0.05),
        record(6, 10.5, prefix_s=0.03, transfer_s=0.40, cloud_s=0.10, suffix_local_s=0.07),
        record(7, 11.0, prefix_s=0.02, transfer_s=0.30, cloud_s=0.20, suffix_local_s=0.06),
    ]
    figures = timing(window)
    row = contract_row(3, (640, 480), figures, LoopFigures(2, 70), lost=0)
    assert set(row) == CONTRACT and tuple(row) == ROW_KEYS
    assert row["option"] == 3 and row["resolution"] == "640x480"
    assert row["update_hz"] == pytest.approx(2.0)  # 3 frames completed over 1 s
    assert row["t_o_s"] == pytest.approx(0.30)
    assert row["t_p_s"] == pytest.approx(0.20)
    assert row["t_c_s"] == pytest.approx(0.02 + 0.06)  # the prefix and the tail
    assert row["t_f_s"] == pytest.approx(0.58)
    assert (row["collisions"], row["maneuvers"], row["lost"]) == (2, 70, 0)
    assert figures.frame_latencies_s == pytest.approx((0.56, 0.60, 0.58))


def test_assistant_off_and_options_not_driven_have_nulls_not_zeros() -> None:
    off = contract_row("off", (320, 240), NO_TIMING, LoopFigures(9, 14), lost=0)
    assert set(off) == CONTRACT
    assert [off[k] for k in ("update_hz", "t_o_s", "t_p_s", "t_c_s", "t_f_s")] == [None] * 5
    assert off["collisions"] == 9
    not_driven = contract_row(2, (320, 240), timing([record(0, 1.0, prefix_s=0.1)]), None, 1)
    assert not_driven["collisions"] is None and not_driven["maneuvers"] == 0
    assert not_driven["update_hz"] is None  # one frame gives no rate
    assert not_driven["lost"] == 1


def test_update_rate_ignores_record_order_and_needs_two_frames() -> None:
    assert update_hz([{"at": 3.0}, {"at": 1.0}, {"at": 2.0}]) == pytest.approx(1.0)
    assert update_hz([{"at": 1.0}]) is None
    assert update_hz([]) is None


def test_options_and_resolutions_parse_and_bad_ones_are_named() -> None:
    assert parse_options("1, 4,Elastic,off,1,elastic-segments") == [
        1, 4, "elastic", "off", "elastic-segments",
    ]  # fmt: skip
    assert parse_resolutions("320x240,640X480") == [(320, 240), (640, 480)]
    # `elastic` is the learner over whole suffixes (a bench variant: the fleet has segments),
    # `elastic-segments` the runtime's own elastic, with the segments among its actions.
    policies = [robot_policy(o) for o in (1, 3, "elastic", "elastic-segments")]
    assert policies == ["option:1", "option:3", "elastic-suffixes", "elastic"]
    assert POLICY_VARIANTS["elastic-suffixes"] == PolicyVariant("elastic", {"segments": False})
    with pytest.raises(UserError, match="unknown '5'"):
        parse_options("1,5")
    with pytest.raises(UserError, match="'640' is not WIDTHxHEIGHT"):
        parse_resolutions("640")
    with pytest.raises(UserError, match="outside"):
        parse_resolutions("16x12")
    with pytest.raises(ValueError, match="not run on the daemons"):
        robot_policy("off")


def test_t_dead_must_be_a_positive_finite_number_of_seconds() -> None:
    assert check_t_dead(3.0) == 3.0
    assert DEFAULT_T_DEAD_S == DEFAULT_DEADLINE_S  # the assistant's own unless asked
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(UserError, match=r"--t-dead .*: must be a positive number of seconds"):
            check_t_dead(bad)


@pytest.mark.parametrize("value", ["0", "-0.5", "nan", "inf"])
def test_a_bad_t_dead_is_one_line_before_anything_runs(value: str) -> None:
    """Checked before the root check, so anyone sees it, and without a traceback."""
    result = CliRunner().invoke(app, ["bench", "nav", "--t-dead", value])
    assert result.exit_code == 2, result.output
    assert f"--t-dead {value}: must be a positive number of seconds" in result.output
    assert "Traceback" not in result.output
