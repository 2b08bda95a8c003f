"""The robot's frame and hedging loop (`robotd.frame_path.frame_loop.FrameLoop`) driven without
Zenoh (STYLE 19): a fake request sender starts each frame's real `CloudCall` over a scripted
cloud that stands in for the session (the test answers each query when it chooses, from the
thread it chooses), the low-priority local-run thread is played in the caller's thread, and the
policy, the source and the sinks are fakes that note what happened in one timeline. The model,
the model runs, the registry link, the telemetry record and the run summary are the real ones.

Nothing waits for time to pass: the cloud answers when the test's script says so, and waits for
a query to arrive with a timeout; only the frames of the deadline test have a deadline short
enough to be reached (their outcome does not depend on how late the loop looks).

Regressions guarded against: a hedged frame the robot served first held back until its reply
came (its result reached the consumers after the next frame's); a reply after the deadline
applied, or recorded twice; a frame answered NOT_SERVING, or whose route moved under it, lost or
finished on the robot while a serving deployment could answer it; results handed on out of order.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from common.config import fleet_from_dict
from common.partition import split_model
from common.partition.runtime import SplitModel
from common.throttled_log import ThrottledLog
from common.wire import ErrorCode, ErrorReply, Message
from common.wire.cloud_to_robot import InferReply
from common.wire.registry import RouteChange
from common.wire.telemetry import FallbackReason, ResendReason, TelemetryRecord
from common.wire.tensor_codecs import EncodedTensor
from robotd.emulation import Emulation, Slowdown
from robotd.frame_path.frame import Frame, FrameResult
from robotd.frame_path.frame_loop import FrameLoop
from robotd.frame_path.local_runs import LocalJob, LocalRunner
from robotd.frame_path.model_runs import ModelRuns
from robotd.frame_path.offload import NO_ROUTE_RESENDS, CallResult, CloudCall
from robotd.frame_path.probes import CloudTime
from robotd.frame_path.registry_link import RegistryLink, Route
from robotd.policies import Decision, FrameContext, Objective, Outcome, Policy
from robotd.robot_model import RobotModel
from robotd.sources.frame_sources import EndOfStream, FrameSource
from robotd.telemetry import SERVED_BY_CLOUD, SERVED_BY_ROBOT, RunSummary
from robotd.telemetry_sink import TelemetrySink
from tests.helpers.observed import ObservedByFrame
from tests.helpers.onnx_graphs import make_model, node, save, vi

FLEET = "unit"
SERVICE = "vision"
ROBOT = "robot-1"
OLD, NEW = "edge-1", "edge-2"
KEY = "ef/unit/svc/vision/robot-1/infer"  # only named in the scripted queries
IMAGE_SHAPE = (1, 3, 4, 4)
CUT = 1  # the cut after the first node (its prefix and suffix both run something)
# The longest a test waits for what another thread does (a query to arrive), and for the
# loop to finish: a loop still running then is stopped and the test fails.
WAIT_S = 10.0
# The deadline of frames the test answers itself: never reached while a test passes (past the
# wait above, so a loop that waits for it fails instead).
DEADLINE_S = 3 * WAIT_S
# The deadline of frames nobody answers in time: reached at once.
SHORT_DEADLINE_S = 0.05
MAX_REPLY_BYTES = 1 << 20
# What the cloud answers for frame n (the robot's own outputs, a sigmoid, are in (0, 1)).
CLOUD_BASE = 10.0


def cloud_value(frame: int) -> float:
    return CLOUD_BASE + frame


def image(frame: int) -> np.ndarray:
    """Frame `frame` of the source: a small BGR image of its own."""
    return np.random.default_rng(frame).integers(0, 256, (4, 4, 3), dtype=np.uint8)


@pytest.fixture(autouse=True)
def no_zenoh_session(monkeypatch: pytest.MonkeyPatch) -> None:
    """These tests run without a network: opening a Zenoh session fails the test."""

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a unit test of the frame loop opened a Zenoh session")

    monkeypatch.setattr(zenoh, "open", refuse)


# -- the scripted cloud (Zenoh's part of a CloudCall) ----------------------------------------------
@dataclass(frozen=True)
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass(frozen=True)
class _Sample:
    payload: _Payload


@dataclass(frozen=True)
class _Reply:
    """A `zenoh.Reply` as `CloudCall` reads it."""

    ok: _Sample | None
    err: _Sample | None = None


@dataclass
class Query:
    """One query of a frame as Zenoh would route it: `resend` when sent again (target ALL, no
    consolidation); the test answers it through the call's own handler."""

    frame: int
    resend: bool
    consolidation: Any
    handler: Any  # the call's zenoh.handlers.Callback

    def reply(self, message: Message) -> None:
        self.handler.callback(_Reply(ok=_Sample(_Payload(message.to_wire()))))

    def finish(self) -> None:
        """Zenoh ends the query (after its replies, or with none: no deployment serves it)."""
        self.handler.drop()

    def answer(self, message: Message) -> None:
        self.reply(message)
        self.finish()


