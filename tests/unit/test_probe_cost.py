"""Exploration's robot CPU in elastic's objective: lost robot probes are priced and spaced, a
stopped local run bounds the robot's time, and an insurance run is started only where it pays.

The robot here is the testbed's weak one: profiled at full speed (the whole model in 5.8 ms),
then given a small CPU quota, so the whole model takes 0.4 s while the cloud answers cut 0 in
0.15 s. A hedged local run started at once never beats the reply: the reply stops it, it times
nothing, and it kept the robot computing until then. The robot daemon reports each frame's CPU
(`Outcome.cpu_s`); the simulator does not, and keeps the probes every `robot_probe_frames`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

from robotd.policies import PURE_ROBOT, FrameContext, Outcome, make_policy
from robotd.policies.elastic import ElasticPolicy
from robotd.policies.insurance import Insurance

FULL_MS = 5.776
PROFILE = {
    "full_ms": FULL_MS,
    "cuts": [
        {"index": i, "bytes": b, "prefix_ms": p, "suffix_ms": FULL_MS - p}
        for i, (b, p) in enumerate(
            [(230400, 0.0), (153600, 2.149), (76800, 4.059), (26880, 5.253), (512, 5.772)]
        )
    ],
}
P_S = 0.4  # the whole model on the weak robot
REPLY_S = 0.15  # cut 0's reply
CPU_S = 0.003  # an offloaded frame's robot CPU (its encode and send)
PROBE = 10


def run(
    frames: int,
    *,
    report_cpu: bool,
    reply_s: float | Callable[[int], float] = REPLY_S,
    p_s: Callable[[int], float] = lambda t: P_S,
    **params: object,
) -> list:
    """Frames of `elastic` on the weak robot: (frame, decision) of every frame."""
    policy = make_policy(
        "elastic", PROFILE, {"robot_probe_frames": PROBE, "forced_schedule": "off", **params}
    )
    assert isinstance(policy, ElasticPolicy)
    out = []
    for t in range(frames):
        d = policy.decide(FrameContext(t, 0.5))
        out.append((t, d))
        cpu = None
        whole_s = p_s(t)
        if d.action == PURE_ROBOT:
            if report_cpu:
                cpu = 0.1 * whole_s
            policy.observe(d, Outcome(prefix_s=whole_s, latency_s=whole_s, cpu_s=cpu))
            continue
        y = reply_s(t) if callable(reply_s) else reply_s
        # A hedged run starting at once loses to the reply: stopped, it reports no time.
        local = whole_s if d.hedge and d.hedge_after_s + whole_s <= y else None
        if report_cpu:
            cpu = CPU_S + (0.1 * max(0.0, y - d.hedge_after_s) if d.hedge else 0.0)
        policy.observe(d, Outcome(prefix_s=0.0, cloud_s=y, local_s=local, cpu_s=cpu))
    return out


def probes(frames: list) -> list[int]:
    """Frames hedged at once on cut 0 (robot probes)."""
    return [
        t
        for t, d in frames
        if d.action == 0 and d.hedge and d.hedge_after_s == 0.0 and not d.local_expected
    ]


def test_lost_probes_are_priced_and_spaced_on_a_robot_that_reports_its_cpu() -> None:
    late = [t for t in probes(run(600, report_cpu=True)) if t >= 200]
    # A lost probe kept the robot busy for a whole reply, about one frame's cost: at most
    # 2.5% of the frames' cost goes to probes, so about one frame in 40 (not one in 10).
    assert late, "no probe at all: a robot that got faster would never be noticed"
    assert len(late) <= 400 / 35, late
    gaps = [b - a for a, b in itertools.pairwise(late)]
    assert all(g >= 35 for g in gaps), gaps


def test_a_robot_far_from_winning_is_probed_rarely_from_the_start() -> None:
    # P costs 8x cut 0's reply (0.4 against 0.05 s): a probe finds something that changes the
    # choice only on a robot several times faster, so they are spaced by that distance before
    # any was lost and priced (the simulator's robot, which reports no CPU, keeps its interval).
    spaced = probes(run(400, report_cpu=True, reply_s=0.05))
    assert len(spaced) >= 400 // (8 * PROBE), spaced  # they keep coming
    assert all(b - a >= 4 * PROBE for a, b in itertools.pairwise(spaced)), spaced
    unspaced = probes(run(400, report_cpu=False, reply_s=0.05))
    assert [b - a for a, b in itertools.pairwise(unspaced)][1:] == [PROBE] * (len(unspaced) - 2)


def test_a_spaced_robot_that_gets_its_cpu_back_is_noticed() -> None:
    # From frame 200 the whole model takes 10 ms: the next probe's local run beats the 50 ms
    # reply, and from then on P serves (the longest spacing is 8 x robot_probe_frames).
    frames = run(400, report_cpu=True, reply_s=0.05, p_s=lambda t: P_S if t < 200 else 0.01)
    p_frames = [t for t, d in frames if d.action == PURE_ROBOT and t >= 200]
    assert p_frames and p_frames[0] <= 200 + 8 * PROBE + 2, p_frames
    assert len(p_frames) >= 0.9 * (400 - p_frames[0]), p_frames


def test_without_a_cpu_report_probes_keep_their_interval() -> None:
    late = [t for t in probes(run(600, report_cpu=False)) if t >= 200]
    assert len(late) >= 400 / PROBE - 2, late


def test_a_stopped_run_bounds_the_robot_and_the_next_probe_times_it_on_p() -> None:
    frames = run(200, report_cpu=True)
    p_frames = [t for t, d in frames if d.action == PURE_ROBOT]
    first = probes(frames)[0]
    # The first lost probe shows the robot slower than its profile; the next frame is served
    # on the robot to time it, and P is not chosen again (it costs 0.4 s against 0.15 s).
    assert first + 1 in p_frames, (first, p_frames)
    assert not [t for t in p_frames if t > first + 3], p_frames


def test_insurance_is_left_out_where_overdue_replies_come_soon_after() -> None:
    # The link slows from 0.15 to 0.2 s at frame 60: an update period hedges its cut-0 frames.
    # The local run (0.4 s) cannot beat the reply. Without a CPU report it is insurance that
    # starts when the reply is 25% late (0.25 s); with one, the overdue replies came a few ms
    # after that, far sooner than the run would take, and it is not started at all.
    def reply(t: int) -> float:
        return REPLY_S if t < 60 else 0.2

    for report_cpu in (False, True):
        frames = run(120, report_cpu=report_cpu, reply_s=reply, robot_probe_frames=0)
        updating = [d for t, d in frames if t >= 60 and d.updating and d.action == 0]
        hedged = [d.hedge_after_s for d in updating if d.hedge]
        assert len(updating) >= 3, "no update period"
        if report_cpu:
            assert not hedged, hedged
        else:
            assert len(hedged) == len(updating), hedged
            assert all(0.15 < after <= 0.26 for after in hedged), hedged


def test_insurance_pays_when_overdue_replies_come_much_later() -> None:
    insurance = Insurance(wait_rate=1.0, robot_rate=1.0)
    assert insurance.worth(0.4)  # nothing seen yet
    for _ in range(30):
        insurance.observe(0.24, 0.19)  # overdue replies 50 ms late: a 0.4 s run never pays
    assert not insurance.worth(0.4)
    assert insurance.worth(0.02)  # a run of 20 ms does (under 50 ms x ln 2)
    for _ in range(30):
        insurance.observe(2.0, 0.19)  # the link broke: replies at the deadline
    assert insurance.worth(0.4)
