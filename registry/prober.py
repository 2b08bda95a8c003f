"""Probing deployments off the control loop: registration, and a refresh every few seconds.

A probe is a Zenoh get with a timeout (`registry.transport`), up to half a second, tried up to
three times for a registration: the control loop must not wait on it. `RegistryProber` runs probes
on a small pool and hands each outcome, a `Probed`, to a callback (the daemon queues it for the
control loop, which alone decides). `close()` cancels the probes not started, lets the running
ones finish (they stop retrying once the daemon is closing) and waits for them; after it, nothing
is probed. A prober probes for one service (`ProbeRequest.service`: each service's plane has its
own), and its outcomes name it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from common.wire import registry as msg
from registry.switch import TransportError
from registry.transport import ZenohTransport

PROBE_TIMEOUT_S = 0.5
REGISTRATION_ATTEMPTS = 3
PROBE_WORKERS = 2


@dataclass(frozen=True)
class Probed:
    """A probe's outcome: the reply, or None and why (`error`). `refresh`: a probe of a
    deployment accepted already (load and repair), not a registration. `service`: the service
    it was probed for (None: the fleet's first)."""

    deployment: str
    reply: msg.ProbeReply | None
    error: str
    refresh: bool
    service: str | None = None


class RegistryProber:
    """`RegistryProber(transport, sender, on_probed, closing, service="vision")`;
    `submit(deployment, refresh=...)`."""

    def __init__(
        self,
        transport: ZenohTransport,
        sender: str,
        on_probed: Callable[[Probed], None],
        closing: threading.Event,
        *,
        timeout_s: float = PROBE_TIMEOUT_S,
        service: str | None = None,
    ) -> None:
        self.transport = transport
        self.sender = sender
        self.service = service
        self.timeout_s = timeout_s
        self._on_probed = on_probed
        self._closing = closing
        self._lock = threading.Lock()  # a submit racing close() must not reach a closed pool
        self._pool: ThreadPoolExecutor | None = ThreadPoolExecutor(
            PROBE_WORKERS, thread_name_prefix="registry-probe"
        )

    def submit(self, deployment: str, *, refresh: bool) -> None:
        """Probe `deployment` on the pool (ignored once closing)."""
        with self._lock:
            if self._pool is not None and not self._closing.is_set():
                self._pool.submit(self._probe, deployment, refresh)

    def close(self) -> None:
        """Cancel what has not started, wait for what has; idempotent."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def _probe(self, deployment: str, refresh: bool) -> None:
        attempts = 1 if refresh else REGISTRATION_ATTEMPTS
        reply, error = None, "no reply"
        for _ in range(attempts):
            if self._closing.is_set():
                return
            request = msg.ProbeRequest(
                sender=self.sender, sent_at=time.time(), service=self.service
            )
            try:
                reply = self.transport.probe(deployment, request, self.timeout_s)
            except TransportError as exc:
                reply, error = None, str(exc)
            if reply is not None:
                break
            if error == "no reply":
                error = f"no probe reply within {self.timeout_s:g} s ({attempts} tries)"
        self._on_probed(Probed(deployment, reply, error, refresh, self.service))
