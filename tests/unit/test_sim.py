"""The trace-driven simulator: cost model, bookkeeping, settling, traces and profiles."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from common.errors import UserError
from robotd.policies import Objective
from robotd.policies.base import CutTable
from robotd.sim.simulator import SimResult, Simulator, regret_slope, segment_costs, simulate
from robotd.sim.trace import Segment, load_profile, load_trace, trace_from_dict

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "tests" / "data" / "profiles"
TRACES = ROOT / "deploy" / "traces"

TINY = {
    "full_ms": 100.0,
    "cuts": [
        {"index": 0, "bytes": 1_000_000, "prefix_ms": 0.0, "suffix_ms": 100.0},
        {"index": 1, "bytes": 100_000, "prefix_ms": 50.0, "suffix_ms": 50.0},
        {"index": 2, "bytes": 1_000, "prefix_ms": 90.0, "suffix_ms": 10.0},
    ],
}
SEGMENT = {
    "frames": 300,
    "uplink_mbit": 8,
    "downlink_mbit": 8,
    "rtt_ms": 20,
    "robot_cpu": 0.5,
    "cloud_speedup": 10,
}


def tiny_trace(**extra: Any) -> dict[str, Any]:
    return {"frames_per_second": 10, "segments": [dict(SEGMENT)], **extra}


def test_segment_costs_match_a_hand_computation() -> None:
    cuts = CutTable.from_profile(TINY)
    costs = segment_costs(cuts, Segment(**SEGMENT), Objective(), None)  # type: ignore[arg-type]
    # Downlink of the 4096-byte result at 8 Mbit/s plus half the RTT: 0.004096 + 0.01 s.
    down = 0.014096
    # cut 0: 1 MB at 1 MB/s + 0.01, cloud 0.1/10; cut 1: prefix 0.05/0.5, 0.1 MB; cut 2: 0.09/0.5.
    expected = [1.01 + 0.01 + down, 0.1 + 0.11 + 0.005 + down, 0.18 + 0.011 + 0.001 + down, 0.2]
    np.testing.assert_allclose(costs.plain, expected)
    np.testing.assert_allclose(costs.latency_plain, expected)
    assert costs.oracle == 3  # P (0.2 s) beats cut 2 (0.206 s)
    # Hedged cut 2: 0.18 + min(y = 0.026, local suffix 0.02) = 0.2.
    assert costs.hedged[2] == pytest.approx(0.2)


def test_a_deadline_turns_a_slow_reply_into_a_local_finish() -> None:
    cuts = CutTable.from_profile(TINY)
    costs = segment_costs(cuts, Segment(**SEGMENT), Objective(), 0.5)  # type: ignore[arg-type]
    # cut 0's reply (1.03 s) misses the 0.5 s deadline: wait 0.5 s, then the whole model, 0.2 s.
    assert costs.latency_plain[0] == pytest.approx(0.7)
    assert costs.latency_plain[1] == pytest.approx(0.1 + 0.11 + 0.005 + 0.014096)


def test_oracle_run_has_no_regret_and_ratio_one() -> None:
    trace = trace_from_dict(tiny_trace(noise={"jitter": 0.1}))
    result = simulate(TINY, trace, "oracle", seed=1)
    summary = result.summary()
    assert summary["ratio_to_oracle"] == pytest.approx(1.0)
    assert summary["cumulative_regret"] == pytest.approx(0.0)
    assert summary["actions"] == {"P": 300}
    assert summary["segments"][0]["settle_frames"] == 0


def test_summary_has_exactly_the_contract_keys() -> None:
    trace = trace_from_dict(tiny_trace())
    summary = simulate(TINY, trace, "elastic").summary()
    assert set(summary) == {
        "policy",
        "frames",
        "mean_latency_s",
        "p95_latency_s",
        "oracle_mean_latency_s",
        "ratio_to_oracle",
        "cumulative_regret",
        "regret_curve",
        "segments",
        "actions",
        "decision_us_median",
    }
    assert set(summary["segments"][0]) == {
        "index",
        "mean_latency_s",
        "oracle_mean_latency_s",
        "settle_frames",
    }
    assert summary["frames"] == 300
    assert summary["regret_curve"][-1] == [300, summary["cumulative_regret"]]
    assert sum(summary["actions"].values()) == 300
    json.dumps(summary)  # plain JSON types only


def test_same_seed_same_run_other_seed_other_conditions() -> None:
    trace = trace_from_dict(tiny_trace(noise={"jitter": 0.05}))
    a = simulate(TINY, trace, "elastic", seed=7)
    b = simulate(TINY, trace, "elastic", seed=7)
    c = simulate(TINY, trace, "elastic", seed=8)
    np.testing.assert_array_equal(a.latency_s, b.latency_s)
    np.testing.assert_array_equal(a.column, b.column)
    assert not np.array_equal(a.latency_s, c.latency_s)


def test_policies_meet_the_same_conditions() -> None:
    trace = trace_from_dict(tiny_trace(noise={"jitter": 0.2}))
    sim = Simulator(CutTable.from_profile(TINY), trace, seed=3)
    robot = sim.run("robot")
    oracle = sim.run("oracle")  # also always P here
    np.testing.assert_array_equal(robot.latency_s, oracle.latency_s)
    np.testing.assert_array_equal(robot.latency_s, robot.oracle_latency_s)
    # Mean-one jitter: the realized mean sits near the expected 0.2 s.
    assert robot.latency_s.mean() == pytest.approx(0.2, rel=0.05)


def result_from(served: list[float], oracle: list[float], starts: list[int]) -> SimResult:
    n = len(served)
    return SimResult(
        policy="test",
        frames_per_second=10,
        segment_starts=starts,
        segment_names=[None] * len(starts),
        actions=("0", "P"),
        column=np.zeros(n, dtype=np.int64),
        hedged=np.zeros(n, dtype=bool),
        latency_s=np.array(served),
        served_cost=np.array(served),
        oracle_cost=np.array(oracle),
        oracle_latency_s=np.array(oracle),
        decision_ns=np.ones(n, dtype=np.int64),
    )


def test_settle_frames_follow_the_definition() -> None:
    # Segment 0: bad for 7 frames, then good except two scattered misses (still >= 18/20).
    good = [False] * 7 + [True] * 93
    good[12] = good[20] = False
    # Segment 1: 5% worse counts as good, 6% does not; it never gets a good window.
    served = [1.0 if g else 2.0 for g in good] + [1.05, 1.06] * 50
    result = result_from(served, [1.0] * 200, [0, 100])
    assert result.settle_frames() == [7, None]
    # A segment shorter than the window cannot settle.
    assert result_from([1.0] * 10, [1.0] * 10, [0]).settle_frames() == [None]


def test_regret_slope_tells_linear_from_bounded_regret() -> None:
    frames = 20_000
    linear = result_from([1.1] * frames, [1.0] * frames, [0])
    assert regret_slope(linear) == pytest.approx(1.0, abs=1e-6)
    early = result_from([2.0] * 300 + [1.0] * (frames - 300), [1.0] * frames, [0])
    assert regret_slope(early) == pytest.approx(0.0, abs=1e-9)
    sqrt_like = np.concatenate([[0.0], np.diff(np.sqrt(np.arange(1, frames + 1)))]) + 1.0
    assert regret_slope(result_from(list(sqrt_like), [1.0] * frames, [0])) == pytest.approx(
        0.5, abs=0.02
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("frames_per_second: 10\n", "segments"),
        ("segments: [{frames: 1}]\n", "frames_per_second"),
        (
            "frames_per_second: 10\nsegments:\n  - {frames: 10, uplink_mbit: -1, downlink_mbit: 5,"
            " rtt_ms: 1, robot_cpu: 1, cloud_speedup: 1}\n",
            r"segments\[0\]\.uplink_mbit",
        ),
        (
            "frames_per_second: 10\nsegments:\n  - {frames: 0, uplink_mbit: 1, downlink_mbit: 5,"
            " rtt_ms: 1, robot_cpu: 1, cloud_speedup: 1}\n",
            r"segments\[0\]\.frames",
        ),
        (
            "frames_per_second: 10\nsegments:\n  - {frames: 5, uplink_mbit: 1, downlink_mbit: 5,"
            " rtt_ms: 1, robot_cpu: 1, cloud_speedup: 1, uplnk: 3}\n",
            "uplnk",
        ),
        ("frames_per_second: 10\nsegments: []\n", "segments"),
        ("frames_per_second: 10\nnoise: {jitter: 2}\nsegments: []\n", "jitter"),
        ("[1, 2]\n", "expected a mapping"),
        ("frames_per_second: [\n", "invalid YAML"),
        ("frames_per_second: 10\nframes_per_second: 5\n", "duplicate key 'frames_per_second'"),
    ],
)
def test_malformed_traces_are_one_line_naming_the_field(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(UserError, match=message) as info:
        load_trace(path)
    assert "\n" not in str(info.value)
    assert str(path) in str(info.value)


def test_missing_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="no such file"):
        load_trace(tmp_path / "nope.yaml")
    with pytest.raises(UserError, match="no such file"):
        load_profile(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        load_profile(bad)


def test_shipped_traces_and_profiles_load() -> None:
    names = sorted(p.stem for p in TRACES.glob("*.yaml"))
    assert names == [
        "bandwidth-recovery",
        "cpu-drop",
        "demo-phases",
        "glitch-10-1",
        "glitch-10-3",
        "glitch-5-1",
        "stationary",
    ]
    for path in TRACES.glob("*.yaml"):
        trace, _ = load_trace(path)
        # demo-phases is `elasticfog demo`'s script, as short as the demo's phases.
        assert trace.total_frames >= (270 if path.stem == "demo-phases" else 2000)
        assert trace.noise.jitter > 0
    for path in PROFILES.glob("*.json"):
        cuts, _ = load_profile(path)
        assert cuts.size == 16
        assert cuts.indices[0] == 0


def test_entropy_can_come_from_a_video(tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    assert writer.isOpened()
    rng = np.random.default_rng(0)
    for i in range(4):
        frame = np.full((48, 64, 3), 40 * i, dtype=np.uint8)
        if i % 2:
            frame = rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
        writer.write(frame)
    writer.release()
    trace = trace_from_dict(tiny_trace(entropy={"kind": "video", "path": "clip.avi"}))
    sim = Simulator(CutTable.from_profile(TINY), trace, trace_dir=tmp_path)
    # Flat frames score ~0, noisy ones high; the four frames loop over the whole trace.
    assert sim.entropy[0] < 0.2 < 0.6 < sim.entropy[1]
    np.testing.assert_allclose(sim.entropy[4:8], sim.entropy[0:4])
    missing = trace_from_dict(tiny_trace(entropy={"kind": "video", "path": "gone.avi"}))
    with pytest.raises(UserError, match="cannot open"):
        Simulator(CutTable.from_profile(TINY), missing, trace_dir=tmp_path)


def test_timeouts_send_elastic_back_to_the_robot() -> None:
    # Every reply misses the deadline: elastic learns offloading costs the deadline and stays home.
    trace = trace_from_dict(
        {
            "frames_per_second": 10,
            "deadline_ms": 300,
            "segments": [dict(SEGMENT, uplink_mbit=0.05, frames=600)],
        }
    )
    result = simulate(TINY, trace, "elastic")
    last = result.column[-200:]
    assert (last == 3).mean() > 0.75  # P, apart from forced samples
    # The forced samples still go out, hedged, so they are served by the local path.
    assert result.hedged[-200:][last != 3].all()
    assert result.latency_s[-200:].mean() < 1.05 * 0.2
    assert result.summary()["segments"][0]["settle_frames"] is not None