def infer_reply(frame: int, deployment: str = OLD, epoch: int = 1) -> InferReply:
    return InferReply(
        frame=frame,
        deployment=deployment,
        epoch=epoch,
        outputs={"y": np.full(IMAGE_SHAPE, cloud_value(frame), np.float32)},
        queue_s=0.001,
        compute_s=0.002,
    )


def not_serving(deployment: str) -> ErrorReply:
    return ErrorReply.make(ErrorCode.NOT_SERVING, f"{deployment} does not serve robot-1")


class ScriptedCloud:
    """Every query of every frame, kept in arrival order; `script[frame]` answers a query of
    that frame as it arrives (on the thread that sends it), else it waits for the test."""

    def __init__(self) -> None:
        self.script: dict[int, Callable[[Query], None]] = {}
        self._queries: list[Query] = []
        self._arrived = threading.Condition()

    def session_for(self, frame: int) -> _FrameSession:
        return _FrameSession(self, frame)

    def arrive(self, query: Query) -> None:
        with self._arrived:
            self._queries.append(query)
            self._arrived.notify_all()
        action = self.script.get(query.frame)
        if action is not None:
            action(query)

    def queries(self, frame: int) -> list[Query]:
        with self._arrived:
            return [q for q in self._queries if q.frame == frame]

    def query(self, frame: int, index: int = 0) -> Query:
        """Query number `index` of `frame`, once it has arrived (a background send)."""
        with self._arrived:
            if not self._arrived.wait_for(lambda: len(self.queries(frame)) > index, WAIT_S):
                pytest.fail(f"query {index} of frame {frame} did not arrive within {WAIT_S} s")
            return self.queries(frame)[index]


class _FrameSession:
    """What one frame's `CloudCall` takes for its session: `get` hands the query to the cloud."""

    def __init__(self, cloud: ScriptedCloud, frame: int) -> None:
        self._cloud = cloud
        self._frame = frame

    def get(self, key: str, handler: Any, **options: Any) -> None:
        assert key == KEY
        resend = options["target"] == zenoh.QueryTarget.ALL
        self._cloud.arrive(Query(self._frame, resend, options["consolidation"], handler))


# -- the robot's fakes -----------------------------------------------------------------------------
@dataclass(frozen=True)
class Sent:
    frame: int
    cut: int
    epoch: int
    background: bool


class FakeSender:
    """Stands in for `RequestSender`: notes what each frame was sent with and starts a real
    `CloudCall` over the scripted cloud (so its classification and resends are the robot's own),
    with `served` saying at once that a deployment serves the key."""

    def __init__(self, cloud: ScriptedCloud, deadline_s: float, timeline: list[str]) -> None:
        self._cloud = cloud
        self._deadline_s = deadline_s
        self._timeline = timeline
        self.sent: list[Sent] = []
        self.served_asked = 0

    def _served(self, timeout_s: float) -> bool:
        self.served_asked += 1
        return True

    def send(
        self,
        frame: int,
        cut: int,
        tensors: dict[str, EncodedTensor],
        epoch: int,
        *,
        background: bool = False,
        end: int | None = None,
        member: str | None = None,
    ) -> CloudCall:
        self._timeline.append(f"send {frame}")
        self.sent.append(Sent(frame, cut, epoch, background))
        call = CloudCall(
            self._cloud.session_for(frame),  # type: ignore[arg-type]
            KEY,
            f"frame {frame} after cut {cut}".encode(),
            frame=frame,
            budget_s=self._deadline_s,
            max_reply_bytes=MAX_REPLY_BYTES,
            served=self._served,
        )
        call.start(background=background)
        return call


