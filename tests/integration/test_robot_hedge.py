"""The robot daemon's hedged frames over real Zenoh on loopback, with a local suffix that costs
real work (a chain of convolutions, tens of ms per run) and a deployment that answers at once
or too late.

What must hold: a reply that comes first serves the frame and stops the local run, which then
costs the robot a small share of a whole run and reports no robot time; a local run the policy
defers is never started when the reply comes within the deferral; when the cloud is too slow,
the deferred local run starts after the deferral and serves the frame before the deadline.
No frame is lost.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
import zenoh
from onnx import TensorProto, numpy_helper

from common import keys
from common.partition import load_partition, sample_feeds
from common.partition.runtime import SplitModel
from robotd.policies import Decision, FrameContext, Outcome, Policy
from robotd.policies.base import CutTable
from tests.helpers.observed import ObservedByFrame
from tests.helpers.onnx_graphs import make_model, node, save, vi
from tests.integration.conftest import Router
from tests.integration.test_robotd import (
    DEPLOYMENT,
    FLEET,
    FakeDeployment,
    assert_no_frame_lost,
    fleet_config,
    run_robot,
)

INPUT_SHAPE = (1, 3, 32, 32)
CHANNELS = 64
LAYERS = 192
CLASSES = 5
CUT_TENSOR = "r0"  # after the first convolution: almost all of the work is the suffix
FRAMES = 5
SHORT_DEADLINE_S = 0.6
DEFER_LONG_S = 5.0


def heavy_conv_model() -> onnx.ModelProto:
    """image → Conv(3→C) → Relu → (Conv(C→C) → Relu) × LAYERS → GAP → Flatten → Gemm."""
    rng = np.random.default_rng(0)

    def weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
        scale = 1.0 / np.sqrt(np.prod(shape[1:])) if len(shape) > 1 else 0.1
        return numpy_helper.from_array(
            (rng.standard_normal(shape) * scale).astype(np.float32), name
        )

    nodes = [node("Conv", ["image", "w0", "b0"], ["c0"], pads=[1, 1, 1, 1])]
    nodes.append(node("Relu", ["c0"], ["r0"]))
    inits = [weight("w0", (CHANNELS, 3, 3, 3)), weight("b0", (CHANNELS,))]
    for i in range(1, LAYERS + 1):
        nodes.append(node("Conv", [f"r{i - 1}", f"w{i}", f"b{i}"], [f"c{i}"], pads=[1, 1, 1, 1]))
        nodes.append(node("Relu", [f"c{i}"], [f"r{i}"]))
        inits += [weight(f"w{i}", (CHANNELS, CHANNELS, 3, 3)), weight(f"b{i}", (CHANNELS,))]
    nodes += [
        node("GlobalAveragePool", [f"r{LAYERS}"], ["g"]),
        node("Flatten", ["g"], ["f"]),
        node("Gemm", ["f", "wf", "bf"], ["logits"]),
    ]
    inits += [weight("wf", (CHANNELS, CLASSES)), weight("bf", (CLASSES,))]
    return make_model(
        nodes,
        [vi("image", list(INPUT_SHAPE), TensorProto.FLOAT)],
        [vi("logits", [1, CLASSES], TensorProto.FLOAT)],
        inits,
    )


@pytest.fixture(scope="module")
def heavy_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save(heavy_conv_model(), tmp_path_factory.mktemp("heavy") / "heavy.onnx")


@pytest.fixture(scope="module")
def local_suffix_cpu_s(heavy_model: Path) -> float:
    """Process CPU seconds of one local suffix run of the cut (what a stopped run saves)."""
    split = SplitModel(load_partition(str(heavy_model), [CUT_TENSOR]), threads=1)
    feeds = sample_feeds(split.input_specs())
    sent = split.run_prefix(1, feeds)
    split.run_suffix(1, sent, feeds)  # warm-up
    runs = 3
    started = time.process_time()
    for _ in range(runs):
        split.run_suffix(1, sent, feeds)
    return (time.process_time() - started) / runs


class InstantOutputs:
    """What the in-test deployment computes: the model's output names, zeros, at once."""

    def run_suffix(self, cut: int, tensors: Any) -> dict[str, np.ndarray]:
        return {"logits": np.zeros((1, CLASSES), dtype=np.float32)}


class Hedged(Policy):
    """Cut 1, hedged, the local run deferred by `after_s`; keeps what it observes, by frame."""

    name = "hedged"

    def __init__(self, cuts: CutTable, after_s: float, local_expected: bool = False) -> None:
        super().__init__(cuts)
        self.after_s = after_s
        self.local_expected = local_expected
        self.seen = ObservedByFrame()

    def decide(self, ctx: FrameContext) -> Decision:
        decision = Decision(
            1, hedge=True, hedge_after_s=self.after_s, local_expected=self.local_expected
        )
        return self.seen.decided(decision, ctx.index)

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        self.seen.observed(decision, outcome)


class Offloaded(Hedged):
    """Cut 1 without hedging: what a frame costs the robot with no local run at all."""

    name = "offloaded"

    def decide(self, ctx: FrameContext) -> Decision:
        return self.seen.decided(Decision(1), ctx.index)


def cut_table() -> CutTable:
    return CutTable.from_profile(
        {
            "full_ms": 10.0,
            "cuts": [
                {"index": 0, "bytes": 12288, "prefix_ms": 0.0, "suffix_ms": 10.0},
                {"index": 1, "bytes": 196608, "prefix_ms": 0.5, "suffix_ms": 9.5},
            ],
        }
    )


