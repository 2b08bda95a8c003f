"""The robot daemon's frame loop over a real Zenoh session on loopback, against a minimal in-test
deployment: a real queryable on the robot's service key (complete=True) that answers with
`SplitModel.run_suffix` from a worker thread, or with a scripted misbehaviour per frame.

What must hold: frames the cloud answered equal the whole model run locally (<= 1e-4); with no
deployment, or one that is too slow, busy, failing or talking garbage, every frame is finished on
the robot with the reason and none is lost; hedged frames serve the first result and still feed the
cloud's reply to the policy; telemetry is in the JSONL file (every contract key) and on
`tele/<robot>`; probe reports name every live deployment; route changes reach the requests.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
import zenoh
from onnx import TensorProto, numpy_helper

from common import keys
from common.config import FleetConfig, fleet_from_dict
from common.heap import can_trim
from common.partition import load_partition
from common.partition.runtime import SplitModel
from common.wire import ErrorCode, ErrorReply, decode
from common.wire.cloud_to_robot import BusyReply, InferReply
from common.wire.registry import PROTOCOL_VERSION, ProbeReply, ProbeRequest, RouteChange
from common.wire.robot_to_cloud import InferRequest
from common.wire.telemetry import JSONL_FIELDS, ProbeReport, TelemetryRecord
from common.wire.tensor_codecs import decode_tensors
from robotd.daemon import FrameResult, RobotDaemon, RobotOptions
from robotd.frame_path.pacing import BITS_PER_BYTE
from robotd.policies import Decision, FrameContext, Outcome, Policy
from robotd.policies.base import CutTable
from robotd.telemetry import EXTRA_FIELDS
from tests.helpers.observed import ObservedByFrame
from tests.helpers.onnx_graphs import make_model, node, save, vi
from tests.integration.conftest import Router

FLEET = "robotd-it"
SERVICE = "vision"
ROBOT = "robot-1"
DEPLOYMENT = "edge-1"
INPUT_SHAPE = (1, 3, 16, 16)
CLASSES = 5
DEADLINE_S = 0.5
SHORT_DEADLINE_S = 0.15
TOLERANCE = 1e-4
FRAMES = 6
# Waits on real events (tokens, replies, records), never sleeps.
WAIT_S = 10.0
# How long the slow deployment holds a request (well past SHORT_DEADLINE_S); released early at
# teardown.
SLOW_HOLD_S = 2.0
DELAYED_HOLD_S = 0.3
"""How long the `delayed` behaviour holds a request before it answers (inside the deadline)."""
# A daemon asked to stop must be gone within this (the CLI contract for SIGINT).
STOP_WITHIN_S = 2.0

# The fake cloud decodes what the robot sends; no test tensor comes near this.
MAX_DECODED_BYTES = 64 << 20


# -- a tiny image model ----------------------------------------------------------------------------
def tiny_conv_model() -> onnx.ModelProto:
    """image[1,3,16,16] → (Conv → Relu) × 2 → GlobalAveragePool → Flatten → Gemm → logits."""
    rng = np.random.default_rng(0)

    def weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
        return numpy_helper.from_array((rng.standard_normal(shape) * 0.3).astype(np.float32), name)

    return make_model(
        [
            node("Conv", ["image", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
            node("Relu", ["c1"], ["r1"]),
            node("Conv", ["r1", "w2", "b2"], ["c2"], pads=[1, 1, 1, 1]),
            node("Relu", ["c2"], ["r2"]),
            node("GlobalAveragePool", ["r2"], ["g"]),
            node("Flatten", ["g"], ["f"]),
            node("Gemm", ["f", "w3", "b3"], ["logits"]),
        ],
        [vi("image", list(INPUT_SHAPE), TensorProto.FLOAT)],
        [vi("logits", [1, CLASSES], TensorProto.FLOAT)],
        [
            weight("w1", (8, 3, 3, 3)),
            weight("b1", (8,)),
            weight("w2", (8, 8, 3, 3)),
            weight("b2", (8,)),
            weight("w3", (8, CLASSES)),
            weight("b3", (CLASSES,)),
        ],
    )


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save(tiny_conv_model(), tmp_path_factory.mktemp("model") / "tiny.onnx")


@pytest.fixture(scope="module")
def split(model_file: Path) -> SplitModel:
    """The deployment's copy of the split model (same cache entry as the robot's)."""
    return SplitModel(load_partition(str(model_file)))


def fleet_config(endpoint: str, model_file: Path, **changes: Any) -> FleetConfig:
    data: dict[str, Any] = {
        "fleet": FLEET,
        "service": SERVICE,
        "model": str(model_file),
        "registry": {"endpoint": endpoint, "listen": [endpoint]},
        "machines": {
            DEPLOYMENT: {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]},
            ROBOT: {"role": "robot", "listen": ["tcp/127.0.0.1:0"]},
        },
        "initial_policy": {DEPLOYMENT: "service", ROBOT: "robot"},
        "latency_bound": {"stat": "median", "seconds": 0.3},
        "deadline_s": DEADLINE_S,
        "policy": {"kind": "cloud"},
    }
    data.update(changes)
    return fleet_from_dict(data)


# -- a minimal deployment --------------------------------------------------------------------------
Script = Callable[[int], str]


class FakeDeployment:
    """A queryable on the robot's service key answering from a worker thread (callbacks must not
    compute). `script(frame)` picks the behaviour: ok, slow (past the deadline), delayed (then
    ok), busy, error, garbage, reply_err, wrong_frame."""

    def __init__(
        self, session: zenoh.Session, model: SplitModel, script: Script | None = None
    ) -> None:
        self.model = model
        self.script = script or (lambda frame: "ok")
        self.requests: list[InferRequest] = []
        self.replied_at: dict[int, float] = {}  # frame -> time.perf_counter() of its reply
        self.release = threading.Event()
        self.answered = threading.Event()
        self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="fake-deployment")
        key = keys.svc_infer(FLEET, SERVICE, ROBOT)
        self._queryable = session.declare_queryable(key, self._on_query, complete=True)

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        self._pool.submit(self._answer, query, data)

    def _answer(self, query: zenoh.Query, data: bytes) -> None:
        request = InferRequest.from_wire(data)
        self.requests.append(request)
        behaviour = self.script(request.frame)
        key = query.key_expr
        if behaviour in ("slow", "delayed"):
            self.release.wait(SLOW_HOLD_S if behaviour == "slow" else DELAYED_HOLD_S)
            behaviour = "ok"
        if behaviour == "busy":
            query.reply(
                key,
                BusyReply(
                    frame=request.frame, deployment=DEPLOYMENT, queued=4, capacity=4
                ).to_wire(),
            )
        elif behaviour == "error":
            query.reply(key, ErrorReply.make(ErrorCode.UNKNOWN_CUT, "no such cut here").to_wire())
        elif behaviour == "garbage":
            query.reply(key, b"\xc1 not msgpack")
        elif behaviour == "reply_err":
            query.reply_err(b"the deployment fell over")
        else:
            frame = request.frame + (1 if behaviour == "wrong_frame" else 0)
            tensors = decode_tensors(request.tensors, max_bytes=MAX_DECODED_BYTES)
            outputs = self.model.run_suffix(request.cut, tensors)
            reply = InferReply(
                frame=frame,
                deployment=DEPLOYMENT,
                epoch=request.epoch,
                outputs=outputs,
                queue_s=0.0,
                compute_s=0.001,
            )
            query.reply(key, reply.to_wire())
            self.replied_at[request.frame] = time.perf_counter()
        self.answered.set()

    def close(self) -> None:
        self.release.set()
        self._queryable.undeclare()
        self._pool.shutdown(wait=True)


@pytest.fixture
def deployment(
    open_peer: Callable[..., zenoh.Session], split: SplitModel
) -> Iterator[Callable[..., FakeDeployment]]:
    made: list[FakeDeployment] = []

    def make(script: Script | None = None) -> FakeDeployment:
        dep = FakeDeployment(open_peer(), split, script)
        made.append(dep)
        return dep

    yield make
    for dep in made:
        dep.close()


@pytest.fixture
def fake_registry(zenoh_peer: zenoh.Session) -> Iterator[zenoh.Session]:
    """The registry's liveliness token (no registry logic): the robot then waits for the
    deployment serving it before its first frame instead of reporting the registry missing."""
    token = zenoh_peer.liveliness().declare_token(keys.alive_registry(FLEET, "registry"))
    yield zenoh_peer
    token.undeclare()


# -- running the robot -----------------------------------------------------------------------------
@dataclass
class Run:
    daemon: RobotDaemon
    results: list[FrameResult] = field(default_factory=list)

    @property
    def records(self) -> list[TelemetryRecord]:
        return [r.record for r in self.results]


def run_robot(
    cfg: FleetConfig,
    frames: int = FRAMES,
    *,
    policy: Policy | str | None = None,
    on_result: Callable[[FrameResult], object] | None = None,
    **options: Any,
) -> Run:
    """Run the daemon in this thread for `frames` frames; every frame's result is kept (and
    handed to `on_result` too). A policy given by name goes through the daemon's own
    `make_policy`."""
    if isinstance(policy, str):
        options["policy"], policy = policy, None
    options.setdefault("registry_wait_s", WAIT_S)
    options.setdefault("route_wait_s", WAIT_S)
    results: list[FrameResult] = []

    def keep(result: FrameResult) -> None:
        results.append(result)
        if on_result is not None:
            on_result(result)

    daemon = RobotDaemon(
        cfg, ROBOT, RobotOptions(frames=frames, **options), policy=policy, on_result=keep
    )
    assert daemon.run() == 0
    return Run(daemon, results)


def assert_no_frame_lost(run: Run, frames: int) -> None:
    assert sorted(r.frame for r in run.records) == list(range(frames))
    assert run.daemon.summary.frames == frames


# -- tests -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("policy", ["cloud", "static:2"])
def test_answered_frames_equal_the_whole_model_run_locally(
    zenoh_router: Router,
    model_file: Path,
    split: SplitModel,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
    policy: str,
) -> None:
    dep = deployment()
    run = run_robot(fleet_config(zenoh_router.endpoint, model_file), policy=policy)
    assert_no_frame_lost(run, FRAMES)
    for result in run.results:
        assert result.record.deployment == DEPLOYMENT and not result.record.fallback
        assert result.served_by == "cloud"
        local = split.run_full(result.feeds)
        for name, value in local.items():
            np.testing.assert_allclose(result.outputs[name], value, atol=TOLERANCE)
    expected_cut = 0 if policy == "cloud" else 2
    assert {r.cut for r in dep.requests} == {expected_cut}
    assert len(dep.requests) == FRAMES  # anycast: each frame computed once
    assert all(r.model_digest == split.digest for r in dep.requests)
    assert run.daemon.summary.answered == FRAMES


def test_without_a_deployment_every_frame_is_finished_on_the_robot(
    zenoh_router: Router, model_file: Path, split: SplitModel, fake_registry: zenoh.Session
) -> None:
    run = run_robot(fleet_config(zenoh_router.endpoint, model_file), route_wait_s=0.2)
    assert_no_frame_lost(run, FRAMES)
    for result in run.results:
        record = result.record
        assert record.fallback and record.reason == "no_route" and record.deployment is None
        assert record.suffix_local_s > 0 and result.served_by == "robot"
        np.testing.assert_allclose(
            result.outputs["logits"], split.run_full(result.feeds)["logits"], atol=TOLERANCE
        )
    summary = run.daemon.summary.to_json()
    assert summary["fallback_reasons"] == {"no_route": FRAMES}
    # Each frame's query was sent again while its deadline allowed, and counted.
    assert all(result.record.resends > 0 for result in run.results)
    assert summary["resends"] == sum(result.record.resends for result in run.results)


def test_a_deployment_slower_than_the_deadline_times_out(
    zenoh_router: Router,
    model_file: Path,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
) -> None:
    deployment(lambda frame: "slow")
    cfg = fleet_config(zenoh_router.endpoint, model_file, deadline_s=SHORT_DEADLINE_S)
    frames = 3
    run = run_robot(cfg, frames)
    assert_no_frame_lost(run, frames)
    for record in run.records:
        assert record.fallback and record.reason == "timeout"
        assert record.latency_s >= SHORT_DEADLINE_S
        assert record.transfer_s >= SHORT_DEADLINE_S * 0.9  # the wait counts as remote time


def test_every_failure_mode_falls_back_with_its_reason(
    zenoh_router: Router,
    model_file: Path,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
) -> None:
    script = ["busy", "error", "garbage", "reply_err", "wrong_frame", "ok"]
    deployment(lambda frame: script[frame])
    run = run_robot(fleet_config(zenoh_router.endpoint, model_file), len(script))
    assert_no_frame_lost(run, len(script))
    reasons = [r.reason for r in run.records]
    assert reasons == ["busy", "error", "decode_error", "error", "decode_error", None]
    assert [r.fallback for r in run.records] == [True] * 5 + [False]
    assert run.records[0].deployment == DEPLOYMENT  # busy names who was busy
    assert run.records[-1].deployment == DEPLOYMENT


def test_telemetry_file_has_every_key_and_records_are_published(
    zenoh_router: Router,
    model_file: Path,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
    tmp_path: Path,
) -> None:
    deployment()
    published: list[TelemetryRecord] = []
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        published.append(decode(sample.payload.to_bytes(), expect=TelemetryRecord))
        if len(published) == FRAMES:
            done.set()

    sub = fake_registry.declare_subscriber(keys.tele(FLEET, ROBOT), on_sample)
    path = tmp_path / "tele" / "robot-1.jsonl"
    try:
        run_robot(fleet_config(zenoh_router.endpoint, model_file), telemetry=path)
        assert done.wait(WAIT_S), f"{len(published)} of {FRAMES} records published"
    finally:
        sub.undeclare()
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert [obj["frame"] for obj in lines] == list(range(FRAMES))
    for obj in lines:
        assert list(obj)[: len(JSONL_FIELDS)] == list(JSONL_FIELDS)
        assert set(EXTRA_FIELDS) <= set(obj)
        assert obj["action"] == "cut:0" and obj["deployment"] == DEPLOYMENT
        assert obj["bytes_up"] > 0 and obj["bytes_down"] > 0 and obj["latency_s"] > 0
        assert obj["robot_cpu_s"] > 0 and obj["energy_j"] > 0
        assert obj["resends"] == 0  # answered first time
    assert sorted(r.frame for r in published) == list(range(FRAMES))
    assert {r.resends for r in published} == {0}
    assert {r.robot for r in published} == {ROBOT}


class HedgeAlways(Policy):
    """Cut 1, hedged, every frame; keeps what it observes, by frame."""

    name = "hedge-always"

    def __init__(self, cuts: CutTable) -> None:
        super().__init__(cuts)
        self.seen = ObservedByFrame()

    def decide(self, ctx: FrameContext) -> Decision:
        return self.seen.decided(Decision(1, hedge=True), ctx.index)

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        self.seen.observed(decision, outcome)


def _cut_table(split: SplitModel) -> CutTable:
    return CutTable.from_profile(
        {
            "full_ms": 1.0,
            "cuts": [
                {"index": c.index, "bytes": c.bytes, "prefix_ms": 0.5, "suffix_ms": 0.5}
                for c in split.partition.cuts
            ],
        }
    )


def test_hedged_frames_serve_the_first_result_and_feed_the_cloud_reply_to_the_policy(
    zenoh_router: Router,
    model_file: Path,
    split: SplitModel,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
) -> None:
    dep = deployment()
    policy = HedgeAlways(_cut_table(split))
    run = run_robot(fleet_config(zenoh_router.endpoint, model_file), policy=policy)
    assert_no_frame_lost(run, FRAMES)
    assert len(dep.requests) == FRAMES
    assert len(policy.seen.outcomes) == FRAMES
    for result, outcome in zip(run.results, policy.seen.of(run.results), strict=True):
        assert result.hedged and result.served_by in ("cloud", "robot")
        # A reply that comes first cancels the local run: it then reports no robot time.
        assert (outcome.local_s is not None and outcome.local_s > 0) or result.served_by == "cloud"
        assert outcome.cloud_s is not None  # the reply came within the deadline
        # One the robot served while its reply was out was handed on with no deployment yet.
        assert not result.record.fallback
        assert result.record.deployment == DEPLOYMENT or (
            result.served_by == "robot" and result.record.deployment is None
        )
        np.testing.assert_allclose(
            result.outputs["logits"], split.run_full(result.feeds)["logits"], atol=TOLERANCE
        )


def test_hedged_frame_with_a_slow_cloud_is_served_by_the_robot_without_waiting(
    zenoh_router: Router,
    model_file: Path,
    split: SplitModel,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
    tmp_path: Path,
) -> None:
    deployment(lambda frame: "slow")
    policy = HedgeAlways(_cut_table(split))
    frames = 2
    telemetry = tmp_path / "robot-1.jsonl"
    run = run_robot(
        fleet_config(zenoh_router.endpoint, model_file, deadline_s=SHORT_DEADLINE_S),
        frames,
        policy=policy,
        telemetry=telemetry,
    )
    assert_no_frame_lost(run, frames)
    for result, outcome in zip(run.results, policy.seen.of(run.results), strict=True):
        assert result.served_by == "robot"
        assert result.record.latency_s < SHORT_DEADLINE_S  # served by the robot, not the wait
        # Handed on when served: the reply's fate was not known then.
        assert not result.record.fallback and result.record.reason is None
        assert outcome.cloud_s is None and outcome.waited_s == SHORT_DEADLINE_S
    # The telemetry has the complete records: the cloud timed out.
    lines = [json.loads(line) for line in telemetry.read_text().splitlines()]
    assert [(obj["frame"], obj["reason"]) for obj in lines] == [(0, "timeout"), (1, "timeout")]
    assert run.daemon.summary.reasons == {"timeout": frames}


def test_a_hedged_frame_served_by_the_robot_is_handed_on_before_its_reply(
    zenoh_router: Router,
    model_file: Path,
    split: SplitModel,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
) -> None:
    """The reply comes within the deadline but after the robot's own result: the result goes
    to its consumers when served, not when the reply settles (then it came after the next
    frame's), and its telemetry still gets the reply's figures."""
    dep = deployment(lambda frame: "delayed")
    policy = HedgeAlways(_cut_table(split))
    handed_at: dict[int, float] = {}
    frames = 3
    run = run_robot(
        fleet_config(zenoh_router.endpoint, model_file),
        frames,
        policy=policy,
        on_result=lambda result: handed_at.setdefault(result.frame, time.perf_counter()),
    )
    assert_no_frame_lost(run, frames)
    assert [r.frame for r in run.results] == list(range(frames))  # in frame order
    for result in run.results:
        assert result.served_by == "robot" and not result.record.fallback
        assert handed_at[result.frame] < dep.replied_at[result.frame]
    # The replies still reached the learner.
    assert all(outcome.cloud_s is not None for outcome in policy.seen.outcomes.values())


def test_unreachable_registry_is_named_and_frames_are_computed_locally(
    free_port_factory: Callable[[], int],
    model_file: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port_factory()}"  # nothing listens there
    caplog.set_level(logging.WARNING, logger="robotd")
    run = run_robot(fleet_config(endpoint, model_file), registry_wait_s=0.2)
    assert_no_frame_lost(run, FRAMES)
    assert all(r.reason == "no_route" for r in run.records)
    assert any(f"registry at {endpoint} not reachable" in m for m in caplog.messages)


@pytest.mark.skipif(not can_trim(), reason="glibc's malloc_trim only")
def test_startup_returns_the_heap_memory_its_model_runs_freed(
    free_port_factory: Callable[[], int],
    model_file: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The warm-up and profile runs' freed tensors stayed resident (~1.1 GB with zoo:stereo at
    640x480) until the robot trimmed its heap after startup."""
    endpoint = f"tcp/127.0.0.1:{free_port_factory()}"  # frames are finished on the robot
    caplog.set_level(logging.INFO, logger="common.heap")
    run = run_robot(fleet_config(endpoint, model_file), frames=2, registry_wait_s=0.2)
    assert_no_frame_lost(run, 2)
    assert any(f"{ROBOT}: freed startup memory returned" in m for m in caplog.messages)


def test_probes_report_every_live_deployment_and_routes_reach_requests(
    zenoh_router: Router,
    model_file: Path,
    open_peer: Callable[..., zenoh.Session],
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
    wait_for_token: Callable[..., None],
) -> None:
    """The robot runs in a thread until stopped: one deployment answers probes, another is
    alive but silent; a RouteChange published by the 'registry' shows up in the requests."""
    dep = deployment()
    cloud = open_peer()
    probes: list[ProbeRequest] = []

    def on_probe(query: zenoh.Query) -> None:
        payload = query.payload
        request = ProbeRequest.from_wire(payload.to_bytes() if payload is not None else b"")
        probes.append(request)
        reply = ProbeReply(
            deployment=DEPLOYMENT,
            protocol_version=PROTOCOL_VERSION,
            capabilities=("infer", "probe", "ctl"),
            service=SERVICE,
            model_digest="d",
            states={},
            load=1,
            capacity=5,
            echo=b"\0" * request.echo_bytes,
        )
        query.reply(query.key_expr, reply.to_wire())

    held = [
        cloud.declare_queryable(keys.dep_probe(FLEET, DEPLOYMENT), on_probe),
        cloud.liveliness().declare_token(keys.alive_deployment(FLEET, DEPLOYMENT)),
        cloud.liveliness().declare_token(keys.alive_deployment(FLEET, "edge-2")),
    ]
    reports: dict[str, ProbeReport] = {}
    both = threading.Event()

    def on_report(sample: zenoh.Sample) -> None:
        report = decode(sample.payload.to_bytes(), expect=ProbeReport)
        reports[report.deployment] = report
        if {DEPLOYMENT, "edge-2"} <= set(reports):
            both.set()

    watcher = fake_registry
    sub = watcher.declare_subscriber(keys.tele_probe(FLEET, ROBOT), on_report)
    daemon = RobotDaemon(
        fleet_config(
            zenoh_router.endpoint,
            model_file,
            machines={
                DEPLOYMENT: {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]},
                ROBOT: {"role": "robot", "listen": ["tcp/127.0.0.1:0"], "fps": 20.0},
            },
        ),
        ROBOT,
        RobotOptions(probe_interval_s=0.2, registry_wait_s=WAIT_S, route_wait_s=WAIT_S),
    )
    thread = threading.Thread(target=daemon.run, name="robot-under-test")
    thread.start()
    try:
        wait_for_token(watcher, keys.alive_robot(FLEET, ROBOT))
        assert both.wait(WAIT_S), f"probe reports: {sorted(reports)}"
        change = RouteChange(robot=ROBOT, deployment=DEPLOYMENT, epoch=7, reason="test", at=0.0)
        watcher.put(keys.route(FLEET, ROBOT), change.to_wire())
        seen = threading.Event()
        for _ in range(int(WAIT_S / 0.05)):  # bounded: each step waits for a new answer
            if any(r.epoch == 7 for r in dep.requests):
                seen.set()
                break
            dep.answered.clear()
            dep.answered.wait(0.05)
        assert seen.is_set(), "no request carried the new route's epoch"
    finally:
        daemon.stop()
        thread.join(STOP_WITHIN_S)
        sub.undeclare()
        for item in held:
            item.undeclare()
    assert not thread.is_alive(), f"the daemon did not stop within {STOP_WITHIN_S} s"
    ok, silent = reports[DEPLOYMENT], reports["edge-2"]
    assert ok.ok and ok.rtt_s is not None and ok.rtt_s > 0
    assert (ok.load, ok.capacity) == (1, 5) and ok.up_bytes > 0 and ok.down_bytes > 4096
    assert not silent.ok and silent.reason and "no probe reply" in silent.reason
    assert probes and len(probes[0].padding) > 0
    assert daemon.route == (DEPLOYMENT, 7)