class InlineRunner(LocalRunner):
    """The low-priority local-run thread, played in the caller's thread: a job runs as it is
    submitted (so it is done before anything else can happen) and is noted in the timeline."""

    def __init__(self, timeline: list[str]) -> None:
        super().__init__("inline-local-run")
        self._timeline = timeline

    def submit(self, fn: Any, wake: threading.Event | None = None) -> LocalJob:
        self._timeline.append("low-priority run")
        job = LocalJob(fn, wake)
        job.run()
        return job


class ScriptedPolicy(Policy):
    """Decides each frame with `decide(n)`; keeps what it observes, by frame."""

    name = "scripted"

    def __init__(self, decide: Callable[[int], Decision], timeline: list[str]) -> None:
        self._decide = decide
        self._timeline = timeline
        self.seen = ObservedByFrame()

    def decide(self, ctx: FrameContext) -> Decision:
        self._timeline.append(f"decide {ctx.index}")
        return self.seen.decided(self._decide(ctx.index), ctx.index)

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        self.seen.observed(decision, outcome)


class ScriptedSource(FrameSource):
    """`frames` images, then the end of the stream; `before[n]` runs (in the loop's thread)
    before frame n is read (n = `frames`: before the end is); keeps the results handed back."""

    description = "scripted source"

    def __init__(self, frames: int, before: dict[int, Callable[[], None]]) -> None:
        self.frames = frames
        self.before = before
        self.read_count = 0
        self.results: list[FrameResult] = []

    def wait_ready(self, timeout_s: float) -> bool:
        hook = self.before.pop(self.read_count, None)
        if hook is not None:
            hook()
        return True

    def read(self) -> np.ndarray:
        if self.read_count >= self.frames:
            raise EndOfStream()
        self.read_count += 1
        return image(self.read_count - 1)

    def on_result(self, result: FrameResult) -> None:
        self.results.append(result)


class RecordingSink(TelemetrySink):
    """The robot's telemetry sink (counting into the run summary), keeping each frame's record;
    `after[n]` runs once frame n's record is made."""

    def __init__(self, summary: RunSummary, timeline: list[str]) -> None:
        super().__init__(ROBOT, summary)
        self._timeline = timeline
        self.records: dict[int, TelemetryRecord] = {}
        self.served_by: dict[int, str] = {}
        self.results: dict[int, CallResult | None] = {}
        self.after: dict[int, Callable[[], None]] = {}

    def frame(self, f: Frame, record: TelemetryRecord, *, phase: str | None) -> None:
        assert f.n not in self.records, f"frame {f.n} recorded twice"
        self._timeline.append(f"record {f.n}")
        self.records[f.n] = record
        self.served_by[f.n] = f.served_by
        self.results[f.n] = f.result
        super().frame(f, record, phase=phase)
        hook = self.after.pop(f.n, None)
        if hook is not None:
            hook()


@dataclass
class ResultList:
    """A result sink (`robotd.results.sinks.ResultSink`) that keeps what it is handed."""

    results: list[FrameResult] = field(default_factory=list)

    def publish(self, result: FrameResult) -> None:
        self.results.append(result)

    def close(self) -> None:
        pass


# -- the robot -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """image → Relu → Neg → Sigmoid → y."""
    graph = make_model(
        [
            node("Relu", ["image"], ["a"]),
            node("Neg", ["a"], ["b"]),
            node("Sigmoid", ["b"], ["y"]),
        ],
        [vi("image", list(IMAGE_SHAPE))],
        [vi("y", list(IMAGE_SHAPE))],
    )
    return save(graph, tmp_path_factory.mktemp("frame-loop") / "m.onnx")


@pytest.fixture(scope="module")
def split(model_file: Path) -> Iterator[SplitModel]:
    """The model split at every cut, as the robot's sessions."""
    model = SplitModel(split_model(model_file, model_file.parent / "split"), threads=1)
    yield model
    model.close()


