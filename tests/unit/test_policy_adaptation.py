"""ElasticAction on a robot with a CPU quota: regressions for what the namespace testbed showed.

A small deterministic world stands in for the testbed (docs/experiments.md): the robot has a
CFS quota, so every robot run takes whole 100 ms periods (a run that needs a fraction of a
period can still wait two more), and a transfer's time comes in the same steps on top of the
bytes' time on the wire. Residuals of ±30-50% are then ordinary noise, not change. The profile is
the robot daemon's own profile of `zoo:vgg` at 3x120x160 (10 cuts; the whole model takes 5.8 ms
on the profiling core, 0.3-0.5 s at 0.02 of it).

Guarded against:
- a noisy link keeping the policy in an update period (which excludes P after a "faster"
  change) so that after 10 -> 1 Mbit/s it kept sending whole frames for 50 frames;
- a policy without hedging never timing the robot again, so it stayed on full offload after the
  robot's CPU came back;
- a prefix of 1% of the model, timed under the quota, making the robot look 5x slower;
- a hedged local run started at once when the cloud was expected first, competing with the
  offload for the robot's CPU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from robotd.policies import PURE_ROBOT, FrameContext, Objective, Outcome, make_policy
from robotd.policies.base import CutTable
from robotd.policies.elastic import ElasticPolicy
from robotd.policies.params import RobotCostParams
from robotd.policies.robotcost import RobotCostModel

# `robot_profile()` of zoo:vgg at 3x120x160 (bytes crossing each cut, ms on the profiling core).
VGG_120X160 = {
    "full_ms": 5.776,
    "cuts": [
        {"index": i, "bytes": b, "prefix_ms": p, "suffix_ms": 5.776 - p}
        for i, (b, p) in enumerate(
            [
                (230400, 0.0),
                (307200, 0.239),
                (614400, 0.875),
                (153600, 2.149),
                (307200, 2.785),
                (76800, 4.059),
                (115200, 4.536),
                (26880, 5.253),
                (35840, 5.475),
                (512, 5.772),
            ]
        )
    ],
}
PERIOD_S = 0.1  # CFS period
SEEDS = range(10)


@dataclass
class QuotaWorld:
    """The testbed's robot and link, frame by frame (seeded)."""

    cpu_ms_per_period: float  # the quota: 2 ms per 100 ms period is 0.02 core
    uplink_mbit: float
    seed: int
    rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def robot_s(self, profiled_ms: float) -> float:
        """A run needing `profiled_ms` of CPU: whole periods, plus up to two of waiting."""
        if profiled_ms <= 0:
            return 0.0
        if self.cpu_ms_per_period >= 100:  # a whole core: no quota steps
            return profiled_ms / 1000 * float(self.rng.uniform(0.9, 1.2))
        periods = math.ceil(profiled_ms / self.cpu_ms_per_period)
        return PERIOD_S * (periods + int(self.rng.integers(0, 3)))

    def cloud_s(self, nbytes: int) -> float:
        """Bytes on the wire, plus the sender's own CPU steps (none on a whole core)."""
        wire = nbytes * 8 / (self.uplink_mbit * 1e6) + 0.005
        if self.cpu_ms_per_period >= 100:
            return wire * float(self.rng.uniform(1.0, 1.2))
        return wire + PERIOD_S * int(self.rng.integers(0, 3))


@dataclass
class Frame:
    action: Any
    latency_s: float
    hedged: bool


def run_frame(policy: ElasticPolicy, world: QuotaWorld, t: int) -> Frame:
    """One frame as the robot daemon runs it: a hedged local run starts `hedge_after_s` after
    the request and is stopped (reporting no time) when the reply comes first."""
    d = policy.decide(FrameContext(t, entropy=0.5))
    cuts = VGG_120X160["cuts"]
    if d.action == PURE_ROBOT:
        lat = world.robot_s(VGG_120X160["full_ms"])
        policy.observe(d, Outcome(prefix_s=lat, latency_s=lat))
        return Frame(PURE_ROBOT, lat, False)
    cut = cuts[int(d.action)]
    pre = world.robot_s(cut["prefix_ms"])
    y = world.cloud_s(cut["bytes"])
    if d.hedge:
        local = world.robot_s(cut["suffix_ms"])
        local_wins = d.hedge_after_s + local < y
        lat = pre + min(y, d.hedge_after_s + local)
        outcome = Outcome(prefix_s=pre, cloud_s=y, local_s=local if local_wins else None)
    else:
        lat = pre + y
        outcome = Outcome(prefix_s=pre, cloud_s=y)
    policy.observe(d, outcome)
    return Frame(d.action, lat, d.hedge)


