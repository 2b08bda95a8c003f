"""A cloud daemon's probe key `dep/<id>/probe`: its profile, and an echo of the size asked for.

The registry compares deployments by their probe replies, so a probe is delayed like every
inference reply (`delay_ms`) and a stalled deployment does not answer it; it is never dropped.
An empty probe asks for the profile alone; a `ProbeRequest` carries padding up and asks for
`echo_bytes` bytes back, so the prober can measure transfer both ways. A probe over the
request limit, or asking for more echo than the deployment's cap (`cloudd.limits`), gets a
`too_large` error reply and is counted (`cloudd.refusals`): a probe cannot make the deployment
send back an arbitrarily large payload. A deployment serving several services answers with the
profile of the one the request names (`ProbeRequest.service`; none, or an empty probe: the
fleet's first service); one it does not serve gets a named `unknown_service` error reply
(`cloudd.planes`).
"""

from __future__ import annotations

from collections.abc import Callable

import zenoh

from cloudd.faults import FaultInjector
from cloudd.limits import CloudLimits
from cloudd.refusals import RefusalReason, Refusals, decode_refusal
from cloudd.replies import Replier, query_payload
from common.throttled_log import ThrottledLog
from common.wire import ErrorReply, WireError, error_reply
from common.wire.registry import ProbeReply, ProbeRequest


class ProbeResponder:
    """Answers the probe key with `profile(service, echo_bytes)` (the named service's profile,
    or an error reply), under the injected faults."""

    def __init__(
        self,
        deployment: str,
        *,
        key: str,
        profile: Callable[[str | None, int], ProbeReply | ErrorReply],
        faults: FaultInjector,
        replies: Replier,
        limits: CloudLimits,
        refusals: Refusals,
        throttled: ThrottledLog,
    ) -> None:
        self.deployment = deployment
        self.key = key
        self._profile = profile
        self._faults = faults
        self._replies = replies
        self._limits = limits
        self._refusals = refusals
        self._throttled = throttled

    def on_query(self, query: zenoh.Query) -> None:
        """The probe queryable's callback."""
        fault = self._faults.get()
        if fault.stall:
            self._replies.hold(query)
            return
        delay_s = fault.delay_ms / 1000.0
        payload = query_payload(query)
        echo_bytes = 0
        service: str | None = None
        if payload:  # an empty probe asks for the profile alone
            try:
                request = ProbeRequest.from_wire(payload, max_bytes=self._limits.request_bytes)
            except WireError as exc:
                self._refusals.count(decode_refusal(exc))
                self._throttled.warning("%s: bad probe request: %s", self.deployment, exc.reason)
                self._replies.send(query, self.key, error_reply(exc), delay_s)
                return
            refusal = self._limits.echo_refusal(request)
            if refusal is not None:
                self._refusals.count(RefusalReason.ECHO_TOO_LARGE)
                self._throttled.warning(
                    "%s: bad probe request from %s: %s",
                    self.deployment,
                    request.sender,
                    refusal.reason,
                )
                self._replies.send(query, self.key, refusal.to_wire(), delay_s)
                return
            echo_bytes, service = request.echo_bytes, request.service
        reply = self._profile(service, echo_bytes)
        self._replies.send(query, self.key, reply.to_wire(), delay_s)
