"""e2e across real network stacks: the daemons in the namespace testbed, with real link caps,
CPU quotas, a pulled cable and SIGKILLed hosts (root only).

Every test brings up a testbed of its own (`experiments.runner.TestbedFleet`): the
registry and its router on `registry`, cloud daemons on `edge-1`/`edge-2`, the robot on `robot`,
an observer on `bench`; peers with gossip, shared memory off, endpoints only. Conditions change
while the robot streams; what is asserted comes from the robot's own telemetry file and from the
kernel's interface counters. At the end of every test the testbed must be gone: no namespace,
`/etc/netns` entry, cgroup or process left (checked by the `fleet` fixture).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from experiments.fleet import FleetSpec
from experiments.runner import TestbedFleet
from experiments.stats import between, by_frame
from tests.e2e.conftest import (
    TEST_INPUT_SHAPE,
    TEST_MODEL,
    processes_under,
    remains_of_testbed,
)
from tests.helpers.gates import root_only

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.netns,
    root_only,
]

HOSTS = ("registry", "robot", "edge-1", "edge-2", "bench")
WAIT_S = 30.0
"""Bound of a wait for a frame the robot should report within seconds."""
RUN_S = 45.0
"""Bound of a whole robot run in a test."""
INPUT_BYTES = 3 * 64 * 64
"""A raw uint8 camera frame of TEST_INPUT_SHAPE: what a full offload sends uncoded."""
BIG_INPUT_SHAPE = [3, 120, 160]
BIG_INPUT_BYTES = 3 * 120 * 160
NO_HEDGE = {"hedge": False, "robot_probe_frames": 0}


_COUNTER = iter(range(1_000_000))


@pytest.fixture
def fleet(tmp_path: Path, e2e_cache: Path, request: pytest.FixtureRequest) -> Iterator[Any]:
    """`fleet(**spec)` -> a TestbedFleet with registry and clouds launched; always torn down,
    then checked to have left nothing behind. A failing test gets the daemons' logs."""
    opened: list[TestbedFleet] = []
    request.node._ef_fleets = opened  # read by conftest's pytest_runtest_makereport

    def launch(**spec: Any) -> TestbedFleet:
        name = f"mh{os.getpid() % 100000}-{next(_COUNTER)}"
        tf = TestbedFleet(tmp_path / name, name=name, hosts=HOSTS, startup_timeout_s=60.0)
        tf.__enter__()
        opened.append(tf)
        settings: dict[str, Any] = {
            "fleet": tf.next_fleet_name("e"),
            "model": TEST_MODEL,
            "input_shape": TEST_INPUT_SHAPE,
            **spec,
        }
        tf.launch(FleetSpec(**settings))
        return tf

    try:
        yield launch
    finally:
        for tf in opened:
            tf.close()
        for tf in opened:
            assert not remains_of_testbed(tf.testbed.name), remains_of_testbed(tf.testbed.name)
        assert not processes_under(tmp_path), "processes left behind"


def _assert_no_frame_lost(records: list[dict[str, Any]], frames: int) -> None:
    seen = sorted(int(r["frame"]) for r in records)
    missing = sorted(set(range(frames)) - set(seen))
    assert not missing, f"frames without telemetry (lost): {missing[:20]}"
    assert len(seen) == len(set(seen)) == frames, "a frame reported twice"


def _answered_by(rec: dict[str, Any]) -> str | None:
    return None if rec.get("fallback") or not rec.get("deployment") else str(rec["deployment"])


def test_sigkill_of_the_serving_host_fails_over_without_losing_a_frame(
    fleet: Callable[..., TestbedFleet],
) -> None:
    tf = fleet(clouds=("edge-1", "edge-2"), deadline_s=0.6, lease_ms=1000)
    frames, kill_at = 60, 15
    robot = tf.start_robot("cloud", frames=frames, fps=20.0)
    tf.follower.wait_for(
        lambda r: r["frame"] >= kill_at and _answered_by(r) == "edge-1",
        timeout_s=WAIT_S,
        what=f"a frame >= {kill_at} answered by edge-1",
        procs=[robot],
    )
    killed = tf.tb.kill("edge-1")
    killed_frame = tf.follower.last_frame() + 1
    assert killed, "nothing was running on edge-1"
    records = by_frame(tf.finish_robot(RUN_S))
    _assert_no_frame_lost(records, frames)
    after = between(records, killed_frame)
    firsts = [r["frame"] for r in after if _answered_by(r) == "edge-2"]
    print(
        f"edge-1 killed at frame {killed_frame}: first answer by edge-2 at frame "
        f"{firsts[0] if firsts else None}; fallbacks {sum(1 for r in after if r['fallback'])}"
    )
    assert firsts, "no frame answered by edge-2 after edge-1 died"
    assert all(_answered_by(r) == "edge-2" for r in after[-10:])