def test_uplink_emulation_paces_requests_and_times_out_what_cannot_arrive(
    zenoh_router: Router,
    model_file: Path,
    deployment: Callable[..., FakeDeployment],
    fake_registry: zenoh.Session,
) -> None:
    """`--uplink-mbit`: once the bucket's burst is spent, each request waits its bytes' time on
    the emulated link (counted in transfer_s); a request the link cannot deliver before the
    deadline is never sent, and the frame times out at the deadline as on a real link."""
    dep = deployment()
    cfg = fleet_config(zenoh_router.endpoint, model_file)
    slow_mbit = 0.4
    frames = 12
    run = run_robot(cfg, frames, uplink_mbit=slow_mbit)
    assert_no_frame_lost(run, frames)
    link_s = [r.bytes_up * BITS_PER_BYTE / (slow_mbit * 1e6) for r in run.records]
    paced = run.records[-3:]  # the burst is long spent by then
    for record, expected in zip(paced, link_s[-3:], strict=True):
        assert not record.fallback
        assert record.transfer_s >= 0.8 * expected, (record.transfer_s, expected)
    assert len(dep.requests) == frames

    crawl_mbit = 0.01  # a request needs seconds: far past the deadline
    sent_before = len(dep.requests)
    crawl_frames = 7  # the burst lets the first few through; the rest cannot make it
    crawl = run_robot(cfg, crawl_frames, uplink_mbit=crawl_mbit)
    assert_no_frame_lost(crawl, crawl_frames)
    late = [r for r in crawl.records if r.reason == "timeout"]
    assert late and all(r.fallback and r.latency_s >= DEADLINE_S for r in late)
    assert len(dep.requests) - sent_before == crawl_frames - len(late)  # late ones never left
