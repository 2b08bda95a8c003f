"""Runs of frames the cloud failed: logged at their start and end (not every frame), and the
point at which the robot asks the registry for another route.

A run is consecutive offloaded frames that failed for the same reason. Its first frame is logged
as a WARNING (`frame N: cloud failed (reason: detail); finished on the robot`), then every
`LOG_FAILURE_EVERY`th; the next answered frame ends it with one INFO line. After
`REROUTE_AFTER_FAILURES` frames of a timeout or a missing route in a row the deployment looks
dead or unreachable: `note` then names the reason to ask for a reroute (the registry link sends
at most one request per interval, so it is asked on every further frame of the run).
"""

from __future__ import annotations

import logging

from common.wire.telemetry import FallbackReason
from robotd.frame_path.offload import CallResult

log = logging.getLogger("robotd")

# Ask the registry for a new route after this many consecutive timeouts / missing routes.
REROUTE_AFTER_FAILURES = 3
# A failure of the same reason is logged again after this many frames of it.
LOG_FAILURE_EVERY = 100
FAILOVER_REASONS = frozenset({FallbackReason.TIMEOUT, FallbackReason.NO_ROUTE})


class FailureRuns:
    """`FailureRuns("robot-1")`; `note(frame, result)` after every offloaded frame."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.reason: FallbackReason | None = None
        self.streak = 0

    def note(self, frame: int, result: CallResult) -> FallbackReason | None:
        """Count offloaded frame `frame`'s `result`; the reason to ask for a reroute, or None."""
        if result.answered:
            if self.reason is not None:
                log.info(
                    "%s: frame %d answered by %s again after %d frame(s) finished on the robot",
                    self.robot,
                    frame,
                    result.deployment,
                    self.streak,
                )
            self.reason, self.streak = None, 0
            return None
        reason = result.reason or FallbackReason.OTHER
        if reason != self.reason or self.streak % LOG_FAILURE_EVERY == 0:
            log.warning(
                "%s: frame %d: cloud failed (%s: %s); finished on the robot",
                self.robot,
                frame,
                reason,
                result.detail,
            )
        if reason != self.reason:
            self.reason, self.streak = reason, 0
        self.streak += 1
        if reason in FAILOVER_REASONS and self.streak >= REROUTE_AFTER_FAILURES:
            return reason
        return None
