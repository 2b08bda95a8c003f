"""A cloud daemon's workers' side: run a batch of one cut and answer each robot with its rows.

`BatchRunner.run` is what each worker thread (`cloudd.workers.BatchWorkers`) calls with a batch
from the queue. Expired requests are answered DEADLINE_EXPIRED without computing (the robot has
finished the frame itself by now). Once the daemon is stopping, the batch is answered
NOT_SERVING. Otherwise each request's tensors are decoded here, off Zenoh's callback thread (one
that does not decode is answered with the codec's error), the suffix runs once for the whole
batch, and each request gets an `InferReply` with its own outputs, its queueing and compute
times and the robot's epoch. A run that fails (onnxruntime's error, or a handler that raised or
returned something not arrays: `common.handlers.HandlerError`, named as the handler's failure)
is answered INTERNAL with the reason; the robot finishes the frame itself and the next request
is served as usual. A segment request (`InferRequest.end_cut`: the part of the model
between two cuts) runs on its own after the batch's suffixes, and its reply carries the end
cut's tensors. A request's slot is freed before its reply goes out, so a robot
that sends its next frame on the reply is not refused for a slot still held.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Sequence

import numpy as np

from cloudd.admission import Job
from cloudd.batch_queue import Batch, BatchCosts, FairQueue, Pending
from cloudd.batch_stats import BatchStats
from cloudd.metrics import ServiceMetrics, error_outcome
from cloudd.refusals import decode_refusal
from cloudd.replies import Replier
from cloudd.robot_book import RobotBook
from cloudd.validate import decode_tensors
from common.handlers import HandlerError
from common.partition import TensorSpec, ort_reason
from common.partition.errors import one_line
from common.partition.runtime import SplitModel
from common.throttled_log import ThrottledLog
from common.wire import ErrorCode, ErrorReply, WireError, error_reply
from common.wire.cloud_to_robot import InferReply

log = logging.getLogger(__name__)


class BatchRunner:
    """Runs admitted batches on the model and sends their replies."""

    def __init__(
        self,
        deployment: str,
        *,
        model: SplitModel,
        cut_specs: Sequence[Sequence[TensorSpec]],
        queue: FairQueue[Job],
        costs: BatchCosts,
        stats: BatchStats,
        book: RobotBook,
        replies: Replier,
        closing: threading.Event,
        throttled: ThrottledLog,
        metrics: ServiceMetrics | None = None,
        who: str = "",
    ) -> None:
        self.deployment = deployment
        self._who = who or deployment  # the log's name: with the service when several
        self._model = model
        self._cut_specs = cut_specs
        self._queue = queue
        self._costs = costs
        self._stats = stats
        self._book = book
        self._replies = replies
        self._closing = closing
        self._throttled = throttled
        self._metrics = metrics

    def run(self, batch: Batch[Job]) -> None:
        """Worker: answer the expired requests, then run the batch's requests together (one
        cut) and answer each with its own results."""
        for item in batch.expired:
            # The robot has finished this frame itself by now: computing it helps nobody.
            request = item.payload.request
            waited_s = batch.taken_at - item.arrived
            self._answer_error(
                item,
                ErrorReply.make(
                    ErrorCode.DEADLINE_EXPIRED,
                    f"frame {request.frame} cannot be answered within its deadline of "
                    f"{request.deadline_s * 1000:.0f} ms (it waited {waited_s * 1000:.0f} ms for "
                    "a worker)",
                ),
            )
        if not batch.items:
            return
        started = time.monotonic()
        if self._closing.is_set():
            stopping = ErrorReply.make(ErrorCode.NOT_SERVING, f"{self.deployment} is stopping")
            for item in batch.items:
                self._answer_error(item, stopping)
            return
        ready: list[tuple[Pending[Job], dict[str, np.ndarray]]] = []
        for item in batch.items:
            request = item.payload.request
            try:
                # Decoding runs here, on a worker, not on Zenoh's callback thread.
                specs = self._cut_specs[request.cut]
                ready.append((item, decode_tensors(request, specs, item.payload.decoded)))
            except WireError as exc:
                self._throttled.warning(
                    "%s: frame %d of %s: %s", self._who, request.frame, item.robot, exc.reason
                )
                self._release(item)
                if self._metrics is not None:
                    self._metrics.refused(item.robot, decode_refusal(exc))
                self._replies.send(
                    item.payload.query, item.payload.key, error_reply(exc), self._replies.delay_s()
                )
        # A segment request (`InferRequest.end_cut`) runs alone, after the batch's suffixes.
        segments = [(i, t) for i, t in ready if i.payload.request.end_cut is not None]
        ready = [(i, t) for i, t in ready if i.payload.request.end_cut is None]
        if ready:
            self._run_suffixes(batch.group, ready, started)
        for item, tensors in segments:
            self._run_segment(item, tensors)

    def _run_suffixes(
        self,
        group: int,
        ready: list[tuple[Pending[Job], dict[str, np.ndarray]]],
        started: float,
    ) -> None:
        """Run the suffix of cut `group` once for all of `ready` and answer each."""
        try:
            outputs = self._model.run_suffix_batch(group, [tensors for _, tensors in ready])
        except Exception as exc:
            reason = _failure(group, exc)
            log.warning(
                "%s: a batch of %d (%s): %s",
                self._who,
                len(ready),
                ", ".join(f"{i.robot} frame {i.payload.request.frame}" for i, _ in ready),
                reason,
            )
            for item, _ in ready:
                self._answer_error(item, ErrorReply.make(ErrorCode.INTERNAL, reason))
            return
        compute_s = time.monotonic() - started
        self._costs.record(group, len(ready), compute_s)
        self._stats.ran(len(ready))
        if self._metrics is not None:
            self._metrics.batch(len(ready))
        for (item, _), result in zip(ready, outputs, strict=True):
            self._answer(item, result, queue_s=started - item.arrived, compute_s=compute_s)

    def _run_segment(self, item: Pending[Job], tensors: dict[str, np.ndarray]) -> None:
        """Run the segment a request names (its cut to its `end_cut`) and answer with the end
        cut's tensors; a segment this split lacks is answered UNKNOWN_CUT (the robot finishes
        the frame itself)."""
        request = item.payload.request
        start, end = request.cut, request.end_cut
        assert end is not None
        if not self._model.has_segment(start, end):
            known = ", ".join(s.label for s in self._model.partition.segments) or "none"
            self._answer_error(
                item,
                ErrorReply.make(
                    ErrorCode.UNKNOWN_CUT,
                    f"no segment from cut {start} to cut {end} here (segments: {known}; the "
                    "fleet's cuts.segments builds them)",
                ),
            )
            return
        started = time.monotonic()
        try:
            outputs = self._model.run_segment(start, end, tensors)
        except Exception as exc:
            reason = f"segment {start}-{end} failed: {ort_reason(exc)}"
            log.warning("%s: %s frame %d: %s", self._who, item.robot, request.frame, reason)
            self._answer_error(item, ErrorReply.make(ErrorCode.INTERNAL, reason))
            return
        compute_s = time.monotonic() - started
        self._stats.ran(1)
        if self._metrics is not None:
            self._metrics.batch(1)
        self._answer(item, outputs, queue_s=started - item.arrived, compute_s=compute_s)

    def _answer(
        self,
        item: Pending[Job],
        outputs: dict[str, np.ndarray],
        *,
        queue_s: float,
        compute_s: float,
    ) -> None:
        job, robot = item.payload, item.robot
        epoch = self._book.wire_epoch(robot)
        self._release(item)
        if self._metrics is not None:
            self._metrics.answered(robot, queue_s, compute_s)
        reply = InferReply(
            frame=job.request.frame,
            deployment=self.deployment,
            epoch=epoch,
            outputs=outputs,
            queue_s=queue_s,
            compute_s=compute_s,
        )
        self._replies.send(
            job.query,
            job.key,
            reply.to_wire(),
            self._replies.delay_s(),
            on_sent=functools.partial(self._count_served, robot, job.request.frame, epoch),
        )

    def _answer_error(self, item: Pending[Job], error: ErrorReply) -> None:
        self._release(item)
        if self._metrics is not None:
            self._metrics.request(item.robot, error_outcome(error.error_code))
        self._replies.send(
            item.payload.query, item.payload.key, error.to_wire(), self._replies.delay_s()
        )

    def _release(self, item: Pending[Job]) -> None:
        """Free the request's slot before its reply goes out (`FairQueue.release`)."""
        self._queue.release(item)

    def _count_served(self, robot: str, frame: int, epoch: int) -> None:
        if self._book.count_served(robot):
            # One line per stay in service: shows that requests reach this deployment and that
            # its replies go out (a robot that times out against it is then a network problem).
            log.info(
                "%s: first frame of %s answered at epoch %d (frame %d)",
                self._who,
                robot,
                epoch,
                frame,
            )


def _failure(cut: int, exc: Exception) -> str:
    """Why the suffix of `cut` failed, for the error reply: a handler's own failure as the
    handler names it (`HandlerError`: it raised, or returned something not arrays), else
    onnxruntime's reason."""
    if isinstance(exc, HandlerError):
        return one_line(exc)
    return f"suffix of cut {cut} failed: {ort_reason(exc)}"
