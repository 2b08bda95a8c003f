"""A cloud daemon's probe key `dep/<id>/probe`: its profile, and an echo of the size asked for.

The registry compares deployments by their probe replies, so a probe is delayed like every
inference reply (`delay_ms`) and a stalled deployment does not answer it; it is never dropped.
An empty probe asks for the profile alone; a `ProbeRequest` carries padding up and asks for
`echo_bytes` bytes back, so the prober can measure transfer both ways.
"""

from __future__ import annotations

from collections.abc import Callable

import zenoh

from cloudd.faults import FaultInjector
from cloudd.replies import Replier, query_payload
from common.throttled_log import ThrottledLog
from common.wire import WireError, error_reply
from common.wire.registry import ProbeReply, ProbeRequest


class ProbeResponder:
    """Answers the probe key with `profile(echo_bytes)`, under the injected faults."""

    def __init__(
        self,
        deployment: str,
        *,
        key: str,
        profile: Callable[[int], ProbeReply],
        faults: FaultInjector,
        replies: Replier,
        max_payload_bytes: int,
        throttled: ThrottledLog,
    ) -> None:
        self.deployment = deployment
        self.key = key
        self._profile = profile
        self._faults = faults
        self._replies = replies
        self._max_payload_bytes = max_payload_bytes
        self._throttled = throttled

    def on_query(self, query: zenoh.Query) -> None:
        """The probe queryable's callback."""
        fault = self._faults.get()
        if fault.stall:
            self._replies.hold(query)
            return
        payload = query_payload(query)
        echo_bytes = 0
        if payload:  # an empty probe asks for the profile alone
            try:
                request = ProbeRequest.from_wire(payload, max_bytes=self._max_payload_bytes)
            except WireError as exc:
                self._throttled.warning("%s: bad probe request: %s", self.deployment, exc.reason)
                self._replies.send(query, self.key, error_reply(exc), fault.delay_ms / 1000.0)
                return
            echo_bytes = request.echo_bytes
        reply = self._profile(echo_bytes)
        self._replies.send(query, self.key, reply.to_wire(), fault.delay_ms / 1000.0)
