"""Where each applied frame's result goes beyond the robot daemon: result sinks.

A `ResultSink` takes every frame the robot applies (whichever path served it: the robot, the
cloud, a pool member, a fallback) as a `robotd.frame_path.frame.FrameResult`, in frame order. A
frame whose result was dropped as stale (pipelining: a newer frame's result was applied first)
reaches no sink; it is counted in the run summary and its telemetry record instead.

The daemon holds a list of sinks. Each is added with `RobotDaemon.add_result_sink`, which enters
it into the daemon's lifecycle: it is taken off the list and closed at shutdown, in reverse order
with the rest, so a sink that publishes on the daemon's Zenoh session is closed before the
session. `open_result_sinks` makes the sinks a robot's configuration asks for, once the session
is open; sinks of other kinds (an embedder's) may be added by hand before `run()`.

`publish` runs on the frame loop's thread: a sink must not block (hand slow work to a thread of
its own). A sink that raises is logged (throttled) and the frame still counts: a failed
publication never stops the robot.

Every robot has one sink: `ZenohResultSink`, each applied frame's `FrameResultMessage`
(`common.wire.robot_to_app`) on `ef/<fleet>/out/<robot>`, its outputs in the machine's
`results.codec`. It publishes whether or not anyone subscribes yet: an application that just
subscribed must not miss the result of the frame it just sent (a robot's view of who subscribes
lags by a network round trip).
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import zenoh

from common import keys
from common.wire.robot_to_app import FrameResultMessage, ServedBy, encode_output
from common.wire.telemetry import parse_action_codec

if TYPE_CHECKING:
    from common.config import FleetConfig
    from robotd.frame_path.frame import FrameResult

log = logging.getLogger("robotd")


@runtime_checkable
class ResultSink(Protocol):
    """Takes each applied frame's result; `close()` releases what the sink holds."""

    def publish(self, result: FrameResult) -> None:
        """Frame `result.frame` was applied: hand its result on (without blocking)."""

    def close(self) -> None:
        """Release the sink's resources (publishers, files); called once, at shutdown."""


class ZenohResultSink:
    """Each applied frame's `FrameResultMessage` on `ef/<fleet>/out/<robot>`, outputs in
    `codec` (a result codec: raw, fp16 or raw+zstd)."""

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        robot: str,
        codec: str,
        service: str | None = None,
    ) -> None:
        self.robot = robot
        self.service = service
        self.codec = codec
        self.key = keys.results_out(fleet, robot)
        # Results are big (a disparity map) and each is wanted: block rather than drop.
        self._publisher = session.declare_publisher(
            self.key, congestion_control=zenoh.CongestionControl.BLOCK
        )
        self.published = 0

    def message(self, result: FrameResult) -> FrameResultMessage:
        """The message of applied frame `result`."""
        record = result.record
        cut, codec = parse_action_codec(record.action)
        return FrameResultMessage(
            robot=self.robot,
            frame=result.frame,
            stamp_ns=result.stamp_ns,
            served_by=ServedBy(result.served_by),
            deployment=record.deployment if result.served_by == ServedBy.CLOUD else None,
            action=record.action,
            cut=cut,
            codec=None if cut is None else codec,
            fallback=record.fallback,
            latency_s=record.latency_s,
            published_ns=time.time_ns(),
            outputs={name: encode_output(a, self.codec) for name, a in result.outputs.items()},
            service=self.service,
        )

    def publish(self, result: FrameResult) -> None:
        try:
            self._publisher.put(self.message(result).to_wire())
        except zenoh.ZError as exc:  # e.g. while the session closes
            log.debug("%s: result of frame %d not published: %s", self.robot, result.frame, exc)
            return
        self.published += 1

    def close(self) -> None:
        self._publisher.undeclare()


def open_result_sinks(
    config: FleetConfig, robot: str, session: zenoh.Session
) -> list[tuple[ResultSink, str]]:
    """The sinks robot `robot`'s configuration asks for, each with what to call it in logs,
    made on the daemon's open `session` (the caller hands each to the lifecycle): always the
    `out/<robot>` publisher, its messages naming the (first) service."""
    results = config.machine(robot, role=keys.Role.ROBOT).results
    sink = ZenohResultSink(session, config.fleet, robot, results.codec, config.service_name)
    return [(sink, "results publisher")]


__all__ = ["ResultSink", "ZenohResultSink", "open_result_sinks"]
