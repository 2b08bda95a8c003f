"""What the registry refused to read, counted: error replies to its queries and publications it
dropped, by input (`register`, `reroute`, `drain`, `rib`, `telemetry`, `probe report`) and error
code (`too_large`, `malformed`, ...).

Why counts: bad input is logged through a throttle, so that a flood cannot flood the log too,
and the log alone then cannot say how much was refused. Zenoh callback threads count at the same
time, hence the lock. The daemon logs the counts when it stops; tests read them.
"""

from __future__ import annotations

import threading
from collections import Counter

from common.wire import ErrorCode


class Refusals:
    """`Refusals().count("register", ErrorCode.TOO_LARGE)`; `get`, `snapshot`, `summary`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[tuple[str, ErrorCode]] = Counter()

    def count(self, what: str, code: ErrorCode) -> None:
        """One more refusal of `what` with `code`."""
        with self._lock:
            self._counts[(what, code)] += 1

    def get(self, what: str, code: ErrorCode) -> int:
        """How many of `what` were refused with `code` so far."""
        with self._lock:
            return self._counts[(what, code)]

    def snapshot(self) -> dict[str, dict[str, int]]:
        """input -> error code -> count, in the order first seen."""
        out: dict[str, dict[str, int]] = {}
        with self._lock:
            for (what, code), n in self._counts.items():
                out.setdefault(what, {})[code.value] = n
        return out

    def summary(self) -> str:
        """One line for the log, e.g. `register too_large 3, telemetry malformed 1` ('' if
        nothing was refused)."""
        return ", ".join(
            f"{what} {code} {n}"
            for what, codes in self.snapshot().items()
            for code, n in codes.items()
        )