def run_phases(params: dict[str, Any], phases: list[tuple[float, float, int]], seed: int) -> list:
    """Frames of each (cpu ms per period, uplink Mbit/s, frames) phase, in one policy run."""
    policy = make_policy("elastic", VGG_120X160, params)
    assert isinstance(policy, ElasticPolicy)
    out, t = [], 0
    for cpu, uplink, frames in phases:
        world = QuotaWorld(cpu, uplink, seed * 100 + t)
        frames_here = []
        for _ in range(frames):
            frames_here.append(run_frame(policy, world, t))
            t += 1
        out.append(frames_here)
    return out


def main_action(frames: list[Frame]) -> Any:
    actions = [f.action for f in frames]
    return max(set(actions), key=actions.count)


@pytest.mark.parametrize("hedge", [True, False])
def test_a_fall_from_20_to_1_mbit_moves_off_full_offload(hedge: bool) -> None:
    # 0.02 core: the robot needs 0.3-0.5 s; a whole frame takes 0.1-0.3 s at 20 Mbit/s and
    # >= 1.85 s at 1 Mbit/s. Before: offload; after: anything that sends less and is faster.
    for seed in SEEDS:
        before, after = run_phases({"hedge": hedge}, [(2.0, 20.0, 40), (2.0, 1.0, 40)], seed)
        assert main_action(before[10:]) == 0, seed
        settled = after[20:]
        assert main_action(settled) != 0, seed
        assert sum(f.action == 0 for f in settled) <= 6, seed  # forced samples only
        assert np.mean([f.latency_s for f in settled]) < 1.0, seed


@pytest.mark.parametrize("hedge", [True, False])
def test_a_robot_that_gets_its_cpu_back_is_noticed(hedge: bool) -> None:
    # A whole core: P in 6 ms. 0.02 core: full offload at 10 Mbit/s (0.2-0.4 s) beats P.
    # The core back: without timing the robot again, nothing would show that P is cheap again.
    # Unhedged robot probes back off to 4x robot_probe_frames while they find the robot slow,
    # so the last 20 of 80 frames are judged.
    for seed in SEEDS:
        _, low, back = run_phases(
            {"hedge": hedge}, [(100.0, 10.0, 30), (2.0, 10.0, 50), (100.0, 10.0, 80)], seed
        )
        assert main_action(low[20:]) == 0, seed
        # Back on the robot: P (cut 9, all but 512 bytes of the model on the robot, is no action:
        # P beats it at any link speed). Forced and confirming samples of the cloud still come.
        settled = back[-40:]
        assert main_action(settled) == PURE_ROBOT, seed
        # The typical frame takes P's 6 ms; the samples (0.03-0.2 s each, not hedged without
        # hedging) keep the mean well below full offload's 0.2-0.4 s.
        assert np.median([f.latency_s for f in settled]) < 0.008, seed
        assert np.mean([f.latency_s for f in settled]) < 0.05, seed


def test_without_hedging_the_robot_is_timed_by_p_probes_that_back_off() -> None:
    # A fast link and a slow robot: cut 0 is best, so only robot probes serve P.
    policy = make_policy("elastic", VGG_120X160, {"hedge": False, "robot_probe_frames": 10})
    assert isinstance(policy, ElasticPolicy)
    p_frames = []
    for t in range(400):
        d = policy.decide(FrameContext(t, 0.5))
        if d.action == PURE_ROBOT:
            p_frames.append(t)
            policy.observe(d, Outcome(prefix_s=0.4, latency_s=0.4))
        else:
            assert not d.hedge
            policy.observe(d, Outcome(prefix_s=0.0, cloud_s=0.1))
    late = [t for t in p_frames if t >= 100]
    gaps = np.diff(late)
    # The estimate keeps fitting: the interval doubles up to 4x robot_probe_frames.
    assert len(late) >= 3 and all(g == 40 for g in gaps[-2:]), p_frames
    assert policy.robot_probes >= 4


