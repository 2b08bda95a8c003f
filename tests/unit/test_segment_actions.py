"""Segments among elastic's actions (fleet `cuts.segments`): one action per segment and codec of
its start cut, looked up by (cut, codec, end) so a segment's outcome is learned under its own
column, never hedged, a fourth context feature (MB returned) only when segments are present, left
out of the dominance pruning, the simulator's downlink carrying the segment's reply, and elastic
converging to a segment where it is the best action."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from common.errors import UserError
from robotd.policies import PURE_ROBOT, Decision, Outcome, make_policy
from robotd.policies.base import CutTable
from robotd.policies.elastic import ElasticPolicy
from robotd.policies.objective import Objective
from robotd.policies.segment_actions import action_contexts, actions_table
from robotd.sim.simulator import Simulator, segment_costs
from robotd.sim.trace import Segment, trace_from_dict

DECISION_COST = Path(__file__).resolve().parents[2] / "benchmarks" / "decision_cost.py"
POINTS = 4
POINTS_BYTES = 921_600  # 320×240×3 float32: zoo:stereo's points at 320×240
PAIR_BYTES = 460_800
D_COLL_BYTES = 164
TAIL_MS = 8.0  # the d_coll stage, from the points


def stereo_profile(segments: list[list[int]] | None = None) -> dict[str, Any]:
    """zoo:stereo's cuts at 320×240 (docs/navigation.md) on a 100 ms model, the pair also as
    JPEG, and the segment cut 0 → points (option 3) unless `segments` says otherwise."""
    profile: dict[str, Any] = {
        "full_ms": 100.0,
        "output_bytes": D_COLL_BYTES,
        "cuts": [
            {
                "index": 0,
                "bytes": PAIR_BYTES,
                "prefix_ms": 0.0,
                "suffix_ms": 100.0,
                "codecs": [
                    {"name": "raw", "bytes": PAIR_BYTES},
                    {"name": "jpeg50", "bytes": 20_000, "encode_ms": 1.0, "decode_ms": 1.0},
                ],
            },
            {"index": 1, "bytes": 153_600, "prefix_ms": 1.0, "suffix_ms": 99.0},
            {"index": 2, "bytes": 1_228_800, "prefix_ms": 3.0, "suffix_ms": 97.0},
            {"index": 3, "bytes": 307_200, "prefix_ms": 88.0, "suffix_ms": 12.0},
            {"index": POINTS, "bytes": POINTS_BYTES, "prefix_ms": 92.0, "suffix_ms": TAIL_MS},
        ],
        "named_cuts": {"points": POINTS},
        "segments": [[0, POINTS]] if segments is None else segments,
    }
    return profile


def elastic(profile: dict[str, Any], **params: Any) -> ElasticPolicy:
    policy = make_policy("elastic", profile, params)
    assert isinstance(policy, ElasticPolicy)
    return policy


def test_every_segment_is_an_action_once_per_codec_of_its_start_cut() -> None:
    table = actions_table(stereo_profile([[0, POINTS], [1, 3]]))
    assert table.labels[-4:] == ("0-4", "0-4:jpeg50", "1-3", PURE_ROBOT)
    assert table.position(0, "jpeg50", POINTS) == table.size - 2
    jpeg = table.position(0, "jpeg50")
    seg = table.position(0, "jpeg50", POINTS)
    # The segment sends what its start cut sends and brings back its end cut's tensors.
    assert table.bytes[seg] == table.bytes[jpeg] == 20_000
    assert table.returns[seg] == POINTS_BYTES and table.returns[jpeg] == D_COLL_BYTES
    assert table.tails[seg] == pytest.approx(TAIL_MS / 1000) and table.tails[jpeg] == 0.0
    # Adding the same segments again adds nothing.
    assert table.with_segments([[0, POINTS]]).labels == table.labels
    assert (
        actions_table(stereo_profile(), segments=False).labels
        == CutTable.from_profile(stereo_profile()).labels
    )


@pytest.mark.parametrize("bad", [[[0, 9]], [[3, 1]], [[0]], [["0", 4]]])
def test_a_malformed_segment_list_is_one_named_error(bad: list[Any]) -> None:
    with pytest.raises(UserError, match="segment"):
        actions_table(stereo_profile(bad))


def test_mb_returned_is_a_feature_only_when_segments_are_present() -> None:
    plain = CutTable.from_profile(stereo_profile())
    assert action_contexts(plain).shape == (plain.size, 3)
    table = actions_table(stereo_profile())
    contexts = action_contexts(table)
    assert contexts.shape == (table.size, 4)
    np.testing.assert_allclose(contexts[:, :3][: plain.size], action_contexts(plain))
    np.testing.assert_allclose(contexts[:, 3], table.returned_bytes / 1e6)
    # elastic takes the split's segments unless told not to; ans keeps whole suffixes.
    learner = elastic(stereo_profile())
    assert learner.contexts.shape[1] == 4 and learner.cuts.has_segments
    without = elastic(stereo_profile(), segments=False, prune_dominated=False)
    assert without.contexts.shape == (plain.size, 3) and without.cuts.labels == plain.labels
    ans = make_policy("ans", stereo_profile(), {"prune_dominated": False})
    assert ans.cuts.labels == plain.labels


def test_segments_stand_outside_the_dominance_pruning() -> None:
    plain = CutTable.from_profile(stereo_profile()).undominated(0.05)
    table = actions_table(stereo_profile([[0, POINTS], [0, 3], [1, POINTS]])).undominated(0.05)
    whole = tuple(label for label in table.labels if "-" not in label)
    # The same whole suffixes stay with or without segments, and every segment stays.
    assert whole == plain.labels
    assert [label for label in table.labels if "-" in label] == [
        "0-4", "0-4:jpeg50", "0-3", "0-3:jpeg50", "1-4",
    ]  # fmt: skip


def test_a_segment_outcome_is_learned_under_the_segments_column() -> None:
    policy = elastic(stereo_profile(), prune_dominated=False, change_detection=False)
    before = policy.learned_bytes()
    # A segment frame whose pair happened to code small: only the segment's bytes move.
    segment = Decision(0, codec="jpeg50", end=POINTS)
    policy.observe(
        segment, Outcome(prefix_s=0.01, cloud_s=0.2, cloud_compute_s=0.05, bytes_up=5_000)
    )
    after = policy.learned_bytes()
    assert after["0-4:jpeg50"] < before["0-4:jpeg50"]
    assert after["0:jpeg50"] == before["0:jpeg50"]
    # The cut and its segment answer in different times: each prediction follows its own.
    cut = Decision(0, codec="jpeg50")
    for _ in range(200):
        policy.observe(cut, Outcome(prefix_s=0.001, cloud_s=0.05, bytes_up=20_000))
        policy.observe(segment, Outcome(prefix_s=0.01, cloud_s=0.2, bytes_up=20_000))
    predicted = policy.predicted_cloud_cost()
    assert predicted["0:jpeg50"] == pytest.approx(0.05, rel=0.1)
    assert predicted["0-4:jpeg50"] == pytest.approx(0.2, rel=0.1)


def test_a_failed_segment_times_the_robot_without_its_tail() -> None:
    # A reply that never came leaves the robot's part at the start cut's prefix (no tail ran):
    # timed against the tail as well, the robot would look faster than it is.
    policy = elastic(stereo_profile([[3, POINTS]]), prune_dominated=False)
    ratio = policy.state()["robot_speed_ratio"]
    for _ in range(5):
        policy.observe(
            Decision(3, end=POINTS),
            Outcome(prefix_s=0.088, bytes_up=307_200, local_s=0.012, waited_s=1.0),
        )
    assert policy.state()["robot_speed_ratio"] == pytest.approx(ratio)


def tail_slow_table(tail_factor: float) -> CutTable:
    """The stereo table as a cloud sees it whose accelerator runs the d_coll stage
    `tail_factor` times slower than the profiling host (its share of every whole suffix),
    with the segment 0 → points (which leaves that stage to the robot)."""
    table = CutTable.from_profile(stereo_profile())
    cloud = table.cloud_s + (tail_factor - 1.0) * TAIL_MS / 1000
    return dataclasses.replace(table, cloud_s=cloud).with_segments([[0, POINTS]])


def run_trace(table: CutTable, downlink_mbit: float, frames: int = 3000) -> Any:
    trace = trace_from_dict(
        {
            "frames_per_second": 10,
            "segments": [
                {
                    "frames": frames,
                    "uplink_mbit": 100,
                    "downlink_mbit": downlink_mbit,
                    "rtt_ms": 5,
                    "robot_cpu": 1,
                    "cloud_speedup": 10,
                }
            ],
            "noise": {"jitter": 0.1},
        }
    )
    return Simulator(table, trace, seed=3)


def test_the_simulators_downlink_carries_the_segments_reply() -> None:
    table = tail_slow_table(1.0)
    seg = Segment(
        frames=10, uplink_mbit=100, downlink_mbit=10, rtt_ms=0, robot_cpu=1, cloud_speedup=1
    )
    costs = segment_costs(table, seg, Objective(), None)
    column = table.position(0, "raw", POINTS)
    assert costs.downlink_s[column] == pytest.approx(POINTS_BYTES * 8 / 10e6)
    assert costs.downlink_s[0] == pytest.approx(D_COLL_BYTES * 8 / 10e6)
    # Robot: the tail after the reply; cloud: the stereo stages; the points come back.
    expected = TAIL_MS / 1000 + PAIR_BYTES * 8 / 100e6 + 0.092 + POINTS_BYTES * 8 / 10e6
    assert costs.latency_plain[column] == pytest.approx(expected)
    # Past a deadline the frame is finished from cut 0 (the whole model), without the tail.
    late = segment_costs(table, seg, Objective(), 0.5)
    assert late.latency_plain[column] == pytest.approx(0.5 + 0.1)
    assert late.hedged[column] == late.plain[column]  # never hedged


def test_elastic_converges_to_the_segment_where_it_is_best() -> None:
    # A cloud 40x slow at the d_coll stage (5x slower than the robot there) and a 1 Gbit/s
    # downlink: option 3 beats option 1 by a fifth, P and option 2 by more.
    sim = run_trace(tail_slow_table(40.0), downlink_mbit=1000)
    table = sim.cuts
    segment = table.position(0, "jpeg50", POINTS)
    assert table.labels[sim.segments[0].oracle] == "0-4:jpeg50"
    result = sim.run("elastic")
    last = result.column[-500:]
    assert np.mean(last == segment) >= 0.9
    assert result.summary()["ratio_to_oracle"] <= 1.10
    # Never hedged, also on the exploring frames that chose a segment.
    segments = np.array([e is not None for e in (*table.ends, None)])
    assert not result.hedged[segments[result.column]].any()


def test_elastic_leaves_the_segment_where_the_cloud_is_faster() -> None:
    # The profiled cloud (10x the robot at every stage) and a 100 Mbit/s downlink: the points
    # coming back make option 3 the worse of the two cloud options, as measured on the testbed.
    sim = run_trace(tail_slow_table(1.0), downlink_mbit=100)
    table = sim.cuts
    segments = np.array([e is not None for e in (*table.ends, None)])
    assert not segments[sim.segments[0].oracle]
    result = sim.run("elastic")
    assert np.mean(segments[result.column[-500:]]) <= 0.05
    assert result.summary()["ratio_to_oracle"] <= 1.10
    assert not result.hedged[segments[result.column]].any()


def _decision_cost() -> ModuleType:
    """benchmarks/decision_cost.py, loaded from its file (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location("decision_cost", DECISION_COST)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_decision_cost_benchmark_runs_the_stereo_sized_action_set() -> None:
    # zoo:stereo's largest action set: 5 cuts x 4 codecs and the 10 segments in their start
    # cut's codecs; the incremental and the inverting learner decide alike on every frame.
    report = _decision_cost().run(frames=300, cuts=5, seed=0, uplink_mbit=200.0, segments=True)
    assert report["actions"] == 5 * 4 + 10 * 4 + 1 and report["features"] == 4
    assert report["mismatched_decisions"] == 0
    assert report["fast"]["decide_median_us"] > 0
