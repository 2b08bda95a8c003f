"""The shared budget of a robot's services (`robotd.shared_budget`), on a fake clock: who gives
way on a loaded uplink (the lower priority, never the higher), the link's rate bounded by a
frame that timed out but not by one that found no route, the hold once a service gave way, and
independent decisions that never override a policy."""

from __future__ import annotations

from typing import Any

import pytest

from common.config import FleetConfig, fleet_from_dict
from robotd.policies import Decision, Outcome
from robotd.policies.base import PURE_ROBOT
from robotd.shared_budget import GIVE_WAY_HOLD_S, MIN_LINK_SAMPLE_BYTES, SharedBudget

FRAME_BYTES = 40_000  # a handler's JPEG 90 at 640x480
LINK_BPS = 250_000.0  # 2 Mbit/s
FPS = 5.0
CLASSIFY_BYTES = 20_000


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def views() -> dict[str, FleetConfig]:
    cfg = fleet_from_dict(
        {
            "services": {
                "classify": {"model": "zoo:vgg", "priority": 2, "deadline_s": 0.15},
                "tags": {"model": "zoo:vgg", "priority": 0, "deadline_s": 0.25},
            },
            "latency_bound": {"seconds": 0.3},
            "deadline_s": 0.5,
            "machines": {
                "edge-1": {"role": "cloud"},
                "robot-1": {"role": "robot", "fps": FPS},
            },
            "initial_policy": {"edge-1": "service"},
        }
    )
    return {name: cfg.for_service(name) for name in cfg.services}


def budget(joint: bool = True) -> tuple[SharedBudget, Clock]:
    clock = Clock()
    return SharedBudget(views(), joint=joint, cores=1.0, clock=clock), clock


OFFLOAD = Decision(0)


def answered(network_s: float, sent: int = FRAME_BYTES) -> Outcome:
    return Outcome(prefix_s=0.001, cloud_s=network_s + 0.002, cloud_compute_s=0.002, bytes_up=sent)


def stream(b: SharedBudget, clock: Clock, service: str, outcome: Outcome, frames: int) -> None:
    """`frames` frames of `service` at FPS, each observed with `outcome`."""
    for _ in range(frames):
        clock.now += 1 / FPS
        b.observe(service, OFFLOAD, outcome)


def test_the_lower_priority_gives_way_where_the_higher_loads_the_link() -> None:
    b, clock = budget()
    # The link measured at 2 Mbit/s; the classifier (ranked above the handler) sends 20 KB
    # frames at 5 fps, 40% of it, and the handler's 40 KB at 5 fps would add 80%.
    stream(b, clock, "tags", answered(FRAME_BYTES / LINK_BPS), 5)
    stream(b, clock, "classify", answered(CLASSIFY_BYTES / LINK_BPS, sent=CLASSIFY_BYTES), 5)
    assert b.link_bps == pytest.approx(LINK_BPS)
    assert b.gives_way("tags", FRAME_BYTES, full_s=0.02)
    # Nobody ranks above the classifier, and its own load leaves the link room.
    assert not b.gives_way("classify", CLASSIFY_BYTES, full_s=0.02)


def test_a_service_whose_own_frames_would_flood_the_link_runs_them_itself() -> None:
    b, clock = budget()
    stream(b, clock, "classify", answered(FRAME_BYTES / LINK_BPS), 5)
    # 40 KB at 5 fps: 80% of the link from the top-ranked service alone, a growing queue.
    assert b.gives_way("classify", FRAME_BYTES, full_s=0.02)


def test_nobody_gives_way_on_an_idle_link_or_where_the_robot_would_miss_the_deadline() -> None:
    b, clock = budget()
    stream(b, clock, "tags", answered(FRAME_BYTES / 2_500_000.0), 5)  # 20 Mbit/s
    assert not b.gives_way("tags", FRAME_BYTES, full_s=0.02)
    b2, clock2 = budget()
    stream(b2, clock2, "tags", answered(FRAME_BYTES / LINK_BPS), 5)
    stream(b2, clock2, "classify", answered(FRAME_BYTES / LINK_BPS), 5)
    assert not b2.gives_way("tags", FRAME_BYTES, full_s=1.0)  # slower than its deadline