@dataclass
class Robot:
    """A frame loop over fakes, and what the test looks at."""

    loop: FrameLoop
    cloud: ScriptedCloud
    sender: FakeSender
    source: ScriptedSource
    policy: ScriptedPolicy
    sink: RecordingSink
    result_sink: ResultList
    link: RegistryLink
    summary: RunSummary
    timeline: list[str]
    applied: list[FrameResult]
    robot_model: RobotModel
    stop: threading.Event

    def run(self) -> None:
        """Run the loop to the source's end; one still running after WAIT_S is stopped (its
        frames then finish at once) and fails the test."""
        watchdog = threading.Timer(WAIT_S, self.stop.set)
        watchdog.daemon = True
        watchdog.start()
        try:
            self.loop.run(frames=None, fps=None)
        finally:
            watchdog.cancel()
        assert not self.stop.is_set(), f"the frame loop was still running after {WAIT_S} s"

    def local_outputs(self, frame: int) -> np.ndarray:
        """What the robot computes for `frame` itself."""
        feeds = self.robot_model.feeds(image(frame))
        return self.robot_model.model.run_full(feeds)["y"]

    def outcome(self, frame: int) -> Outcome:
        """What the policy was told of `frame`."""
        return self.policy.seen.outcomes[frame]


class _NoSession:
    """The registry link's session: the loop must not use it (no registry is up)."""

    def __getattr__(self, name: str) -> Any:
        raise AssertionError(f"the frame loop used the registry link's session ({name})")


MakeRobot = Callable[..., Robot]


@pytest.fixture
def make_robot(split: SplitModel, model_file: Path) -> Iterator[MakeRobot]:
    """`make_robot(decide, frames, ...)`: a frame loop whose route is edge-1 at epoch 1."""
    stops: list[threading.Event] = []

    def make(
        decide: Callable[[int], Decision],
        frames: int,
        *,
        deadline_s: float = DEADLINE_S,
        max_in_flight: int = 1,
        before: dict[int, Callable[[], None]] | None = None,
    ) -> Robot:
        timeline: list[str] = []
        applied: list[FrameResult] = []
        cloud = ScriptedCloud()
        summary = RunSummary(ROBOT)
        sink = RecordingSink(summary, timeline)
        source = ScriptedSource(frames, before or {})
        result_sink = ResultList()
        stop = threading.Event()
        stops.append(stop)
        config = fleet_from_dict(
            {
                "fleet": FLEET,
                "service": SERVICE,
                "model": str(model_file),
                "latency_bound": {"stat": "median", "seconds": 0.1},
                "deadline_s": deadline_s,
            }
        )
        link = RegistryLink(
            _NoSession(),  # type: ignore[arg-type]
            config,
            ROBOT,
            model_digest=split.digest,
            throttled=ThrottledLog(logging.getLogger("robotd")),
            guard=lambda callback, what=None: callback,
        )
        link.apply_route(RouteChange(robot=ROBOT, deployment=OLD, epoch=1, reason="initial", at=0))
        runner = InlineRunner(timeline)
        slowdown = Slowdown(stop=stop)
        robot_model = RobotModel(split, "tiny")

        def on_result(result: FrameResult) -> None:
            timeline.append(f"apply {result.frame}")
            applied.append(result)

        sender = FakeSender(cloud, deadline_s, timeline)
        policy = ScriptedPolicy(decide, timeline)
        loop = FrameLoop(
            robot=ROBOT,
            model=split,
            robot_model=robot_model,
            policy=policy,
            objective=Objective(),
            deadline_s=deadline_s,
            source=source,
            requests=sender,  # type: ignore[arg-type]
            link=link,
            runs=ModelRuns(slowdown, runner),
            local=runner,
            slowdown=slowdown,
            emulation=Emulation([], slowdown, lambda bucket: None, robot=ROBOT),
            sink=sink,
            summary=summary,
            cloud_time=CloudTime(),
            stop=stop,
            throttled=ThrottledLog(logging.getLogger("robotd")),
            max_in_flight=max_in_flight,
            result_sinks=[result_sink],
            on_result=on_result,
        )
        return Robot(
            loop,
            cloud,
            sender,
            source,
            policy,
            sink,
            result_sink,
            link,
            summary,
            timeline,
            applied,
            robot_model,
            stop,
        )

    yield make
    for stop in stops:  # a failed test lets go of whatever still waits
        stop.set()


