"""The registry's Zenoh side of the switch protocol, and the probe it registers deployments with.

`ZenohTransport` implements `registry.switch.SwitchTransport` over a Zenoh session:

- `send_ctl` is a get on `ef/<fleet>/dep/<id>/ctl` carrying a `CtlRequest`; the first reply is
  decoded strictly as a `CtlReply`. An `ErrorReply` from the deployment (it could not even read
  the request) becomes a refusal carrying its code and reason, so the switch records it and moves
  on to the next candidate. No reply within the timeout is None (the switch's "timeout").
- `publish_route` puts a `RouteChange` on `ef/<fleet>/route/<robot>`.
- `probe` is a get on `ef/<fleet>/dep/<id>/probe`: the deployment's registration information
  (protocol version, capabilities, service, model digest, per-robot states, load and capacity).

Every network or decoding failure is a `TransportError` whose message names the deployment and
the problem; nothing here raises anything else for what comes off the wire.
"""

from __future__ import annotations

import zenoh

from common import keys
from common.session import zenoh_error_text
from common.wire import ErrorReply, Message, WireError, decode
from common.wire.registry import CtlReply, CtlRequest, ProbeReply, ProbeRequest, RouteChange
from registry.switch import TransportError

# Replies from deployments are small (states of a few robots, no echo asked): bigger ones are
# refused before unpacking.
MAX_REPLY_BYTES = 1024 * 1024


class ZenohTransport:
    """`SwitchTransport` over Zenoh for one fleet (the session is the caller's to close)."""

    def __init__(
        self, session: zenoh.Session, fleet: str, *, max_reply_bytes: int = MAX_REPLY_BYTES
    ) -> None:
        self.session = session
        self.fleet = fleet
        self.max_reply_bytes = max_reply_bytes

    def send_ctl(self, deployment: str, request: CtlRequest, timeout_s: float) -> CtlReply | None:
        """Send `request` to the deployment's ctl key; its reply, or None after `timeout_s`."""
        what = f"ctl {request.op.value} to {deployment}"
        key = keys.dep_ctl(self.fleet, deployment)
        message = self._ask(key, request.to_wire(), what, timeout_s, (CtlReply, ErrorReply))
        if message is None or isinstance(message, CtlReply):
            return message
        assert isinstance(message, ErrorReply)
        # The deployment could not act on the request; a refusal without an epoch of its own.
        return CtlReply(
            ok=False,
            deployment=deployment,
            op=request.op,
            robot=request.robot,
            epoch=0,
            state=None,
            reason=f"error reply {message.code}: {message.reason}",
        )

    def publish_route(self, change: RouteChange) -> None:
        """Publish a route change on the robot's route key."""
        try:
            self.session.put(keys.route(self.fleet, change.robot), change.to_wire())
        except zenoh.ZError as exc:
            raise TransportError(
                f"cannot publish the route of {change.robot}: {zenoh_error_text(exc)}"
            ) from None

    def probe(self, deployment: str, request: ProbeRequest, timeout_s: float) -> ProbeReply | None:
        """The deployment's probe reply, or None after `timeout_s` without one. An error reply
        (the deployment refused the probe) is a TransportError naming its reason."""
        what = f"probe of {deployment}"
        key = keys.dep_probe(self.fleet, deployment)
        message = self._ask(key, request.to_wire(), what, timeout_s, (ProbeReply, ErrorReply))
        if message is None or isinstance(message, ProbeReply):
            return message
        assert isinstance(message, ErrorReply)
        raise TransportError(f"{what}: error reply {message.code}: {message.reason}")

    def _ask(
        self,
        key: str,
        payload: bytes,
        what: str,
        timeout_s: float,
        expected: tuple[type[Message], ...],
    ) -> Message | None:
        """The first reply to a get on `key`, decoded as one of `expected` (None: no reply)."""
        try:
            replies = self.session.get(key, payload=payload, timeout=timeout_s)
            for reply in replies:
                if reply.ok is None:
                    text = reply.err.payload.to_string() if reply.err is not None else "unknown"
                    raise TransportError(f"{what}: error reply: {text}")
                return decode(
                    reply.ok.payload.to_bytes(), expect=expected, max_bytes=self.max_reply_bytes
                )
        except zenoh.ZError as exc:
            raise TransportError(f"{what}: {zenoh_error_text(exc)}") from None
        except WireError as exc:
            raise TransportError(f"{what}: bad reply: {exc}") from None
        return None