def test_a_robot_probe_that_finds_the_robot_changed_resets_the_interval() -> None:
    policy = make_policy("elastic", VGG_120X160, {"hedge": False, "robot_probe_frames": 10})
    assert isinstance(policy, ElasticPolicy)
    p_frames = []
    for t in range(300):
        d = policy.decide(FrameContext(t, 0.5))
        if d.action == PURE_ROBOT:
            p_frames.append(t)
            # From frame 200 the robot is 40x faster: every P from then on is a surprise first.
            lat = 0.4 if t < 200 else 0.01
            policy.observe(d, Outcome(prefix_s=lat, latency_s=lat))
        else:
            policy.observe(d, Outcome(prefix_s=0.0, cloud_s=0.1))
    after = [t for t in p_frames if t >= 200]
    # One probe after the change (within the longest interval), a second one on the next frame
    # confirms it, and from then on P is the policy's own choice (but for forced samples).
    assert after and after[0] <= 200 + 40
    assert after[1] - after[0] == 1
    assert len(after[2:]) >= 0.75 * (300 - after[1] - 1)


def test_short_runs_under_a_quota_do_not_make_the_robot_look_slow() -> None:
    cuts = CutTable.from_profile(VGG_120X160)
    model = RobotCostModel(cuts, Objective(), RobotCostParams())
    for _ in range(2):  # the whole model at 0.02 core (the profile is from a fast host)
        model.observe(0.4, cuts.full_s)
    full = model.full_cost
    for _ in range(2):  # cut 2's prefix (15% of the model) waited out two extra periods
        model.observe(0.3, float(cuts.prefix_s[2]))
    assert model.full_cost < 1.5 * full
    assert not model.suspect
    for _ in range(2):  # the whole model twice as slow, twice: adopted
        model.observe(0.8, cuts.full_s)
    assert model.full_cost == pytest.approx(0.8, rel=0.05)


def test_a_hedge_starts_its_local_run_only_when_the_cloud_is_late() -> None:
    # Cut 0 beats the robot's 0.4 s; the link slows from 0.15 to 0.3 s, which starts an update
    # period whose cut-0 frames are hedged. Cut 0 is still the best choice, so each defers its
    # local run to when the reply is overdue (it cannot beat the reply; started at once it
    # would only compete with the offload for the robot's CPU).
    policy = make_policy("elastic", VGG_120X160, {"robot_probe_frames": 0})
    assert isinstance(policy, ElasticPolicy)
    hedged = []
    for t in range(120):
        d = policy.decide(FrameContext(t, 0.5))
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=0.4, latency_s=0.4))
            continue
        if t >= 60 and d.hedge and d.action == 0:
            hedged.append(d.hedge_after_s)
        policy.observe(d, Outcome(prefix_s=0.0, cloud_s=0.15 if t < 60 else 0.3))
    assert len(hedged) >= 3, "no hedged cut-0 frame in the update period"
    assert all(0.1 < after <= 0.45 for after in hedged), hedged


def test_a_hedge_whose_greedy_choice_is_the_robot_starts_at_once() -> None:
    # A slow link: P (0.4 s) is best; a forced cut-0 frame races a local run started at once,
    # which finishes when P would have.
    policy = make_policy("elastic", VGG_120X160, {"forced_schedule": "every"})
    assert isinstance(policy, ElasticPolicy)
    decisions = []
    for t in range(60):
        d = policy.decide(FrameContext(t, 0.5))
        decisions.append(d)
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=0.4, latency_s=0.4))
        else:
            policy.observe(d, Outcome(prefix_s=0.0, cloud_s=3.0, local_s=0.4))
    forced = [d for d in decisions[30:] if d.forced]
    assert forced and all(d.hedge and d.hedge_after_s < 1e-9 for d in forced)


def test_robot_probes_hedge_at_once() -> None:
    policy = make_policy("elastic", VGG_120X160, {"robot_probe_frames": 10})
    assert isinstance(policy, ElasticPolicy)
    probes = []
    for t in range(200):
        d = policy.decide(FrameContext(t, 0.5))
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=0.4, latency_s=0.4))
            continue
        if t >= 100 and d.hedge and d.action == 0:
            probes.append(d)
        # The reply always comes first: probes time nothing, and keep coming.
        policy.observe(d, Outcome(prefix_s=0.0, cloud_s=0.15))
    # Cut 0 is the greedy choice: its hedged frames are robot probes, every 10 frames.
    assert len(probes) >= 8, "robot probes stopped"
    assert all(d.hedge_after_s == 0.0 for d in probes)