def offload(frame: int) -> Decision:
    return Decision(CUT)


def answer_at_once(deployment: str = OLD, epoch: int = 1) -> Callable[[Query], None]:
    return lambda q: q.answer(infer_reply(q.frame, deployment, epoch))


def handed_on(robot: Robot) -> list[tuple[int, str]]:
    """(frame, served by) of each result handed on, as `on_result` saw them; the result sinks
    and the source must have been handed the same, in the same order."""
    seen = [(r.frame, r.served_by) for r in robot.applied]
    assert [(r.frame, r.served_by) for r in robot.result_sink.results] == seen
    assert [(r.frame, r.served_by) for r in robot.source.results] == seen
    return seen


# -- hedging
# -----------------------------------------------------------------------------------------
def test_a_hedged_frame_the_robot_serves_first_is_handed_on_before_its_reply(
    make_robot: MakeRobot,
) -> None:
    """Frame 0 is hedged and its reply is held back until frame 1 is sent: the robot's own
    result serves frame 0 and is handed on at once; frame 1's model runs go to the low-priority
    thread while that reply is out; the late reply completes frame 0's record and feeds the
    learner, and is never applied."""

    def release_frame_0_then_answer(q: Query) -> None:
        robot.cloud.query(0).answer(infer_reply(0))
        robot.timeline.append("cloud answers 0")
        q.answer(infer_reply(1))

    robot = make_robot(lambda n: Decision(CUT, hedge=n == 0), frames=2)
    robot.cloud.script[1] = release_frame_0_then_answer
    robot.run()

    assert robot.timeline == [
        "decide 0",
        "send 0",
        "low-priority run",  # frame 0's local suffix, raced against the cloud
        "apply 0",  # served by the robot before its reply
        "decide 1",
        "low-priority run",  # frame 1's prefix, while frame 0's reply is awaited
        "send 1",
        "cloud answers 0",
        "record 1",
        "apply 1",
        "record 0",  # frame 0's telemetry, complete once its reply came
    ]
    assert handed_on(robot) == [(0, SERVED_BY_ROBOT), (1, SERVED_BY_CLOUD)]
    first = robot.applied[0]
    assert first.hedged
    np.testing.assert_array_equal(first.outputs["y"], robot.local_outputs(0))
    # As known when it was handed on: the reply still out, no fallback.
    assert (first.record.fallback, first.record.deployment, first.record.bytes_down) == (
        False,
        None,
        0,
    )
    assert np.all(robot.applied[1].outputs["y"] == cloud_value(1))

    record = robot.sink.records[0]
    assert robot.sink.served_by[0] == SERVED_BY_ROBOT
    assert (record.fallback, record.reason, record.deployment) == (False, None, OLD)
    assert record.bytes_down > 0
    outcome = robot.outcome(0)
    assert outcome.cloud_s is not None and outcome.waited_s is None  # the learner is fed
    assert outcome.local_s is not None
    assert robot.sender.sent[0].background  # a hedged request never blocks the local run
    assert (robot.summary.hedged, robot.summary.served_by_robot, robot.summary.fallbacks) == (
        1,
        1,
        0,
    )


def test_a_hedged_frame_answered_within_the_deferral_never_runs_locally(
    make_robot: MakeRobot,
) -> None:
    """The policy defers the local run by the whole deadline; the reply comes at once and
    serves the frame: no local run is started."""
    robot = make_robot(lambda n: Decision(CUT, hedge=True, hedge_after_s=DEADLINE_S), frames=1)
    robot.cloud.script[0] = answer_at_once()
    robot.run()

    assert "low-priority run" not in robot.timeline
    assert handed_on(robot) == [(0, SERVED_BY_CLOUD)]
    assert np.all(robot.applied[0].outputs["y"] == cloud_value(0))
    record = robot.sink.records[0]
    assert (record.fallback, record.deployment, record.suffix_local_s) == (False, OLD, 0.0)
    assert robot.outcome(0).local_s is None


