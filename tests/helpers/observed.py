"""What a test policy observed, by frame.

A hedged frame the robot served while its reply was out is handed on when served but observed
when the reply settles, after later frames may have been: results and observations are paired
by frame, not by order.
"""

from __future__ import annotations

from collections.abc import Sequence

from robotd.frame_path.frame import FrameResult
from robotd.policies import Decision, Outcome


class ObservedByFrame:
    """`decided` when a decision is made, `observed` when its outcome comes."""

    def __init__(self) -> None:
        self.outcomes: dict[int, Outcome] = {}
        self._frame_of: dict[int, int] = {}  # id(decision) -> its frame

    def decided(self, decision: Decision, frame: int) -> Decision:
        self._frame_of[id(decision)] = frame
        return decision

    def observed(self, decision: Decision, outcome: Outcome) -> None:
        self.outcomes[self._frame_of.pop(id(decision))] = outcome

    def of(self, results: Sequence[FrameResult]) -> list[Outcome]:
        """The outcome of each of `results`' frames, in their order."""
        return [self.outcomes[result.frame] for result in results]
