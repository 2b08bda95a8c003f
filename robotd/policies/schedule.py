"""Forced-sampling schedules: which frames must offload so the learner keeps learning.

`doubling` (default): epoch e covers frames [T_e/2, T_e) (the first [0, T_0)), with T_e = T_0·2^e,
and forces every ceil(T_e^exponent)-th frame of its epoch — the interval grows slowly, so forced
frames are a vanishing fraction of a long run. `every`: every I-th frame, which is what ElasticROS's
sequence n·T^(1/log_I T) reduces to. `off`: never.
"""

from __future__ import annotations

import math

# Guard for T^exponent landing a hair above an integer (e.g. 256**0.25).
_CEIL_SLACK = 1e-9


class ForcedSchedule:
    """Answers "is frame n a forced-sampling frame?" for frames counted from 0."""

    def __init__(
        self, kind: str, start_frames: int = 200, exponent: float = 0.25, every_frames: int = 10
    ) -> None:
        if kind not in ("doubling", "every", "off"):
            raise ValueError(f"unknown forced schedule {kind!r}")
        if start_frames < 1 or every_frames < 1 or not 0 < exponent < 1:
            raise ValueError("forced schedule needs start_frames >= 1, every_frames >= 1, 0<exp<1")
        self.kind = kind
        self.start_frames = start_frames
        self.exponent = exponent
        self.every_frames = every_frames
        # The doubling epoch last looked up, [first, end) and its interval: is_forced runs every
        # frame and frames arrive in order, so the epoch arithmetic runs once per epoch.
        self._epoch_first, self._epoch_end, self._epoch_interval = 0, 0, 1

    def epoch(self, n: int) -> tuple[int, int, int]:
        """(epoch start frame, T_e, interval) of the doubling epoch holding frame n."""
        if n < self.start_frames:
            start, horizon = 0, self.start_frames
        else:
            e = (n // self.start_frames).bit_length()  # T_0·2^(e-1) <= n < T_0·2^e
            horizon = self.start_frames << e
            start = horizon >> 1
        interval = max(1, math.ceil(horizon**self.exponent - _CEIL_SLACK))
        return start, horizon, interval

    def interval(self, n: int) -> int:
        """Frames between forced frames around frame n (0 when the schedule is off)."""
        if self.kind == "off":
            return 0
        if self.kind == "every":
            return self.every_frames
        return self.epoch(n)[2]

    def is_forced(self, n: int) -> bool:
        """True when frame n is in the forced-sampling sequence."""
        if self.kind == "off" or n < 0:
            return False
        if self.kind == "every":
            return n % self.every_frames == 0
        if not self._epoch_first <= n < self._epoch_end:
            first, end, interval = self.epoch(n)
            self._epoch_first, self._epoch_end, self._epoch_interval = first, end, interval
        return (n - self._epoch_first) % self._epoch_interval == 0