# -- the deadline ----------------------------------------------------------------------------------
@pytest.mark.parametrize("hedged", [False, True], ids=["offloaded", "hedged"])
def test_a_reply_after_the_deadline_is_neither_applied_nor_recorded_again(
    make_robot: MakeRobot, hedged: bool
) -> None:
    """No reply within the deadline: the robot finishes (or has served) the frame itself, as a
    `timeout`; the reply that comes once the frame is recorded changes nothing."""

    def late_reply() -> None:
        robot.cloud.query(0).answer(infer_reply(0))
        robot.timeline.append("cloud answers 0 late")

    robot = make_robot(lambda n: Decision(CUT, hedge=hedged), frames=1, deadline_s=SHORT_DEADLINE_S)
    robot.sink.after[0] = late_reply
    robot.run()

    assert "cloud answers 0 late" in robot.timeline  # the late reply did come
    assert handed_on(robot) == [(0, SERVED_BY_ROBOT)]
    np.testing.assert_array_equal(robot.applied[0].outputs["y"], robot.local_outputs(0))
    assert list(robot.sink.records) == [0]
    record = robot.sink.records[0]
    assert robot.sink.served_by[0] == SERVED_BY_ROBOT
    assert (record.fallback, record.reason, record.deployment) == (
        True,
        FallbackReason.TIMEOUT,
        None,
    )
    outcome = robot.outcome(0)
    assert (outcome.cloud_s, outcome.waited_s) == (None, SHORT_DEADLINE_S)
    assert outcome.local_s is not None
    assert dict(robot.summary.reasons) == {FallbackReason.TIMEOUT.value: 1}


# -- resends and moves -----------------------------------------------------------------------------
def test_a_frame_answered_not_serving_is_sent_again_and_served_by_the_cloud(
    make_robot: MakeRobot,
) -> None:
    """The deployment the query reached is in standby and answers NOT_SERVING: the query is sent
    again (target ALL, no consolidation) and the serving deployment's reply serves the frame."""

    def standby_then_serving(q: Query) -> None:
        if q.resend:
            q.answer(infer_reply(0, NEW, 2))
        else:
            q.answer(not_serving(OLD))

    robot = make_robot(offload, frames=1)
    robot.cloud.script[0] = standby_then_serving
    robot.run()

    first, again = robot.cloud.queries(0)
    assert (first.resend, again.resend) == (False, True)
    assert again.consolidation == zenoh.ConsolidationMode.NONE
    assert robot.sender.served_asked == 1  # waited for a serving deployment before resending
    assert handed_on(robot) == [(0, SERVED_BY_CLOUD)]
    assert np.all(robot.applied[0].outputs["y"] == cloud_value(0))
    record = robot.sink.records[0]
    assert (record.fallback, record.deployment, record.epoch, record.resends) == (
        False,
        NEW,
        2,
        1,
    )
    result = robot.sink.results[0]
    assert result is not None and result.resends == (ResendReason.NOT_SERVING,)
    assert robot.summary.resends == 1


def test_a_frame_only_ever_answered_not_serving_is_finished_on_the_robot(
    make_robot: MakeRobot,
) -> None:
    """NOT_SERVING to every query: after its resends the frame is finished on the robot (the
    refusal is an error reply), not lost, and never computed by the refusing deployment."""
    robot = make_robot(offload, frames=1)
    robot.cloud.script[0] = lambda q: q.answer(not_serving(OLD))
    robot.run()

    assert len(robot.cloud.queries(0)) == 1 + NO_ROUTE_RESENDS
    assert handed_on(robot) == [(0, SERVED_BY_ROBOT)]
    np.testing.assert_array_equal(robot.applied[0].outputs["y"], robot.local_outputs(0))
    record = robot.sink.records[0]
    assert (record.fallback, record.reason, record.resends) == (
        True,
        FallbackReason.ERROR,
        NO_ROUTE_RESENDS,
    )
    result = robot.sink.results[0]
    assert result is not None
    assert result.resends == (ResendReason.NOT_SERVING,) * NO_ROUTE_RESENDS


