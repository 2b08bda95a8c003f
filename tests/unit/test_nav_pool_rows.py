"""`bench pool`'s rows from synthetic telemetry: the row's keys, the update rate and delays over
the measured window, who answered, fallbacks by reason, lost frames, the "each frame once" checks
against the cloud daemons' counts, the sizing rule p >= ceil(t_p / T_f), the kill run split at
the kill, and the option checks."""

from __future__ import annotations

from typing import Any

import pytest

from common.errors import UserError
from experiments.nav_pool_rows import (
    ROW_KEYS,
    KillEvent,
    PoolRun,
    duplicate_frames,
    kill_summary,
    p_needed,
    parse_computed,
    parse_sizes,
    pool_row,
    reference_t_p,
)
from experiments.nav_rows import parse_resolution


def record(
    frame: int,
    at: float,
    deployment: str | None,
    *,
    cloud_s: float = 0.4,
    reason: str | None = None,
) -> dict[str, Any]:
    """An option-1 frame: the pair sent, d_coll back from `deployment`, or finished on the robot
    (`reason`)."""
    fallback = reason is not None
    return {
        "frame": frame,
        "at": at,
        "action": "cut:0",
        "prefix_s": 0.0,
        "transfer_s": 0.05,
        "cloud_s": 0.0 if fallback else cloud_s,
        "suffix_local_s": 0.3 if fallback else 0.0,
        "latency_s": 0.35 if fallback else 0.05 + cloud_s,
        "deployment": None if fallback else deployment,
        "fallback": fallback,
        "reason": reason,
    }


def round_robin(frames: int, members: list[str], period_s: float) -> list[dict[str, Any]]:
    """Frame k answered by members[k % P], one completing every `period_s`."""
    return [record(k, 100.0 + k * period_s, members[k % len(members)]) for k in range(frames)]


def test_a_pool_row_has_its_keys_and_the_window_figures() -> None:
    records = round_robin(10, ["edge-1", "edge-2"], 0.25)
    run = PoolRun(
        pool_size=2,
        max_in_flight=2,
        frames=10,
        measure_from=2,
        records=records,
        pool=("edge-1", "edge-2"),
        served={"edge-1": 5, "edge-2": 5},
        computed={"edge-1": 5, "edge-2": 5},
    )
    row = pool_row(run, (320, 240), p_needed_ref=4)
    assert tuple(row) == ROW_KEYS
    assert row["pool_size"] == 2 and row["resolution"] == "320x240"
    assert row["pool"] == ["edge-1", "edge-2"]
    assert row["frames"] == 8  # frames 2..9
    assert row["update_hz"] == pytest.approx(4.0)  # 7 intervals of 0.25 s
    assert row["t_o_s"] == pytest.approx(0.05) and row["t_p_s"] == pytest.approx(0.4)
    assert row["t_c_s"] == pytest.approx(0.0) and row["t_f_s"] == pytest.approx(0.45)
    assert row["answered_by"] == {"edge-1": 4, "edge-2": 4}  # over the window
    assert row["fallbacks"] == {} and row["lost"] == 0 and row["duplicates"] == []
    # The daemons' counts cover the whole run: 10 frames offloaded, 10 answered.
    assert row["offloaded"] == 10 and row["served_sum"] == 10
    assert row["each_frame_once"] is True
    assert row["p_needed"] == 4


def test_a_frame_answered_twice_or_counted_apart_fails_each_frame_once() -> None:
    records = round_robin(6, ["edge-1", "edge-2"], 0.25)
    twice = PoolRun(2, 2, 6, 0, [*records, record(3, 102.0, "edge-1")], served={})
    assert duplicate_frames(twice.records) == [3]
    assert pool_row(twice, (320, 240), None)["each_frame_once"] is False
    # edge-2 says it answered 4 frames for the robot; the robot saw 3 answered by it: one was
    # computed for nothing (a reply after the robot had finished the frame itself).
    extra = PoolRun(2, 2, 6, 0, records, served={"edge-1": 3, "edge-2": 4})
    row = pool_row(extra, (320, 240), None)
    assert row["each_frame_once"] is False and row["served_sum"] == 7


def test_fallbacks_by_reason_and_lost_frames() -> None:
    records = [
        record(0, 1.0, "edge-1"),
        record(1, 1.5, None, reason="timeout"),
        record(2, 2.0, None, reason="busy"),
        record(3, 2.5, None, reason="timeout"),
        record(5, 3.5, "edge-1"),  # frame 4 never reported
    ]
    row = pool_row(PoolRun(1, 1, 6, 0, records, served={"edge-1": 2}), (160, 120), None)
    assert row["fallbacks"] == {"busy": 1, "timeout": 2}
    assert row["answered_by"] == {"edge-1": 2}
    assert row["lost"] == 1
    # Every frame the daemon answered was used once; the robot finished the others itself.
    assert row["each_frame_once"] is True
    assert row["offloaded"] == 5 and row["served_sum"] == 2


