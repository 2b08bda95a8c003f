"""Persisting latency windows a slice per tick, so the control loop never stalls on a save.

The registry keeps every robot x deployment x source latency window in memory and writes the
changed ones to the RIB, so a restarted registry starts from them. At 1,000 robots x 100
deployments about 100,000 windows change every 5 s; written at once they held the control loop
for 0.6-1.4 s on a 2-core host (no round, no failover meanwhile: docs/scale.md). `PacedSaver`
looks every `interval_s` at how many windows are unsaved: up to `at_once` of them (a small
fleet) are written there and then, in one transaction, as before; more are spread over the
interval's ticks, the longest unsaved first (`Measurements.save(limit=...)`), so each tick
writes a fiftieth. A window is written within about two intervals of changing (within one
before), and no tick holds the loop for a whole save.
"""

from __future__ import annotations

import math

from registry.measurements import Measurements
from registry.rib import Rib

AT_ONCE_ROWS = 2_000
"""Unsaved windows written in one go at the interval (about 20 ms here); more are spread."""


class PacedSaver:
    """Writes `measurements`' unsaved windows to `rib`: at each interval, all of them when few,
    else a share per tick."""

    def __init__(
        self,
        measurements: Measurements,
        rib: Rib,
        *,
        tick_s: float,
        interval_s: float,
        at_once: int = AT_ONCE_ROWS,
    ) -> None:
        if tick_s <= 0 or interval_s < tick_s or at_once < 1:
            raise ValueError(
                f"need 0 < tick_s <= interval_s and at_once >= 1, got {tick_s}, {interval_s}, "
                f"{at_once}"
            )
        self._measurements = measurements
        self._rib = rib
        self._ticks = math.ceil(interval_s / tick_s)
        self._interval_s = interval_s
        self._at_once = at_once
        self._quota = 0  # per tick, until the next plan
        self._left = 0  # of the planned windows
        self._next_plan: float | None = None

    def tick(self, now: float) -> int:
        """One tick: plan at each interval, write this tick's share; returns how many windows
        were written."""
        if self._next_plan is None:
            self._next_plan = now + self._interval_s
        elif now >= self._next_plan:
            self._next_plan = now + self._interval_s
            unsaved = self._measurements.unsaved
            if unsaved <= self._at_once:
                self._left = 0
                return self._measurements.save(self._rib)
            self._left = unsaved
            self._quota = math.ceil(unsaved / self._ticks)
        if self._left <= 0:
            return 0
        written = self._measurements.save(self._rib, min(self._quota, self._left))
        self._left -= max(written, 1)  # a window dropped meanwhile still uses up its turn
        return written
