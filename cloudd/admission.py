"""A cloud daemon's service keys `svc/<service>/<robot>/infer`: decode, check and admit requests.

Runs on Zenoh's callback thread, so it only decides and returns; suffixes run on the workers
(`cloudd.batch_runner`). In order: a stalled deployment holds the query; a request that does not
decode (over the request limit included) is answered with the codec's error; one with a tensor
over the deployment's limit (`cloudd.limits`) is answered `too_large`; a drop (fault injection)
holds it; one whose body names another robot than its key (`wrong_robot`) or that does not fit
this model (`cloudd.validate.check_request`) is answered with what is wrong; one that reaches a
deployment no longer serving its robot (it crossed a switch) is answered NOT_SERVING and the
robot finishes the frame itself; a video frame (`h264`) is decoded here, in its stream's order,
by the robot's decoder (`cloudd.video_streams`: `need_keyframe` for a P-frame it cannot decode,
the codec's error for a corrupt one); the rest is offered to the queue, which admits it or
refuses it at once (answered "busy": every slot taken, or the robot at its in-flight limit).
Every refusal but NOT_SERVING is counted by reason (`cloudd.refusals`); bad input is one
throttled WARNING line, never a traceback.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import zenoh

from cloudd.batch_queue import FairQueue, Pending, Refusal
from cloudd.faults import FaultInjector
from cloudd.limits import CloudLimits
from cloudd.metrics import RequestOutcome, ServiceMetrics
from cloudd.refusals import (
    RefusalReason,
    Refusals,
    check_refusal,
    decode_refusal,
    video_refusal,
)
from cloudd.replies import Replier, query_payload
from cloudd.robot_book import RobotBook
from cloudd.validate import check_request
from cloudd.video_streams import VideoDecoders
from common.partition import TensorSpec
from common.throttled_log import ThrottledLog
from common.wire import ErrorCode, ErrorReply, WireError, error_reply
from common.wire.cloud_to_robot import BusyReply
from common.wire.robot_to_cloud import InferRequest

log = logging.getLogger(__name__)

BUSY_REASONS = {
    Refusal.FULL: RefusalReason.QUEUE_FULL,
    Refusal.ROBOT_LIMIT: RefusalReason.ROBOT_IN_FLIGHT,
    Refusal.CLOSED: RefusalReason.STOPPING,
}
"""What each of the queue's refusals (all answered busy) is counted as."""


@dataclass(frozen=True)
class Job:
    """What answering one admitted inference request needs."""

    key: str
    query: zenoh.Query
    request: InferRequest
    decoded: dict[str, np.ndarray] | None = None
    """Its video tensors, decoded at admission (`cloudd.video_streams`)."""


class Admission:
    """Decides, on the callback thread, what becomes of each inference request."""

    def __init__(
        self,
        deployment: str,
        *,
        digest: str,
        cut_specs: Sequence[Sequence[TensorSpec]],
        queue: FairQueue[Job],
        book: RobotBook,
        faults: FaultInjector,
        replies: Replier,
        limits: CloudLimits,
        refusals: Refusals,
        throttled: ThrottledLog,
        metrics: ServiceMetrics | None = None,
        video: VideoDecoders | None = None,
        who: str = "",
    ) -> None:
        self.deployment = deployment
        self._video = video if video is not None else VideoDecoders()
        self._who = who or deployment  # the log's name: with the service when several
        self._digest = digest
        self._cut_specs = cut_specs
        self._queue = queue
        self._book = book
        self._faults = faults
        self._replies = replies
        self._limits = limits
        self._refusals = refusals
        self._throttled = throttled
        self._metrics = metrics

    def on_query(self, robot: str, key: str, query: zenoh.Query) -> None:
        """The callback of `robot`'s service key `key`."""
        arrived = time.monotonic()
        fault = self._faults.get()
        if fault.stall:
            self._outcome(robot, RequestOutcome.DROPPED)
            self._replies.hold(query)
            return
        delay_s = fault.delay_ms / 1000.0
        try:
            request = InferRequest.from_wire(
                query_payload(query), max_bytes=self._limits.request_bytes
            )
        except WireError as exc:
            self._count(robot, decode_refusal(exc))
            self._throttled.warning(
                "%s: bad inference request for %s: %s", self._who, robot, exc.reason
            )
            self._replies.send(query, key, error_reply(exc), delay_s)
            return
        too_large = self._limits.tensor_refusal(request)
        if too_large is not None:
            reason = RefusalReason.TENSOR_TOO_LARGE
            self._refuse(query, robot, key, request, too_large, reason, delay_s)
            return
        if self._faults.drop_now(fault):
            self._outcome(robot, RequestOutcome.DROPPED)
            self._replies.hold(query)
            return
        error = check_request(request, robot=robot, digest=self._digest, cut_specs=self._cut_specs)
        if error is not None:
            self._refuse(query, robot, key, request, error, check_refusal(error), delay_s)
            return
        if not self._book.serving(robot):
            # A request that crossed a switch: the robot finishes the frame itself.
            log.info("%s: frame %d of %s arrived in standby", self._who, request.frame, robot)
            reply = ErrorReply.make(
                ErrorCode.NOT_SERVING, f"{self.deployment} does not serve {robot} now"
            )
            self._outcome(robot, RequestOutcome.NOT_SERVING)
            self._replies.send(query, key, reply.to_wire(), delay_s)
            return
        decoded = None
        if request.video is not None:
            try:
                decoded = self._video.decode(robot, request, self._cut_specs[request.cut])
            except WireError as exc:
                reason = video_refusal(exc)
                self._refuse(query, robot, key, request, ErrorReply.of(exc), reason, delay_s)
                return
        item = Pending(
            robot=robot,
            group=request.cut,
            arrived=arrived,
            deadline_at=arrived + request.deadline_s,
            payload=Job(key, query, request, decoded),
        )
        refusal = self._queue.offer(item)
        if refusal is not None:
            self._count(robot, BUSY_REASONS[refusal])
            busy = BusyReply(
                frame=request.frame,
                deployment=self.deployment,
                queued=self._queue.load,
                capacity=self._queue.capacity,
            )
            self._replies.send(query, key, busy.to_wire(), delay_s)

    def _refuse(
        self,
        query: zenoh.Query,
        robot: str,
        key: str,
        request: InferRequest,
        error: ErrorReply,
        reason: RefusalReason,
        delay_s: float,
    ) -> None:
        """Answer a decoded request on `robot`'s key `key` with `error`, counted as `reason`,
        with one warning line."""
        self._count(robot, reason)
        self._throttled.warning(
            "%s: refused frame %d of %s: %s", self._who, request.frame, robot, error.reason
        )
        self._replies.send(query, key, error.to_wire(), delay_s)

    def _count(self, robot: str, reason: RefusalReason) -> None:
        """A request of `robot` refused for `reason`: in the refusal counts and the metrics."""
        self._refusals.count(reason)
        if self._metrics is not None:
            self._metrics.refused(robot, reason)

    def _outcome(self, robot: str, outcome: RequestOutcome) -> None:
        if self._metrics is not None:
            self._metrics.request(robot, outcome)
