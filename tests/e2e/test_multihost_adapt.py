"""e2e on the namespace testbed: the elastic policy, with its default parameters (hedged
exploration on), adapts to a real uplink glitch and to a real CPU quota drop while the robot
streams (root only; each test takes under a minute: 40-50 s and about 30 s measured here).

Same fixture as `test_multihost.py` (a testbed of its own per test, checked to leave nothing
behind). Frames of 120x160 here: the model's ~9 ms of CPU per frame, not the runtime's ~2 ms per
offloaded frame, must dominate what the robot computes, or a CPU quota would slow every action
alike.
"""

from __future__ import annotations

import contextlib
import os
import statistics
from collections.abc import Callable

import pytest

from deploy.experiments.runner import TestbedFleet
from deploy.experiments.stats import action_order, between, by_frame, final_action, summary
from deploy.procs import DaemonError
from tests.e2e import test_multihost as mh

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.netns,
    pytest.mark.skipif(
        os.geteuid() != 0, reason="needs root: creates network namespaces, tc qdiscs and cgroups"
    ),
]

fleet = mh.fleet  # the fixture: a testbed fleet per test, torn down and checked

AFTER_BUDGET_S = 30.0
"""How long the frames after the glitch may take; a policy still sending whole frames (3-4 s
each at 1 Mbit/s) is judged on the frames it managed by then."""


@pytest.mark.skip(
    reason="out of the suite until re-tuned for uint8 camera frames and the finer CPU period: at "
    "0.25 Mbit/s it passed 1 of 2 runs (too few frames after the glitch to settle), at 0.5 Mbit/s "
    "0 of 3 (settled on P, but slow robot frames kept the mean above a full offload)"
)
def test_uplink_glitch_moves_elastic_to_a_cut_that_sends_less_and_is_faster(
    fleet: Callable[..., TestbedFleet],
) -> None:
    """20 -> 0.25 Mbit/s under a slow robot (0.015 core): before, sending the frame wins; after, a
    full offload needs >= 1.8 s on the wire alone, and the elastic policy (default parameters,
    hedged exploration on) must find a cheaper action (a later cut or the robot) that ends
    faster than that.

    0.015 rather than 0.02 core: the whole model then takes 0.5-0.6 s on the robot, twice a
    full offload at 20 Mbit/s even when other work on the shared machine slows the transfers to
    0.3 s; at 0.02 core (0.4 s) a loaded machine made the two nearly equal, and the policy then
    rightly served some of the "before" frames on the robot."""
    # Raw crossings: what is tested is the move to a later cut (with JPEG allowed, cut 0 in
    # jpeg50 sends 2 KB and stays best at both rates).
    tf = fleet(
        deadline_s=5.0,
        input_shape=mh.BIG_INPUT_SHAPE,
        changes={"fidelity": {"codecs": ["raw"]}},
    )
    # 0.25 Mbit/s: the uint8 frame (57.6 KB) then needs 1.8 s on the wire, as the float32 frame
    # of the same shape did at 1 Mbit/s.
    high, low, cpu = 20.0, 0.25, 0.015
    warmup, before, after = 6, 16, 24
    frames = warmup + before + after
    tf.shape_robot(high)
    robot = tf.start_robot("elastic", frames=frames, cpu_fraction=cpu)
    start = tf.measure_from + warmup
    tf.follower.wait_frame(start + before - 1, timeout_s=mh.WAIT_S, procs=[robot])
    tf.shape_robot(low)
    change = tf.follower.last_frame() + 1
    with contextlib.suppress(DaemonError):
        tf.follower.wait_frame(frames - 1, timeout_s=AFTER_BUDGET_S, procs=[robot])
    tf.stop_robot()
    records = by_frame(tf.follower.records())
    mh._assert_no_frame_lost(records, max(r["frame"] for r in records) + 1)

    pre = between(records, start, change)
    post = between(records, change)
    assert len(post) >= 8, f"only {len(post)} frames in {AFTER_BUDGET_S:.0f} s after the glitch"
    tail = post[len(post) // 2 :]  # settled: the second half of the frames after the glitch
    pre_s, tail_s = summary(pre), summary(tail)
    full_offload_floor_s = mh.BIG_INPUT_BYTES * 8 / (low * 1e6)
    # What most settled frames send (forced samples keep exploring other cuts, a few of them
    # bigger than the input: they may not decide this), and less than before on average too.
    median_bytes = statistics.median(float(r["bytes_up"]) for r in tail)
    print(
        f"before ({high:g} Mbit/s): {pre_s['actions']} mean {pre_s['mean_latency_s']:.3f} s, "
        f"{pre_s['bytes_up']:.0f} B up; settled after ({low:g} Mbit/s): {tail_s['actions']} "
        f"mean {tail_s['mean_latency_s']:.3f} s, {tail_s['bytes_up']:.0f} B up (median "
        f"{median_bytes:.0f} B); a full offload needs >= {full_offload_floor_s:.3f} s"
    )
    assert pre_s["bytes_up"] > 0.5 * mh.BIG_INPUT_BYTES, "elastic did not offload at 20 Mbit/s"
    assert median_bytes < 0.5 * pre_s["bytes_up"], "it still sends as much after the glitch"
    assert tail_s["bytes_up"] < pre_s["bytes_up"]
    assert tail_s["main_action"] != "cut:0"
    assert tail_s["mean_latency_s"] < full_offload_floor_s


def test_cpu_quota_drop_moves_work_to_the_cloud(fleet: Callable[..., TestbedFleet]) -> None:
    """A whole core: the robot computes (most of) the model itself. 0.02 core: every local
    millisecond costs 50, and the elastic policy moves to an earlier cut, answered by edge-1."""
    tf = fleet(deadline_s=5.0, input_shape=mh.BIG_INPUT_SHAPE)
    warmup, high, low = 6, 20, 30
    frames = warmup + high + low
    tf.shape_robot(20.0)
    robot = tf.start_robot("elastic", frames=frames, cpu_fraction=1.0)
    start = tf.measure_from + warmup
    tf.follower.wait_frame(start + high - 1, timeout_s=mh.WAIT_S, procs=[robot])
    tf.cpu_robot(0.02)
    drop = tf.follower.last_frame() + 1
    records = by_frame(tf.finish_robot(mh.RUN_S))
    mh._assert_no_frame_lost(records, frames)

    pre = between(records, start, drop)
    post = between(records, drop)
    before_action, after_action = final_action(pre), final_action(post)
    tail = post[len(post) // 2 :]
    pre_s, tail_s = summary(pre), summary(tail)
    answered = [r for r in tail if mh._answered_by(r) == "edge-1"]
    print(
        f"1 core: {pre_s['actions']} mean {pre_s['mean_latency_s']:.3f} s; 0.02 core: "
        f"{summary(post)['actions']}, settled on {after_action}, mean "
        f"{tail_s['mean_latency_s']:.3f} s, {len(answered)}/{len(tail)} answered by edge-1"
    )
    assert before_action is not None and after_action is not None
    assert action_order(after_action) < action_order(before_action), "no work moved off the robot"
    assert len(answered) >= 0.7 * len(tail), "the cloud does not answer most settled frames"