def test_sizing_rule_rounds_up_from_the_smallest_pool_t_p() -> None:
    assert p_needed(0.2, 10.0) == 2  # exactly two periods, not three from float error
    assert p_needed(0.21, 10.0) == 3
    assert p_needed(0.05, 10.0) == 1  # faster than the camera: one deployment keeps up
    assert p_needed(None, 10.0) is None
    one = PoolRun(1, 1, 4, 0, [record(k, k * 0.5, "edge-1", cloud_s=0.36) for k in range(4)])
    two = PoolRun(2, 2, 4, 0, [record(k, k * 0.25, "edge-1", cloud_s=0.5) for k in range(4)])
    assert reference_t_p([two, one]) == pytest.approx(0.36)
    assert reference_t_p([]) is None


def test_kill_summary_splits_at_the_kill_and_leaves_the_dead_member_uncounted() -> None:
    # Pool edge-1, edge-2, cloud-1; cloud-1 killed at frame 9 (its frame 11 ends on the robot),
    # then cloud-2 (the standby) takes its turn.
    members = ["edge-1", "edge-2", "cloud-1"]
    records = [record(k, 10.0 + 0.2 * k, members[k % 3]) for k in range(9)]
    records.append(record(9, 12.0, "edge-1"))
    records.append(record(10, 12.2, "edge-2"))
    records.append(record(11, 13.0, None, reason="timeout"))
    records += [record(k, 13.0 + 0.2 * (k - 11), ["edge-1", "edge-2", "cloud-2"][k % 3])
                for k in range(12, 18)]  # fmt: skip
    served = {"edge-1": 6, "edge-2": 6, "cloud-1": None, "cloud-2": 2}
    run = PoolRun(3, 3, 18, 3, records, pool=members, served=served)
    event = KillEvent(
        primary="edge-1",
        killed="cloud-1",
        kill_frame=9,
        standby=("cloud-2",),
        pool_before=members,
        pool_after=["edge-1", "edge-2", "cloud-2"],
        repaired_after_s=1.5,
    )
    out = kill_summary(run, event)
    assert out["killed"] == "cloud-1" and out["killed_primary"] is False
    assert out["standby_joined"] is True
    assert out["lost"] == 0
    assert out["fallbacks"] == {"timeout": 1}
    assert out["answered_before"] == {"cloud-1": 2, "edge-1": 2, "edge-2": 2}  # frames 3..8
    assert out["answered_after"] == {"cloud-2": 2, "edge-1": 3, "edge-2": 3}
    assert out["update_hz_before"] == pytest.approx(5.0)
    # The killed member's count is unknown; the live ones match the telemetry.
    assert out["served_by_cloud"]["cloud-1"] is None
    assert out["each_frame_once"] is True


def test_a_route_that_kept_the_killed_member_is_no_repair() -> None:
    run = PoolRun(2, 2, 3, 0, round_robin(3, ["edge-1", "edge-2"], 0.3))
    event = KillEvent("edge-1", "edge-2", 1, ("cloud-1",), ["edge-1", "edge-2"],
                      ["edge-1", "edge-2", "cloud-1"], None)  # fmt: skip
    assert kill_summary(run, event)["standby_joined"] is False


def test_computed_requests_are_read_from_the_exit_summary() -> None:
    log = (
        "12:00:01 INFO cloudd.batch_runner: edge-1: first frame of robot-1 answered at epoch 1\n"
        "12:00:09 INFO cloudd.batch_stats: edge-1: 27 request(s) computed in 27 run(s) "
        "(mean batch 1.00, largest 1)\n"
    )
    assert parse_computed(log, "edge-1") == 27
    assert parse_computed(log, "edge-2") is None
    assert parse_computed("killed before its summary\n", "edge-1") is None


@pytest.mark.parametrize(
    ("text", "standby", "message"),
    [
        ("", True, "at least one pool size"),
        ("1,x", True, "'x' is not a pool size"),
        ("0", False, "'0' is not a pool size"),
        ("4", True, "--sizes 4: at most 3"),
        ("5", False, "--sizes 5: at most 4"),
    ],
)
def test_bad_sizes_are_one_line(text: str, standby: bool, message: str) -> None:
    with pytest.raises(UserError, match=message):
        parse_sizes(text, hosts=4, standby=standby)


def test_sizes_and_resolution_parse() -> None:
    assert parse_sizes("3, 1,2,1", hosts=4, standby=True) == [1, 2, 3]
    assert parse_sizes("4", hosts=4, standby=False) == [4]
    assert parse_resolution("160x120") == (160, 120)
    with pytest.raises(UserError, match="not WIDTHxHEIGHT"):
        parse_resolution("640")
    with pytest.raises(UserError, match="outside"):
        parse_resolution("16x12")
