"""Fault injection of a cloud daemon: extra delay, dropped requests, a stall.

Set at start (fleet.yaml `machines.<id>.fault`, or `--inject-delay-ms` / `--inject-drop`) and at
run time by a ctl `fault` request. What each fault does, and why:

- `delay_ms` is added before every reply on the service and probe keys (results, busy and error
  replies, probe replies alike), as extra network delay would be: it does not hold a worker.
  Probes are delayed too, because the registry compares deployments by their probe profiles.
- `drop` is the probability that a well-formed inference request gets no reply at all. The query
  is held (not answered) until the request's deadline, so the robot sees what a lost message
  looks like: a timeout, not an immediate empty answer.
- `stall` is a frozen host that still holds its liveliness token: no inference or probe request
  is answered (each is held until its deadline). Control requests are still obeyed, so an
  operator or a test can clear the stall.
"""

from __future__ import annotations

import random
import threading

from common.wire.registry import FaultSpec


class FaultInjector:
    """The current fault settings, thread-safe; `drop_now()` draws one drop decision."""

    def __init__(self, spec: FaultSpec | None = None, *, seed: int | None = None) -> None:
        self._lock = threading.Lock()
        self._spec = spec if spec is not None else FaultSpec()
        self._random = random.Random(seed)

    def get(self) -> FaultSpec:
        """The settings now (an immutable snapshot)."""
        with self._lock:
            return self._spec

    def set(self, spec: FaultSpec) -> FaultSpec:
        """Replace the settings; returns the previous ones."""
        with self._lock:
            previous, self._spec = self._spec, spec
            return previous

    def drop_now(self, spec: FaultSpec | None = None) -> bool:
        """Whether to drop this request (true with probability `drop`)."""
        spec = spec if spec is not None else self.get()
        if spec.drop <= 0:
            return False
        with self._lock:
            return self._random.random() < spec.drop


def describe(spec: FaultSpec) -> str:
    """One line for logs: `delay 250 ms, drop 0.1, stall` or `none`."""
    parts = []
    if spec.delay_ms > 0:
        parts.append(f"delay {spec.delay_ms:g} ms")
    if spec.drop > 0:
        parts.append(f"drop {spec.drop:g}")
    if spec.stall:
        parts.append("stall")
    return ", ".join(parts) or "none"