@pytest.fixture
def registry_token(zenoh_peer: zenoh.Session) -> Iterator[None]:
    """The registry's liveliness token only: the robot then waits for its deployment."""
    token = zenoh_peer.liveliness().declare_token(keys.alive_registry(FLEET, "registry"))
    yield
    token.undeclare()


@pytest.fixture
def deployment(open_peer: Callable[..., zenoh.Session]) -> Iterator[Callable[..., FakeDeployment]]:
    made: list[FakeDeployment] = []

    def make(behaviour: str = "ok") -> FakeDeployment:
        model: Any = InstantOutputs()
        dep = FakeDeployment(open_peer(), model, lambda frame: behaviour)
        made.append(dep)
        return dep

    yield make
    for dep in made:
        dep.close()


def config(router: Router, model: Path, **changes: Any) -> Any:
    return fleet_config(router.endpoint, model, cuts={"names": [CUT_TENSOR]}, **changes)


def test_a_reply_first_stops_the_local_run(
    zenoh_router: Router,
    heavy_model: Path,
    local_suffix_cpu_s: float,
    deployment: Callable[..., FakeDeployment],
    registry_token: None,
) -> None:
    dep = deployment()
    policy = Hedged(cut_table(), after_s=0.0)
    run = run_robot(config(zenoh_router, heavy_model), FRAMES, policy=policy)
    assert_no_frame_lost(run, FRAMES)
    assert len(dep.requests) == FRAMES
    for result, outcome in zip(run.results, policy.seen.of(run.results), strict=True):
        assert result.served_by == "cloud" and result.record.deployment == DEPLOYMENT
        assert outcome.local_s is None and result.record.suffix_local_s == 0.0
    # Each frame's local run was started and stopped: together they cost far less than the
    # whole runs would have. CPU per frame also includes Zenoh's and the daemon's own work, which
    # does not shrink with the model, so the hedged run is compared with the same frames offloaded
    # without a local run, side by side.
    plain = run_robot(config(zenoh_router, heavy_model), FRAMES, policy=Offloaded(cut_table(), 0.0))
    assert_no_frame_lost(plain, FRAMES)
    hedged_cpu_s = sum(r.record.robot_cpu_s for r in run.results)
    plain_cpu_s = sum(r.record.robot_cpu_s for r in plain.results)
    print(
        f"robot CPU {hedged_cpu_s:.4f} s hedged, {plain_cpu_s:.4f} s offloaded, in {FRAMES} "
        f"frames; one local run {local_suffix_cpu_s:.4f} s"
    )
    assert hedged_cpu_s - plain_cpu_s < 0.5 * FRAMES * local_suffix_cpu_s


def test_a_deferred_local_run_is_not_started_when_the_reply_comes_first(
    zenoh_router: Router,
    heavy_model: Path,
    local_suffix_cpu_s: float,
    deployment: Callable[..., FakeDeployment],
    registry_token: None,
) -> None:
    deployment()
    policy = Hedged(cut_table(), after_s=DEFER_LONG_S)
    run = run_robot(config(zenoh_router, heavy_model), FRAMES, policy=policy)
    assert_no_frame_lost(run, FRAMES)
    for result, outcome in zip(run.results, policy.seen.of(run.results), strict=True):
        assert result.served_by == "cloud" and outcome.local_s is None
        assert result.record.latency_s < DEFER_LONG_S  # served by the reply, not the deferral
    assert sum(r.record.robot_cpu_s for r in run.results) < 0.5 * FRAMES * local_suffix_cpu_s


def test_a_deferred_local_run_serves_the_frame_when_the_cloud_is_too_slow(
    zenoh_router: Router,
    heavy_model: Path,
    local_suffix_cpu_s: float,
    deployment: Callable[..., FakeDeployment],
    registry_token: None,
) -> None:
    deployment("slow")  # holds every request well past the deadline
    after_s = 0.1
    policy = Hedged(cut_table(), after_s=after_s)
    frames = 2
    run = run_robot(
        config(zenoh_router, heavy_model, deadline_s=SHORT_DEADLINE_S), frames, policy=policy
    )
    assert_no_frame_lost(run, frames)
    for result, outcome in zip(run.results, policy.seen.of(run.results), strict=True):
        record = result.record
        assert result.served_by == "robot"
        assert outcome.local_s is not None and outcome.local_s > 0
        # Started after the deferral, finished before the deadline.
        assert after_s <= record.latency_s < SHORT_DEADLINE_S
        # Handed on when served, before the deadline told the reply's fate.
        assert not record.fallback and record.reason is None
        assert outcome.waited_s == SHORT_DEADLINE_S
    # The telemetry records (the summary counts them) say the cloud timed out.
    assert run.daemon.summary.reasons == {"timeout": frames}


def test_a_sample_taken_while_the_robot_is_best_is_served_locally_and_still_learned_from(
    zenoh_router: Router,
    heavy_model: Path,
    deployment: Callable[..., FakeDeployment],
    registry_token: None,
) -> None:
    # `local_expected`: the local run is the frame's main path (run at once, at the loop's
    # priority); the request is a sample whose reply, coming later, still reaches the learner.
    dep = deployment("delayed")  # answers after a delay longer than the local run
    policy = Hedged(cut_table(), after_s=0.0, local_expected=True)
    frames = 3
    run = run_robot(config(zenoh_router, heavy_model, deadline_s=2.0), frames, policy=policy)
    assert_no_frame_lost(run, frames)
    assert len(dep.requests) == frames
    for result, outcome in zip(run.results, policy.seen.of(run.results), strict=True):
        assert result.served_by == "robot", (
            f"local run {outcome.local_s} s, reply {outcome.cloud_s} s"
        )
        assert outcome.local_s is not None and outcome.local_s > 0
        assert outcome.cloud_s is not None and outcome.cloud_s > result.record.latency_s
