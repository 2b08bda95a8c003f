"""The demo's per-phase summary and the `--compare` verdict (deploy/demo_summary.py), on
telemetry records built here: frames are placed in phases by number, the main action is the
most frequent one, bytes are per frame, and the verdict names the fastest run and whether the
first policy chose like the fastest fixed one."""

from __future__ import annotations

from typing import Any

import pytest

from deploy.demo_summary import (
    action_kind,
    answered_since,
    compare_verdict,
    summarize,
    summarize_phases,
)
from robotd.emulation import Phase

PHASES = (Phase("good", 0, 4, 20.0, 3.0), Phase("bad", 4, 4, 0.2, 3.0))


def rec(frame: int, action: str, latency_s: float, **extra: Any) -> dict[str, Any]:
    offloaded = action != "P"
    return {
        "frame": frame,
        "action": action,
        "latency_s": latency_s,
        "bytes_up": extra.pop("bytes_up", 1000 if offloaded else 0),
        "deployment": extra.pop("deployment", "edge-1" if offloaded else None),
        "fallback": extra.pop("fallback", False),
        **extra,
    }


def test_answered_since_wants_the_deployment_the_frame_and_the_instant() -> None:
    answered = answered_since("edge-2", from_frame=3, after=100.0)
    assert answered(rec(3, "cut:0", 0.04, deployment="edge-2", at=100.0))
    assert not answered(rec(3, "cut:0", 0.04, deployment="edge-1", at=100.0))
    assert not answered(rec(2, "cut:0", 0.04, deployment="edge-2", at=100.0))
    assert not answered(rec(3, "cut:0", 0.04, deployment="edge-2", at=99.9))
    assert not answered(rec(3, "cut:0", 0.04, deployment="edge-2", at=100.0, fallback=True))


def test_phase_rows_place_frames_by_number_and_pick_the_main_action() -> None:
    records = [
        rec(0, "cut:0:jpeg50", 0.04),
        rec(1, "cut:0:jpeg50", 0.06),
        rec(2, "P", 0.10),
        rec(3, "cut:0:jpeg50", 0.05, bytes_up=3000),
        rec(4, "cut:0:jpeg50", 0.30, fallback=True, reason="timeout"),
        rec(5, "P", 0.12),
        rec(6, "P", 0.11),
        # frame 7 is missing (lost): the phase row averages what it has
        rec(5, "cut:0:raw", 9.0),  # a duplicate record of frame 5 is ignored
    ]
    good, bad = summarize_phases(records, PHASES)
    assert good["name"] == "good" and good["uplink_mbit"] == 20.0 and good["slowdown"] == 3.0
    assert good["main_action"] == "cut:0:jpeg50" and good["main_share"] == 0.75
    assert good["actions"] == {"cut:0:jpeg50": 3, "P": 1}
    assert good["mean_latency_s"] == pytest.approx(0.0625)
    assert good["bytes_up"] == round((1000 + 1000 + 0 + 3000) / 4)
    assert good["fallbacks"] == 0
    assert bad["main_action"] == "P" and bad["main_share"] == pytest.approx(0.667, abs=1e-3)
    assert bad["mean_latency_s"] == pytest.approx((0.30 + 0.12 + 0.11) / 3, abs=1e-6)
    assert bad["p95_latency_s"] == pytest.approx(0.282, abs=1e-6)
    assert bad["fallbacks"] == 1
    # The contract of --json's `phases`.
    contract = {
        "name",
        "uplink_mbit",
        "main_action",
        "mean_latency_s",
        "p95_latency_s",
        "bytes_up",
        "fallbacks",
    }
    assert contract <= set(good)


def test_a_phase_without_frames_has_no_figures() -> None:
    (row,) = summarize_phases([], PHASES[:1])
    assert row["main_action"] is None and row["mean_latency_s"] is None
    assert row["bytes_up"] is None and row["fallbacks"] == 0


def test_run_summary_counts_lost_frames_and_fallbacks() -> None:
    records = [rec(0, "P", 0.1), rec(1, "cut:0:jpeg50", 0.3, fallback=True, reason="busy")]
    summary, reasons = summarize(records, frames=3)
    assert summary["lost"] == 1 and summary["fallbacks"] == 1 and summary["answered"] == 0
    assert reasons == {"busy": 1}
    assert list(summary["actions"]) == ["cut:0:jpeg50", "P"]


@pytest.mark.parametrize(
    ("label", "kind"),
    [("P", "robot"), ("cut:0:jpeg80", "offload"), ("cut:0", "offload"), ("cut:7:int8", "cut:7")],
)
def test_action_kinds(label: str, kind: str) -> None:
    assert action_kind(label) == kind


def run(policy: str, *phases: tuple[str | None, float | None]) -> dict[str, Any]:
    return {
        "policy": policy,
        "phases": [
            {"name": f"p{i}", "main_action": action, "mean_latency_s": mean}
            for i, (action, mean) in enumerate(phases)
        ],
    }


def test_verdict_names_the_fastest_and_checks_the_learner_chose_like_it() -> None:
    runs = [
        run("elastic", ("cut:0:jpeg50", 0.050), ("P", 0.130), ("cut:0:jpeg50", 0.20)),
        run("robot", ("P", 0.120), ("P", 0.120), ("P", 0.12)),
        run("cloud:jpeg80", ("cut:0:jpeg80", 0.055), ("cut:0:jpeg80", 0.40), ("cut:0:jpeg80", 0.1)),
    ]
    first, second, third = compare_verdict(runs)
    assert first["fastest"] == "elastic" and first["fastest_fixed"] == "cloud:jpeg80"
    assert first["agrees"] and first["near_best"]
    assert second["fastest"] == "robot" and second["agrees"] and second["near_best"]
    # Offloading when the cloud baseline is fastest is right, but 2x slower is not near the best.
    assert third["fastest"] == "cloud:jpeg80" and third["agrees"] and not third["near_best"]
    assert second["mean_latency_s"] == {"elastic": 0.13, "robot": 0.12, "cloud:jpeg80": 0.4}


def test_verdict_disagrees_when_the_learner_chose_the_slower_kind() -> None:
    runs = [
        run("elastic", ("cut:0:jpeg50", 0.30)),
        run("robot", ("P", 0.12)),
        run("cloud:jpeg80", ("cut:0:jpeg80", 0.40)),
    ]
    (verdict,) = compare_verdict(runs)
    assert verdict["fastest"] == "robot" and not verdict["agrees"] and not verdict["near_best"]


def test_a_middle_cut_that_beats_both_baselines_agrees() -> None:
    runs = [
        run("elastic", ("cut:7:int8", 0.09)),
        run("robot", ("P", 0.12)),
        run("cloud:jpeg80", ("cut:0:jpeg80", 0.15)),
    ]
    (verdict,) = compare_verdict(runs)
    assert verdict["fastest"] == "elastic" and verdict["agrees"]