def test_a_timeout_bounds_the_link_a_frame_without_a_route_does_not() -> None:
    b, clock = budget()
    stream(b, clock, "tags", answered(FRAME_BYTES / 2_500_000.0), 5)
    fast = b.link_bps
    assert fast is not None
    no_route = Outcome(prefix_s=0.001, bytes_up=FRAME_BYTES, waited_s=0.25, timed_out=False)
    stream(b, clock, "tags", no_route, 1)
    assert b.link_bps == pytest.approx(fast)
    timeout = Outcome(prefix_s=0.001, bytes_up=FRAME_BYTES, waited_s=0.25, timed_out=True)
    stream(b, clock, "tags", timeout, 1)
    assert b.link_bps == pytest.approx(FRAME_BYTES / 0.25)


def test_small_frames_do_not_measure_the_link() -> None:
    b, clock = budget()
    small = MIN_LINK_SAMPLE_BYTES // 2
    stream(b, clock, "classify", answered(0.001, sent=small), 10)
    assert b.link_bps is None
    assert not b.gives_way("tags", FRAME_BYTES, full_s=0.02)  # nothing known: no override


def test_a_service_that_gave_way_holds_then_lets_one_frame_through() -> None:
    b, clock = budget()
    stream(b, clock, "tags", answered(FRAME_BYTES / LINK_BPS), 5)
    stream(b, clock, "classify", answered(FRAME_BYTES / LINK_BPS), 5)
    assert b.gives_way("tags", FRAME_BYTES, full_s=0.02)
    clock.now += GIVE_WAY_HOLD_S / 2
    assert b.gives_way("tags", FRAME_BYTES, full_s=0.02)  # held, whatever the estimates say
    clock.now += GIVE_WAY_HOLD_S
    assert not b.gives_way("tags", FRAME_BYTES, full_s=0.02)  # one through, to measure again
    assert b.state()["services"]["tags"]["gave_way"] == 2


def test_independent_decisions_never_give_way() -> None:
    b, clock = budget(joint=False)
    stream(b, clock, "tags", answered(FRAME_BYTES / LINK_BPS), 5)
    stream(b, clock, "classify", answered(FRAME_BYTES / LINK_BPS), 5)
    assert not b.gives_way("tags", FRAME_BYTES, full_s=0.02)


class Offloads:
    """A policy that always offloads cut 0 and records what it observes."""

    def __init__(self, cuts: Any) -> None:
        self.cuts = cuts
        self.name = "offloads"
        self.seen: list[Decision] = []

    def decide(self, ctx: Any) -> Decision:
        return OFFLOAD

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        self.seen.append(decision)

    def state(self) -> dict[str, Any]:
        return {"policy": self.name}


def test_the_wrapped_policy_runs_a_frame_that_gave_way_on_the_robot_and_learns_it_as_p() -> None:
    from types import SimpleNamespace

    import numpy as np

    from robotd.policies.base import FrameContext

    b, clock = budget()
    stream(b, clock, "tags", answered(FRAME_BYTES / LINK_BPS), 5)
    stream(b, clock, "classify", answered(FRAME_BYTES / LINK_BPS), 5)
    cuts = SimpleNamespace(
        full_s=0.02,
        indices=(0,),
        codecs=("raw",),
        ends=(None,),
        bytes=np.array([float(FRAME_BYTES)]),
    )
    inner = Offloads(cuts)
    policy = b.share("tags").wrap(inner)  # type: ignore[arg-type]
    decision = policy.decide(FrameContext(index=0))
    assert decision.action == PURE_ROBOT
    policy.observe(decision, Outcome(prefix_s=0.02))
    assert inner.seen == [decision]
    assert policy.name == "offloads"