def test_registry_killed_data_keeps_flowing_and_never_crossed_it(
    fleet: Callable[..., TestbedFleet],
) -> None:
    """While the robot offloads every frame, the registry's link carries a tiny share of what the
    robot sends (peers talk directly); then the registry host is killed and frames go on."""
    tf = fleet(deadline_s=0.6)
    frames, count_from, kill_at = 60, 8, 30
    robot = tf.start_robot("cloud", frames=frames, fps=20.0)
    tf.follower.wait_frame(count_from, timeout_s=WAIT_S, procs=[robot])
    before = {h: tf.tb.counters(h) for h in ("registry", "robot")}
    tf.follower.wait_frame(kill_at, timeout_s=WAIT_S, procs=[robot])
    after = {h: tf.tb.counters(h) for h in ("registry", "robot")}
    assert tf.tb.kill("registry"), "nothing was running on the registry host"
    killed_frame = tf.follower.last_frame() + 1
    records = by_frame(tf.finish_robot(RUN_S))
    _assert_no_frame_lost(records, frames)

    robot_tx = after["robot"]["tx_bytes"] - before["robot"]["tx_bytes"]
    registry = sum(after["registry"][k] - before["registry"][k] for k in ("rx_bytes", "tx_bytes"))
    rest = between(records, killed_frame)
    served = [r for r in rest if _answered_by(r) == "edge-1"]
    print(
        f"robot sent {robot_tx} B, the registry's link carried {registry} B "
        f"({100 * registry / max(1, robot_tx):.2f}%); after the kill {len(served)}/{len(rest)} "
        f"frames answered by edge-1"
    )
    assert robot_tx >= (kill_at - count_from - 2) * INPUT_BYTES
    assert registry < 0.05 * robot_tx
    assert len(served) >= 0.9 * len(rest), "frames stopped flowing when the registry died"


def test_cut_link_to_the_deployment_falls_back_locally_then_reroutes(
    fleet: Callable[..., TestbedFleet],
) -> None:
    """edge-1's cable is pulled (its bridge port goes down): the robot's requests time out and it
    finishes those frames itself, then the registry moves it to edge-2. No frame is lost."""
    tf = fleet(clouds=("edge-1", "edge-2"), deadline_s=0.5, lease_ms=1000)
    frames, cut_at = 80, 15
    robot = tf.start_robot("cloud", frames=frames, fps=20.0)
    tf.follower.wait_for(
        lambda r: r["frame"] >= cut_at and _answered_by(r) == "edge-1",
        timeout_s=WAIT_S,
        what=f"a frame >= {cut_at} answered by edge-1",
        procs=[robot],
    )
    tf.tb.link("edge-1", up=False)
    cut_frame = tf.follower.last_frame() + 1
    rerouted = tf.follower.wait_for(
        lambda r: r["frame"] >= cut_frame and _answered_by(r) == "edge-2",
        timeout_s=WAIT_S,
        what="a frame answered by edge-2 after the cut",
        procs=[robot],
    )
    records = by_frame(tf.finish_robot(RUN_S))
    _assert_no_frame_lost(records, frames)
    during = between(records, cut_frame, int(rerouted["frame"]))
    fallbacks = [r for r in during if r["fallback"]]
    print(
        f"cable cut at frame {cut_frame}; frames finished on the robot meanwhile: "
        f"{len(fallbacks)} ({sorted({str(r['reason']) for r in fallbacks})}); "
        f"edge-2 from frame {rerouted['frame']}"
    )
    assert fallbacks, "no local fallback while the deployment was unreachable"
    assert all(_answered_by(r) is None for r in during), "a frame answered by edge-1 after the cut"
    assert all(_answered_by(r) == "edge-2" for r in between(records, frames - 10))
