"""A cloud daemon's batch statistics: runs by size, logged once at exit (what was refused is
counted apart, by reason: `cloudd.refusals`)."""

from __future__ import annotations

import logging
import threading
from collections import Counter

log = logging.getLogger(__name__)


class BatchStats:
    """Batches run, by size, for the log and the tests (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.sizes: Counter[int] = Counter()

    def ran(self, size: int) -> None:
        with self._lock:
            self.sizes[size] += 1

    def snapshot(self) -> dict[int, int]:
        """Runs by batch size."""
        with self._lock:
            return dict(self.sizes)

    def log_summary(self, deployment: str) -> None:
        """One INFO line of what the workers computed, if they computed anything."""
        sizes = self.snapshot()
        if not sizes:
            return
        runs = sum(sizes.values())
        frames = sum(size * count for size, count in sizes.items())
        log.info(
            "%s: %d request(s) computed in %d run(s) (mean batch %.2f, largest %d)",
            deployment,
            frames,
            runs,
            frames / runs,
            max(sizes),
        )
