"""Where each applied frame's result goes beyond the robot daemon: result sinks.

A `ResultSink` takes every frame the robot applies (whichever path served it: the robot, the
cloud, a pool member, a fallback) as a `robotd.frame.FrameResult`, in frame order. A frame whose
result was dropped as stale (pipelining: a newer frame's result was applied first) reaches no
sink; it is counted in the run summary and its telemetry record instead.

The daemon holds a list of sinks. Each is added with `RobotDaemon.add_result_sink`, which enters
it into the daemon's lifecycle: it is taken off the list and closed at shutdown, in reverse order
with the rest, so a sink that publishes on the daemon's Zenoh session is closed before the
session. `open_result_sinks` makes the sinks a robot's configuration asks for, once the session
is open; sinks of other kinds (an embedder's) may be added by hand before `run()`.

`publish` runs on the frame loop's thread: a sink must not block (hand slow work to a thread of
its own). A sink that raises is logged (throttled) and the frame still counts: a failed
publication never stops the robot.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    import zenoh

    from common.config import FleetConfig
    from robotd.frame import FrameResult


@runtime_checkable
class ResultSink(Protocol):
    """Takes each applied frame's result; `close()` releases what the sink holds."""

    def publish(self, result: FrameResult) -> None:
        """Frame `result.frame` was applied: hand its result on (without blocking)."""

    def close(self) -> None:
        """Release the sink's resources (publishers, files); called once, at shutdown."""


def open_result_sinks(
    config: FleetConfig, robot: str, session: zenoh.Session
) -> list[tuple[ResultSink, str]]:
    """The sinks robot `robot`'s configuration asks for, each with what to call it in logs,
    made on the daemon's open `session` (the caller hands each to the lifecycle)."""
    del config, robot, session  # no sink kind is configured yet
    return []


__all__ = ["ResultSink", "open_result_sinks"]