def test_a_move_in_the_middle_of_a_frame_is_answered_by_the_new_deployment(
    make_robot: MakeRobot,
) -> None:
    """Frame 0 is sent to edge-1 at epoch 1; while it is out the registry moves the robot to
    edge-2 (epoch 2) and edge-1 withdraws the key, so the query ends without a reply. It is sent
    again and edge-2 answers it; frame 1 goes out under the new route's epoch."""

    def moved_while_out(q: Query) -> None:
        if q.resend:
            q.answer(infer_reply(0, NEW, 2))
            return
        robot.link.apply_route(
            RouteChange(robot=ROBOT, deployment=NEW, epoch=2, reason="bound_violation", at=0)
        )
        q.finish()  # edge-1 no longer serves the key: no reply

    robot = make_robot(offload, frames=2)
    robot.cloud.script[0] = moved_while_out
    robot.cloud.script[1] = answer_at_once(NEW, 2)
    robot.run()

    assert [(s.frame, s.epoch) for s in robot.sender.sent] == [(0, 1), (1, 2)]
    assert robot.link.held == Route(NEW, 2, known=True)
    assert handed_on(robot) == [(0, SERVED_BY_CLOUD), (1, SERVED_BY_CLOUD)]
    for applied in robot.applied:
        assert np.all(applied.outputs["y"] == cloud_value(applied.frame))
    moved = robot.sink.records[0]
    assert (moved.fallback, moved.deployment, moved.epoch, moved.resends) == (False, NEW, 2, 1)
    assert moved.suffix_local_s == 0.0  # nothing was computed twice on the robot
    result = robot.sink.results[0]
    assert result is not None and result.resends == (ResendReason.NO_REPLY,)
    assert (robot.sink.records[1].deployment, robot.sink.records[1].resends) == (NEW, 0)


# -- frames in flight ------------------------------------------------------------------------------
def test_replies_that_arrive_out_of_order_are_handed_on_in_frame_order(
    make_robot: MakeRobot,
) -> None:
    """Three frames in flight, answered newest first: each result is handed on, oldest first,
    with its own frame's outputs."""

    def answer_newest_first() -> None:
        for frame in (2, 1, 0):
            robot.cloud.query(frame).answer(infer_reply(frame))
            robot.timeline.append(f"cloud answers {frame}")

    robot = make_robot(offload, frames=3, max_in_flight=4, before={3: answer_newest_first})
    robot.run()

    answered = [e for e in robot.timeline if e.startswith(("cloud answers", "apply"))]
    assert answered == [
        "cloud answers 2",
        "cloud answers 1",
        "cloud answers 0",
        "apply 0",
        "apply 1",
        "apply 2",
    ]
    assert handed_on(robot) == [(n, SERVED_BY_CLOUD) for n in range(3)]
    for result in robot.applied:
        assert np.all(result.outputs["y"] == cloud_value(result.frame))
        assert not result.record.stale
    assert all(s.background for s in robot.sender.sent)  # sent beside the frames in flight
    assert robot.summary.stale_dropped == 0


def test_an_older_reply_after_a_newer_result_was_applied_is_dropped_as_stale(
    make_robot: MakeRobot,
) -> None:
    """Frame 1's reply comes and is applied while frame 0's is still out; frame 0's reply
    comes later: it would take the consumers back in time, so it is dropped and counted, but
    still recorded and fed to the policy. Frames 2 and 3 are handed on after frame 1."""

    def answer(*frames: int) -> Callable[[], None]:
        def hook() -> None:
            for frame in frames:
                robot.cloud.query(frame).answer(infer_reply(frame))
                robot.timeline.append(f"cloud answers {frame}")

        return hook

    robot = make_robot(
        offload,
        frames=4,
        max_in_flight=4,
        before={2: answer(1), 3: answer(0, 2), 4: answer(3)},
    )
    robot.run()

    assert handed_on(robot) == [(n, SERVED_BY_CLOUD) for n in (1, 2, 3)]
    assert robot.timeline.index("apply 1") < robot.timeline.index("cloud answers 0")
    for result in robot.applied:
        assert np.all(result.outputs["y"] == cloud_value(result.frame))
    stale = robot.sink.records[0]
    assert (stale.stale, stale.fallback, stale.deployment) == (True, False, OLD)
    assert [robot.sink.records[n].stale for n in (1, 2, 3)] == [False, False, False]
    assert sorted(robot.policy.seen.outcomes) == [0, 1, 2, 3]  # frame 0 still taught the policy
    assert robot.summary.stale_dropped == 1
