"""A cloud daemon's link to the registry: opening the session, following it, asking it to drain.

- Opening: a peer session opens without the registry (Zenoh keeps retrying its endpoint in the
  background, backing off from 1 s to 4 s): the daemon says so, naming the endpoint, and serves
  meanwhile. A client session cannot open without it: that is retried here with backoff until
  it opens or the daemon is stopped.
- Following: the registry's liveliness (`common.membership`) is logged as it comes and goes;
  robots keep their current routes while it is away.
- Draining: a deployment stopping on SIGTERM asks `reg/drain` to move its robots and waits at
  most DRAIN_TIMEOUT_S for the answer.
"""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from common import keys
from common.config import FleetConfig
from common.errors import UserError
from common.membership import MemberChange
from common.session import open_session, zenoh_error_text, zenoh_settings
from common.wire import ErrorReply, WireError, decode
from common.wire.registry import DrainReply, DrainRequest

log = logging.getLogger(__name__)

DRAIN_TIMEOUT_S = 1.2
"""How long a draining daemon waits for the registry to move its robots before exiting anyway
(the daemon promises to stop within 2 s of SIGTERM)."""

OPEN_RETRY_FIRST_S = 0.5
OPEN_RETRY_MAX_S = 8.0
"""Backoff between attempts to open a client session while the registry is unreachable."""


class RegistryLink:
    """What one deployment (`deployment` of `cfg`) does with the registry. `seen` is set while
    a registry is alive; `stop` ends the retries of `open_session`."""

    def __init__(self, cfg: FleetConfig, deployment: str, stop: threading.Event) -> None:
        self.cfg = cfg
        self.deployment = deployment
        self.seen = threading.Event()
        self._stop = stop

    def open_session(self) -> zenoh.Session | None:
        """The deployment's Zenoh session, or None if stopped while waiting for the registry."""
        endpoint = self.cfg.registry.endpoint
        mode = zenoh_settings(self.cfg, machine=self.deployment)["mode"]
        backoff_s = OPEN_RETRY_FIRST_S
        attempt = 0
        while not self._stop.is_set():
            attempt += 1
            try:
                session = open_session(self.cfg, machine=self.deployment)
            except UserError as exc:
                if mode != "client":
                    raise  # a peer opens without the registry: this is something else
                log.warning(
                    "%s: cannot reach the registry at %s (attempt %d): %s; retrying in %.1f s",
                    self.deployment,
                    endpoint,
                    attempt,
                    exc,
                    backoff_s,
                )
                if self._stop.wait(backoff_s):
                    return None
                backoff_s = min(backoff_s * 2, OPEN_RETRY_MAX_S)
                continue
            if not list(session.info.routers_zid()):
                log.warning(
                    "%s: the registry at %s is not reachable yet; serving probes and ctl "
                    "meanwhile (Zenoh keeps retrying in the background with backoff)",
                    self.deployment,
                    endpoint,
                )
            return session
        return None

    def on_change(self, change: MemberChange) -> None:
        """The registry membership's listener."""
        if change.alive:
            self.seen.set()
            log.info("%s: registry %s is up", self.deployment, change.id)
            return
        if not change.alive_ids:
            self.seen.clear()
        log.warning(
            "%s: registry %s is gone; robots keep their current routes meanwhile",
            self.deployment,
            change.id,
        )

    def drain(self, session: zenoh.Session) -> bool:
        """Ask the registry to move this deployment's robots (bounded by DRAIN_TIMEOUT_S) and
        log its answer; True if it moved them all."""
        request = DrainRequest(deployment=self.deployment, reason="planned shutdown (SIGTERM)")
        started = time.monotonic()
        answer = self._ask_drain(session, request)
        took_ms = (time.monotonic() - started) * 1000
        if isinstance(answer, DrainReply) and answer.ok:
            log.info(
                "%s: the registry moved %s in %.0f ms",
                self.deployment,
                ", ".join(answer.moved) or "no robot",
                took_ms,
            )
            return True
        if answer is not None:
            reason = answer.reason
            log.warning("%s: the registry could not move every robot: %s", self.deployment, reason)
        else:
            log.warning(
                "%s: no registry answered the drain request (waited %.0f ms, at most %.1f s); "
                "exiting anyway",
                self.deployment,
                took_ms,
                DRAIN_TIMEOUT_S,
            )
        return False

    def _ask_drain(
        self, session: zenoh.Session, request: DrainRequest
    ) -> DrainReply | ErrorReply | None:
        """The first reply that decodes, or None (no answer in time, or the get failed)."""
        try:
            replies = session.get(
                keys.reg_drain(self.cfg.fleet),
                payload=request.to_wire(),
                timeout=DRAIN_TIMEOUT_S,
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    message = decode(reply.ok.payload.to_bytes(), expect=(DrainReply, ErrorReply))
                except WireError as exc:
                    log.warning("%s: bad drain reply from the registry: %s", self.deployment, exc)
                    continue
                assert isinstance(message, (DrainReply, ErrorReply))
                return message
        except zenoh.ZError as exc:
            log.warning("%s: drain request failed: %s", self.deployment, zenoh_error_text(exc))
        return None
