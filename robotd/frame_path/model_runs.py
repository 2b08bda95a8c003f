"""Where the robot's model work runs (a P frame's whole model, a prefix, a fallback suffix): in the
frame loop's own thread, or on the low-priority local-run thread while a hedged frame's cloud
reply is still on its way.

On a robot short of CPU, receiving that reply then goes first, and the learner sees the link, not
the robot's later frames. Otherwise the work runs in the loop's thread, at its own priority (on
the testbed's 0.02-core robot, P frames on the low-priority thread took a median 0.50 s against
0.40 s there: Zenoh's and the prober's threads went first). A pending reply of a sample taken
while P was best (`Decision.local_expected`) does not get that precedence: it only has to show
whether offloading got cheaper, and a reply delayed by the robot's own frame errs towards P, the
choice in force; the robot's frames do not pay for the sample. Every run goes through the
emulated slowdown (`robotd.emulation.Slowdown`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from robotd.emulation import Slowdown
from robotd.frame_path.frame import Frame
from robotd.frame_path.local_runs import LocalRunner


class ModelRuns:
    """`ModelRuns(slowdown, local)`; `run(fn, pending)` runs `fn` (it gets onnxruntime run
    options) and waits for its outputs; `pending` is the hedged frame whose reply is awaited."""

    def __init__(self, slowdown: Slowdown, local: LocalRunner) -> None:
        self._slowdown = slowdown
        self._local = local

    def run(
        self, fn: Callable[[Any], Mapping[str, np.ndarray]], pending: Frame | None
    ) -> dict[str, np.ndarray]:
        if (
            pending is None
            or pending.call is None
            or pending.call.settled
            or pending.decision.local_expected
        ):
            return dict(self._slowdown.run(fn, None))
        job = self._local.submit(self._slowdown.stretched(fn))
        job.wait()  # as long as the run takes, as if computed in this thread
        if job.error is not None:
            raise job.error
        assert job.outputs is not None
        return job.outputs
