"""A robot's per-frame telemetry, received over Zenoh as it happens (`TelemetryTap`)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from deploy.procs import WATCH_INTERVAL_S, DaemonError, DaemonProc, ProcessSet
from deploy.readiness import check_procs


class TelemetryTap:
    """The per-frame telemetry of one robot, received over Zenoh as it happens.

    Records are kept as the robot's JSONL objects plus `at` (completion wall clock) and `epoch`.
    `wait_for` blocks until a record satisfies a predicate; `on_record` callbacks run on the
    subscriber's thread (keep them short).
    """

    def __init__(
        self,
        session: Any,
        key_expr: str,
        on_record: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        from common.wire import WireError, decode
        from common.wire.telemetry import TelemetryRecord

        self._decode = lambda data: decode(data, expect=TelemetryRecord)
        self._wire_error = WireError
        self.records: list[dict[str, Any]] = []
        self.bad = 0
        self._on_record = on_record
        self._changed = threading.Condition()
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            message = self._decode(sample.payload.to_bytes())
        except self._wire_error:
            self.bad += 1
            return
        rec: dict[str, Any] = message.to_jsonl()
        rec["at"] = message.at
        rec["epoch"] = message.epoch
        rec["robot"] = message.robot
        with self._changed:
            self.records.append(rec)
            self._changed.notify_all()
        if self._on_record is not None:
            self._on_record(rec)

    def snapshot(self) -> list[dict[str, Any]]:
        with self._changed:
            return list(self.records)

    def wait_for(
        self,
        pred: Callable[[dict[str, Any]], bool],
        *,
        timeout_s: float,
        what: str,
        procs: ProcessSet | Sequence[DaemonProc] | None = None,
    ) -> dict[str, Any]:
        """The first record (already received or to come) satisfying `pred`."""
        deadline = time.monotonic() + timeout_s
        seen = 0
        with self._changed:
            while True:
                for rec in self.records[seen:]:
                    if pred(rec):
                        return rec
                seen = len(self.records)
                check_procs(procs)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DaemonError(f"timed out after {timeout_s:.0f} s waiting for {what}")
                self._changed.wait(min(WATCH_INTERVAL_S * 4, remaining))

    def wait_frame(
        self,
        frame: int,
        *,
        timeout_s: float,
        procs: ProcessSet | Sequence[DaemonProc] | None = None,
    ) -> dict[str, Any]:
        """The first record of a frame >= `frame`."""
        return self.wait_for(
            lambda r: int(r.get("frame", -1)) >= frame,
            timeout_s=timeout_s,
            what=f"telemetry of frame {frame}",
            procs=procs,
        )

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._sub.undeclare()
