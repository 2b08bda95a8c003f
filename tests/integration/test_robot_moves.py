"""A move of a robot between deployments, seen from the robot's queries (real Zenoh sessions on
loopback: the registry's router, two deployment peers, the robot peer).

The deployments move the robot's complete service queryable make-before-break, as the switch
protocol does (the new one declares, the old one undeclares after): here the robot has seen the
new declaration before the old one is withdrawn (the new deployment's token, declared after its
queryable on the same session, is seen first), a frame is sent while both declare the key and
one while the old one, in standby, still declares it (answered NOT_SERVING there).
With zenoh 1.10 the robot's BEST_MATCHING route then still points at the old deployment, and
every query finishes at once without a reply (`no_route`) until another declaration changes the
key; `CloudCall` resends such a query within
its deadline (target ALL, after waiting for a matching queryable), so every frame is answered by
the deployment in service and only by it. Each resend is counted, by why it was made, in the
frame's telemetry record, the run summary and the robot's `resends_total` counter.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh
from prometheus_client import CollectorRegistry

from common import keys
from common.wire import ErrorCode, ErrorReply
from common.wire.cloud_to_robot import InferReply
from common.wire.telemetry import FallbackReason, ResendReason
from robotd.frame_path.offload import NO_ROUTE_RESENDS, CallResult, CloudCall
from robotd.metrics import RobotMetrics
from robotd.telemetry import SERVED_BY_CLOUD, RunSummary, frame_record, jsonl_object

FLEET = "moves"
DEADLINE_S = 0.5
MOVES = 4
FRAMES_PER_MOVE = 5
MAX_REPLY_BYTES = 1 << 20


class Deployment:
    """A peer that serves the robot's service key (complete) while in service, and counts the
    queries it computed."""

    def __init__(self, session: zenoh.Session, name: str, key: str) -> None:
        self.session = session
        self.name = name
        self.key = key
        self.computed = 0
        self.serving = False
        self._lock = threading.Lock()
        self._queryable: Any = None
        self._tokens: list[Any] = []

    def _on_query(self, query: zenoh.Query) -> None:
        if not self.serving:  # in standby, key not withdrawn yet: as cloudd.admission answers
            refusal = ErrorReply.make(ErrorCode.NOT_SERVING, f"{self.name} does not serve")
            query.reply(self.key, refusal.to_wire())
            return
        with self._lock:
            self.computed += 1
        assert query.payload is not None
        reply = InferReply(
            frame=int(query.payload.to_bytes()),
            deployment=self.name,
            epoch=0,
            outputs={"y": np.zeros(1, np.float32)},
            queue_s=0.0,
            compute_s=0.0,
        )
        query.reply(self.key, reply.to_wire())

    def service(self, marker: str) -> str:
        """Declare the key, then a token `marker` (seen by a peer only after the queryable)."""
        self.serving = True
        self._queryable = self.session.declare_queryable(self.key, self._on_query, complete=True)
        token_key = keys.alive_deployment(FLEET, marker)
        self._tokens.append(self.session.liveliness().declare_token(token_key))
        return token_key

    def standby(self) -> None:
        """Stop serving; the key stays declared until `withdraw` (cloudd.control's order)."""
        self.serving = False

    def withdraw(self) -> None:
        self._queryable.undeclare()
        self._queryable = None


def _served_waiter(robot: zenoh.Session, key: str) -> tuple[Callable[[float], bool], list[Any]]:
    """The robot daemon's `ServiceMatch.wait_served`: a querier's matching listener."""
    served = threading.Event()
    querier = robot.declare_querier(key)

    def on_matching(status: zenoh.MatchingStatus) -> None:
        if status.matching:
            served.set()
        else:
            served.clear()

    listener = querier.declare_matching_listener(on_matching)
    status: Any = querier.matching_status  # a MatchingStatus (the stub says bool)
    if bool(getattr(status, "matching", status)):
        served.set()
    return served.wait, [querier, listener]


def _frame(robot: zenoh.Session, key: str, frame: int, served: Callable[[float], bool]) -> Any:
    call = CloudCall(
        robot,
        key,
        str(frame).encode(),
        frame=frame,
        budget_s=DEADLINE_S,
        max_reply_bytes=MAX_REPLY_BYTES,
        served=served,
    )
    call.start()
    assert call.wait()
    return call.result()


def _count(results: list[CallResult]) -> tuple[list[int], dict[str, Any], dict[str, float]]:
    """Each frame's `resends` in its JSONL object, the run summary, and the robot's
    `resends_total` by reason, as the robot daemon's telemetry sink counts them."""
    registry = CollectorRegistry()
    metrics = RobotMetrics(registry, "robot-1", lambda: (None, 0))
    summary = RunSummary("robot-1")
    lines = []
    for frame, result in enumerate(results):
        record = frame_record(
            "robot-1", frame, cut=0, codec="raw", result=result, bytes_up=1, prefix_s=0.0,
            local_s=None, latency_s=0.01, cpu_s=0.0, energy_j=0.0, epoch=0,
        )  # fmt: skip
        lines.append(jsonl_object(record, entropy=0.0, hedged=False, served_by=SERVED_BY_CLOUD))
        summary.add(record, hedged=False, served_by=SERVED_BY_CLOUD)
        metrics.frame(record, SERVED_BY_CLOUD, result.resends)
    counter = {
        reason.value: registry.get_sample_value(
            "elasticfog_robot_resends_total", {"robot": "robot-1", "reason": reason.value}
        )
        or 0.0
        for reason in ResendReason
    }
    return [line["resends"] for line in lines], summary.to_json(), counter


def test_frames_after_make_before_break_moves_reach_the_new_deployment(
    open_peer: Callable[..., zenoh.Session], wait_for_token: Callable[..., None]
) -> None:
    key = keys.svc_infer(FLEET, "vision", "robot-1")
    edges = [Deployment(open_peer(), name, key) for name in ("edge-1", "edge-2")]
    robot = open_peer()
    served, _held = _served_waiter(robot, key)
    wait_for_token(robot, edges[0].service("edge-1-in-0"))
    results = [_frame(robot, key, frame, served) for frame in range(FRAMES_PER_MOVE)]
    serving = 0
    for move in range(1, MOVES + 1):
        old, new = edges[serving], edges[1 - serving]
        wait_for_token(robot, new.service(f"{new.name}-in-{move}"))  # make ...
        # A frame while both declare the key (the robot keeps sending during a move): one of
        # them computes it, and the robot's route for the key is cached.
        overlap = _frame(robot, key, 1000 + move, served)
        assert overlap.reason is None, overlap.detail
        old.standby()  # ... before break: the old one answers NOT_SERVING ...
        results.append(_frame(robot, key, 2000 + move, served))
        old.withdraw()  # ... and then withdraws the key
        serving = 1 - serving
        for i in range(FRAMES_PER_MOVE):
            frame = move * FRAMES_PER_MOVE + i
            result = _frame(robot, key, frame, served)
            assert result.reason is not FallbackReason.NO_ROUTE, (move, i, result.detail)
            results.append(result)
    assert all(r.reason is None for r in results), [r.detail for r in results if r.reason]
    per_frame, summary, counter = _count(results)
    # Answered first time before any move; after a move the stale route makes resends.
    assert per_frame[:FRAMES_PER_MOVE] == [0] * FRAMES_PER_MOVE
    assert per_frame == [len(r.resends) for r in results]
    assert summary["resends"] == sum(per_frame) > 0
    assert counter == {
        reason.value: float(sum(r.resends.count(reason) for r in results))
        for reason in ResendReason
    }
    assert counter[ResendReason.NO_REPLY.value] > 0
    # Each frame computed once, by the deployment in service when it was sent.
    assert sum(edge.computed for edge in edges) == len(results) + MOVES
    assert [r.deployment for r in results[FRAMES_PER_MOVE:]] == [
        edges[move % 2].name for move in range(1, MOVES + 1) for _ in range(FRAMES_PER_MOVE + 1)
    ]


def test_resends_are_counted_by_reason(
    open_peer: Callable[..., zenoh.Session], wait_for_token: Callable[..., None]
) -> None:
    """No deployment at all: every resend is `no_reply` (and the frame falls back, no_route);
    one in standby that keeps the key: every resend is `not_serving`; one in service: none."""
    key = keys.svc_infer(FLEET, "vision", "robot-1")
    robot = open_peer()
    served, _held = _served_waiter(robot, key)
    nobody = _frame(robot, key, 0, served)
    assert nobody.reason is FallbackReason.NO_ROUTE, nobody.detail
    edge = Deployment(open_peer(), "edge-1", key)
    wait_for_token(robot, edge.service("edge-1-in"))
    answered = _frame(robot, key, 1, served)
    assert answered.reason is None, answered.detail
    edge.standby()
    refused = _frame(robot, key, 2, served)
    assert refused.reason is FallbackReason.ERROR, refused.detail  # NOT_SERVING is its answer
    assert nobody.resends == (ResendReason.NO_REPLY,) * NO_ROUTE_RESENDS
    assert answered.resends == ()
    assert refused.resends == (ResendReason.NOT_SERVING,) * NO_ROUTE_RESENDS
    per_frame, summary, counter = _count([nobody, answered, refused])
    assert per_frame == [NO_ROUTE_RESENDS, 0, NO_ROUTE_RESENDS]
    assert summary["resends"] == 2 * NO_ROUTE_RESENDS
    # Every reason is served from the start (`keyframe`: h264 frames resent as keyframes).
    assert counter == {
        "no_reply": NO_ROUTE_RESENDS,
        "not_serving": NO_ROUTE_RESENDS,
        "keyframe": 0,
    }
