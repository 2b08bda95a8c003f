"""What a cloud daemon refused, counted by reason: its limits (`cloudd.limits`), a request whose
body names another robot than its key, busy answers and other bad requests.

Why counts: bad input is logged through a throttle, so that a flood cannot flood the log too,
and the log alone then cannot say how much was refused. Zenoh callback threads count at the same
time, hence the lock. The daemon logs the counts when it stops, answers them in its probe reply
(`ProbeReply.refused`) and tests read them (`CloudDaemon.refusals`).
"""

from __future__ import annotations

import enum
import logging
import threading
from collections import Counter

from common.wire import ErrorCode, ErrorReply, PayloadTooLarge, TensorTooLarge, WireError

log = logging.getLogger(__name__)


class RefusalReason(str, enum.Enum):
    """Why a request on the service, probe or ctl key was answered without being served."""

    REQUEST_TOO_LARGE = "request_too_large"  # payload over limits.max_request_bytes
    TENSOR_TOO_LARGE = "tensor_too_large"  # a tensor over limits.max_tensor_bytes
    ECHO_TOO_LARGE = "echo_too_large"  # a probe asking for more than limits.max_echo_bytes
    WRONG_ROBOT = "wrong_robot"  # the body names another robot than its service key
    ROBOT_IN_FLIGHT = "robot_in_flight"  # busy: the robot's in-flight limit reached
    # A robot announced more frames in flight than batching.max_in_flight_per_robot (once each).
    IN_FLIGHT_CAP = "in_flight_cap"
    QUEUE_FULL = "queue_full"  # busy: every worker and queue slot taken
    STOPPING = "stopping"  # busy: the deployment is shutting down
    BAD_REQUEST = "bad_request"  # any other request that does not decode or fit the model
    # A video P-frame this deployment's decoder cannot decode (`cloudd.video_streams`).
    NEED_KEYFRAME = "need_keyframe"
    # A probe or ctl naming a service this deployment does not serve (or the fleet lacks).
    UNKNOWN_SERVICE = "unknown_service"

    def __str__(self) -> str:
        return self.value


def decode_refusal(error: WireError) -> RefusalReason:
    """The reason to count for a request that did not decode."""
    if isinstance(error, TensorTooLarge):
        return RefusalReason.TENSOR_TOO_LARGE
    if isinstance(error, PayloadTooLarge):
        return RefusalReason.REQUEST_TOO_LARGE
    return RefusalReason.BAD_REQUEST


def video_refusal(error: WireError) -> RefusalReason:
    """The reason to count for a video frame the stream's decoder refused."""
    if error.code is ErrorCode.NEED_KEYFRAME:
        return RefusalReason.NEED_KEYFRAME
    return decode_refusal(error)


def check_refusal(reply: ErrorReply) -> RefusalReason:
    """The reason to count for a decoded request refused by `cloudd.validate.check_request`."""
    if reply.error_code is ErrorCode.WRONG_ROBOT:
        return RefusalReason.WRONG_ROBOT
    return RefusalReason.BAD_REQUEST


class Refusals:
    """`Refusals().count(RefusalReason.WRONG_ROBOT)`; `get`, `snapshot`, `summary`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[RefusalReason] = Counter()

    def count(self, reason: RefusalReason) -> None:
        """One more request refused for `reason`."""
        with self._lock:
            self._counts[reason] += 1

    def get(self, reason: RefusalReason) -> int:
        """How many requests were refused for `reason` so far."""
        with self._lock:
            return self._counts[reason]

    def snapshot(self) -> dict[str, int]:
        """reason (its wire value) -> count, in the order first seen."""
        with self._lock:
            return {reason.value: n for reason, n in self._counts.items()}

    def summary(self) -> str:
        """One line for the log, e.g. `wrong_robot 2, queue_full 5` ('' if nothing was
        refused)."""
        return ", ".join(f"{reason} {n}" for reason, n in self.snapshot().items())

    def log_summary(self, deployment: str) -> None:
        """One INFO line of what was refused, if anything was."""
        summary = self.summary()
        if summary:
            log.info("%s: refused (reason, count): %s", deployment, summary)
