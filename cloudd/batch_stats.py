"""A cloud daemon's batch statistics: runs by size and requests refused, logged once at exit."""

from __future__ import annotations

import logging
import threading
from collections import Counter

from cloudd.batch_queue import Refusal

log = logging.getLogger(__name__)


class BatchStats:
    """Batches run and requests refused, for the log and the tests (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.sizes: Counter[int] = Counter()
        self.refused: Counter[Refusal] = Counter()

    def ran(self, size: int) -> None:
        with self._lock:
            self.sizes[size] += 1

    def refuse(self, why: Refusal) -> None:
        with self._lock:
            self.refused[why] += 1

    def snapshot(self) -> tuple[dict[int, int], dict[Refusal, int]]:
        with self._lock:
            return dict(self.sizes), dict(self.refused)

    def log_summary(self, deployment: str) -> None:
        """One INFO line of what the workers computed, if they computed anything."""
        sizes, refused = self.snapshot()
        if not sizes:
            return
        runs = sum(sizes.values())
        frames = sum(size * count for size, count in sizes.items())
        log.info(
            "%s: %d request(s) computed in %d run(s) (mean batch %.2f, largest %d); "
            "refused busy: %s",
            deployment,
            frames,
            runs,
            frames / runs,
            max(sizes),
            ", ".join(f"{n} ({why.value})" for why, n in refused.items()) or "none",
        )
